"""Bursts of requests to primitive_server, real processes over real DDS (LOCALHOST discovery, random
domain): the shipped ``config/primitive_server.yaml``, in both service modes (``fast_path`` true: the
services' own thread; false: the executor), no robot.

A client sends many requests at once (a planner replanning, several planners at a time): every one is
answered. The server's services and the Execute action's goal and result services keep the last 100
requests and responses (``primitive_server.SERVICE_QOS``): a keep-last reader of depth 10, rmw's
default, drops the oldest unanswered requests of a larger burst without a trace. The clients here
keep 1000 so that only the server's side is tested.
"""
from __future__ import annotations

import pytest
from deepprompt_msgs.action import Execute
from deepprompt_msgs.msg import ResultCode
from deepprompt_msgs.srv import Condition, ListPrimitives
from rclpy.action import ActionClient
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from deepprompt_ros.ros.primitive_server import SERVICE_QOS
from deepprompt_ros.ros.testing import NodeProcess, RosTestClient

SRV = "/primitive_server"
#: more requests at once than rmw's default depth (10), fewer than the server's (100)
BURST = 80
CLIENT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE)


@pytest.fixture(scope="module", params=[True, False], ids=["fast_path", "plain_rclpy"])
def client(request, ros_env, repo_root):
    with NodeProcess.start_module("deepprompt_ros.ros.primitive_server", ros_env,
                                  params_files=[repo_root / "config" / "primitive_server.yaml"],
                                  params={"fast_path": request.param}) as server:
        with RosTestClient(ros_env) as c:
            c.server = server
            c.condition = c.node.create_client(Condition, f"{SRV}/condition", qos_profile=CLIENT_QOS)
            c.list = c.node.create_client(ListPrimitives, f"{SRV}/list_primitives", qos_profile=CLIENT_QOS)
            c.ac = ActionClient(c.node, Execute, f"{SRV}/execute", goal_service_qos_profile=CLIENT_QOS,
                                result_service_qos_profile=CLIENT_QOS, cancel_service_qos_profile=CLIENT_QOS)
            assert c.wait_for(lambda: c.condition.service_is_ready() and c.list.service_is_ready()
                              and c.ac.server_is_ready(), 60), server.output_tail()
            c.spin_for(0.5)  # every endpoint of the server matched
            yield c
            c.ac.destroy()


def test_the_server_keeps_more_requests_than_a_burst():
    assert SERVICE_QOS.depth >= 100 and SERVICE_QOS.depth > BURST
    assert SERVICE_QOS.history == HistoryPolicy.KEEP_LAST and SERVICE_QOS.reliability == ReliabilityPolicy.RELIABLE


def test_a_burst_of_service_requests_is_answered_in_full(client):
    for srv_client, req, answered in (
            (client.condition, Condition.Request(primitive="reach", preview_points=50),
             lambda r: r.success and r.handle and r.preview.n_points == 50),
            (client.list, ListPrimitives.Request(), lambda r: r.success and [p.name for p in r.primitives])):
        futs = [srv_client.call_async(req) for _ in range(BURST)]
        client.wait_for(lambda: all(f.done() for f in futs), 60)
        done = sum(f.done() for f in futs)
        assert done == BURST, f"{done} of {BURST} {srv_client.srv_name} requests answered"
        assert all(answered(f.result()) for f in futs), [f.result().message for f in futs if not answered(f.result())]
        if srv_client is client.condition:  # every Condition stored its own distribution
            handles = {f.result().handle for f in futs}
            assert len(handles) == BURST, f"{len(handles)} distinct handles for {BURST} Condition requests"


def test_a_burst_of_execute_goals_gets_every_goal_response_and_every_result(client):
    """No robot runs: every goal is accepted and ends with ROBOT_STATE_STALE (or PREEMPTED by a newer
    one), each with its result."""
    r = client.condition.call_async(Condition.Request(primitive="reach"))
    assert client.wait_for(r.done, 20) and r.result().success, r.result().message if r.done() else "no answer"
    handle = r.result().handle
    # a duration far above the shortest the velocity limits allow for the reach (the demonstrations' speed
    # needs a few seconds): the plan is made, and no robot runs, so no goal lasts that long
    sent = [client.ac.send_goal_async(Execute.Goal(handle=handle, duration=30.0)) for _ in range(BURST)]
    client.wait_for(lambda: all(f.done() for f in sent), 60)
    done = sum(f.done() for f in sent)
    assert done == BURST, f"{done} of {BURST} goal requests answered"
    assert all(f.result().accepted for f in sent)
    results = [f.result().get_result_async() for f in sent]
    client.wait_for(lambda: all(f.done() for f in results), 60)
    done = sum(f.done() for f in results)
    assert done == BURST, f"{done} of {BURST} results received"
    codes = {f.result().result.code.value for f in results}
    assert codes <= {ResultCode.ROBOT_STATE_STALE, ResultCode.PREEMPTED}, [f.result().result.message for f in results]
