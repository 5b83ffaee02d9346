"""ros/fastpath/service_client.py: a client on the node itself (listed by the graph as that node's)
whose caller waits for the response on its own wait set, with no executor spinning the client's
node; a call without an answer raises TimeoutError, and the late answer to it is dropped, not
returned to the next call. A tiny service in the test process (a second node, spun by an executor
in a thread of its own) on an isolated network (LOCALHOST discovery, random domain)."""
import threading
import time

import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from std_srvs.srv import SetBool

from deepprompt_ros.ros.fastpath.service_client import BlockingClient
from deepprompt_ros.ros.testing import RosTestClient, isolated_ros_env


@pytest.fixture
def client(tmp_path):
    with RosTestClient(isolated_ros_env(tmp_path / "log"), "service_client_test") as c:
        yield c


@pytest.fixture
def service(client):
    """A SetBool service '/tiny/set' answering "answer <n>" to its n-th request; a request with
    data=True is answered only after 1.5 s. Yields the list of requests received (their data)."""
    received = []

    def handle(request, response):
        received.append(request.data)
        if request.data:
            time.sleep(1.5)
        response.success, response.message = True, f"answer {len(received)}"
        return response

    node = rclpy.create_node("tiny", context=client.context)
    node.create_service(SetBool, "~/set", handle)
    executor = SingleThreadedExecutor(context=client.context)
    executor.add_node(node)
    stop = threading.Event()

    def spin():
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.05)

    thread = threading.Thread(target=spin, daemon=True)
    thread.start()
    try:
        yield received
    finally:
        stop.set()
        thread.join(5.0)
        executor.shutdown()
        node.destroy_node()


def test_a_call_returns_its_response_taken_in_the_calling_thread(client, service):
    cli = BlockingClient(client.node, SetBool, "/tiny/set")
    try:
        assert cli.wait_for_service(10.0)
        for n in (1, 2, 3):
            r = cli.call(SetBool.Request(data=False), timeout=10.0)
            assert r.success and r.message == f"answer {n}"
        assert service == [False] * 3
        clients = dict(client.node.get_client_names_and_types_by_node("service_client_test", "/"))
        assert clients["/tiny/set"] == ["std_srvs/srv/SetBool"]  # the node's own client
        client.spin_for(0.3)  # the node's executor leaves the client alone
        assert cli.call(SetBool.Request(data=False), timeout=10.0).message == "answer 4"
    finally:
        cli.destroy()
    assert client.wait_for(lambda: "/tiny/set" not in dict(
        client.node.get_client_names_and_types_by_node("service_client_test", "/")), 5.0)


def test_no_response_in_time_raises_and_the_late_response_is_not_taken_for_the_next(client, service):
    cli = BlockingClient(client.node, SetBool, "/tiny/set")
    try:
        assert cli.wait_for_service(10.0)
        t0 = time.monotonic()
        with pytest.raises(TimeoutError, match=r"no /tiny/set response within 0.5 s"):
            cli.call(SetBool.Request(data=True), timeout=0.5)  # answered after 1.5 s
        assert time.monotonic() - t0 >= 0.5
        # served after the slow one: its answer ("answer 1") arrives first and is dropped
        r = cli.call(SetBool.Request(data=False), timeout=10.0)
        assert r.message == "answer 2" and service == [True, False]
    finally:
        cli.destroy()


def test_a_service_nobody_serves(client):
    cli = BlockingClient(client.node, SetBool, "/nobody/set")
    try:
        assert not cli.wait_for_service(0.5)
        with pytest.raises(TimeoutError, match="no /nobody/set response within 0.3 s"):
            cli.call(SetBool.Request(data=False), timeout=0.3)
    finally:
        cli.destroy()
