"""RosTestClient against a server process whose replies can be lost.

rmw_fastrtps drops a service reply when the server has not yet matched the client's reply reader
(ros2/rmw_fastrtps#390): the call then never returns. The server here reproduces that loss
deterministically: it takes requests itself and leaves the first ``N_DROPPED`` unanswered.

* a plain call whose reply is lost raises TimeoutError (it does not hang);
* ``call(resend_after=...)`` sends again and returns the first reply;
* ``wait_for_service(probe=...)`` returns only once the server has answered, and False when it
  never does within the timeout.
"""
from __future__ import annotations

import sys
import textwrap
import time

import pytest
from std_srvs.srv import SetBool

from deepprompt_ros.ros.testing import NodeProcess, RosTestClient

# Serves SetBool on the service named by the second argument, taking requests itself (no executor);
# answers request k (from 1) only when k > N_DROPPED (the first argument), with "answered k".
SERVER = textwrap.dedent("""
    import sys, time
    import rclpy
    from std_srvs.srv import SetBool
    n_dropped = int(sys.argv[1])
    rclpy.init()
    node = rclpy.create_node("lossy_server")
    srv = node.create_service(SetBool, sys.argv[2], lambda req, res: res)  # never spun: no executor answers
    print("serving", flush=True)
    k = 0
    while True:
        taken = srv.handle.service_take_request(SetBool.Request)
        if taken is None or taken[0] is None:
            time.sleep(0.005)
            continue
        k += 1
        if k > n_dropped:
            srv.send_response(SetBool.Response(success=True, message=f"answered {k}"), taken[1])
""")


@pytest.fixture
def client(ros_env):
    with RosTestClient(ros_env) as c:
        yield c


def start_server(env, tmp_path, n_dropped: int, name: str) -> NodeProcess:
    return NodeProcess([sys.executable, "-c", SERVER, str(n_dropped), name], env, tmp_path / f"{name}.log")


def test_a_lost_reply_is_a_timeout_and_a_resent_request_gets_the_next_reply(ros_env, client, tmp_path):
    with start_server(ros_env, tmp_path, 1, "drop_one") as server:
        assert client.wait_for_service(SetBool, "drop_one", 30.0), server.output_tail()
        t0 = time.monotonic()
        with pytest.raises(TimeoutError, match="did not answer within 1.5 s"):
            client.call(SetBool, "drop_one", SetBool.Request(data=True), timeout=1.5)
        assert 1.5 <= time.monotonic() - t0 < 5.0
        res = client.call(SetBool, "drop_one", SetBool.Request(data=True), timeout=10.0)  # the server's 2nd
        assert res.message == "answered 2"

    with start_server(ros_env, tmp_path, 2, "drop_two") as server:
        assert client.wait_for_service(SetBool, "drop_two", 30.0), server.output_tail()
        t0 = time.monotonic()
        res = client.call(SetBool, "drop_two", SetBool.Request(data=True), timeout=10.0, resend_after=0.5)
        assert res.message == "answered 3", server.output_tail()  # two lost, the third answered
        assert 1.0 <= time.monotonic() - t0 < 5.0


def test_a_probe_waits_for_an_answer_and_fails_when_none_comes(ros_env, client, tmp_path):
    with start_server(ros_env, tmp_path, 2, "probe_two") as server:
        assert client.wait_for_service(SetBool, "probe_two", 30.0, probe=SetBool.Request()), server.output_tail()
        assert client.call(SetBool, "probe_two", SetBool.Request(), timeout=10.0).message == "answered 4"

    with start_server(ros_env, tmp_path, 1000, "probe_never") as server:
        t0 = time.monotonic()
        assert not client.wait_for_service(SetBool, "probe_never", 4.0, probe=SetBool.Request())
        assert 4.0 <= time.monotonic() - t0 < 8.0, server.output_tail()
