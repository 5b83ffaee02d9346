"""ros/fastpath/service_thread.py: services on the node itself (listed by the graph as that node's),
answered by their own thread while the node's executor never dispatches them; a callback's
exception is logged and the thread keeps serving; the reception-to-taking time is reported; stop
ends the thread. One in-process node on an isolated network (LOCALHOST discovery, random domain)."""
import threading
import time

import pytest
from std_srvs.srv import SetBool, Trigger

from deepprompt_ros.ros.fastpath.service_thread import ServiceThread
from deepprompt_ros.ros.testing import RosTestClient, isolated_ros_env


@pytest.fixture
def client(tmp_path):
    with RosTestClient(isolated_ros_env(tmp_path / "log"), "service_thread_test") as c:
        yield c


def test_requests_are_answered_by_the_service_thread(client):
    threads, queued = [], []

    def set_bool(request, response):
        threads.append(threading.current_thread().name)
        if request.data:
            raise RuntimeError("refused on purpose")
        response.success, response.message = True, "done"
        return response

    def trigger(request, response):
        threads.append(threading.current_thread().name)
        response.success = True
        return response

    srv = ServiceThread(client.node, "test_services", on_queued=queued.append)
    srv.create_service(SetBool, "~/set", set_bool)
    srv.create_service(Trigger, "~/trigger", trigger)
    srv.start()
    with pytest.raises(RuntimeError, match="before ServiceThread.start"):
        srv.create_service(Trigger, "~/late", trigger)
    rtt = []  # s of each call, from before its request to after its answer (or its timeout)

    def timed(*args, **kwargs):
        t0 = time.monotonic()
        try:
            return client.call(*args, **kwargs)
        finally:
            rtt.append(time.monotonic() - t0)

    try:
        r = timed(SetBool, "/service_thread_test/set", SetBool.Request(data=False))
        assert r.success and r.message == "done"
        assert timed(Trigger, "/service_thread_test/trigger").success
        with pytest.raises(TimeoutError):  # the callback raised: no response, a warning
            timed(SetBool, "/service_thread_test/set", SetBool.Request(data=True), timeout=1.0)
        assert timed(SetBool, "/service_thread_test/set", SetBool.Request(data=False)).success  # still serving
        assert threads == ["test_services"] * 4  # never the executor (the test's own thread)
        # one reception-to-taking time per request, each part of that request's round trip
        assert len(queued) == 4 and all(0.0 <= q <= t for q, t in zip(queued, rtt)), (queued, rtt)
        services = dict(client.node.get_service_names_and_types_by_node("service_thread_test", "/"))
        assert services["/service_thread_test/set"] == ["std_srvs/srv/SetBool"]
        assert services["/service_thread_test/trigger"] == ["std_srvs/srv/Trigger"]
    finally:
        srv.stop(2.0)
    assert not srv._thread.is_alive()
