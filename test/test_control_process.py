"""primitive_server's control loop in a child process (loop_process: true, the default):
a crash of the child ends the running goal with INTERNAL_ERROR (no hang) and a new child takes
over; the child dies with the server (no orphan); the in-process mode (loop_process: false) still
executes. Real processes, real DDS (LOCALHOST discovery, random domain)."""
import os
import re
import signal
import time

import pytest
import yaml

from deepprompt_msgs.action import Execute
from deepprompt_msgs.msg import ResultCode
from deepprompt_msgs.srv import Condition
from rclpy.action import ActionClient

from deepprompt_ros.ros.testing import NodeProcess, RosTestClient, isolated_ros_env

from test_primitive_server_node import train_tiny_reach

SRV = "/primitive_server"
CHILD = re.compile(r"control loop running in its own process \(pid (\d+)\)")


def alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError):
        return False


def start(tmp, name, params):
    reach = tmp / "reach.safetensors"
    if not reach.exists():
        train_tiny_reach(reach)
    prims = tmp / "primitives.yaml"
    prims.write_text(yaml.safe_dump({"primitives": [{"name": "reach", "model": str(reach)}]}))
    env = isolated_ros_env(tmp / f"log_{name}")
    sim = NodeProcess.start_module("deepprompt_ros.ros.sim_bridge", env, params={
        "camera.enabled": False, "publish_clock": False})
    server = NodeProcess.start_module("deepprompt_ros.ros.primitive_server", env, params={
        "primitives_file": str(prims), "stale_timeout": 1.0, **params})
    return env, sim, server


def run_goal(client, ac, server, duration, feedback=None, before_result=None):
    r = client.call(Condition, f"{SRV}/condition", Condition.Request(primitive="reach"), timeout=20)
    assert r.success, r.message
    fut = ac.send_goal_async(Execute.Goal(handle=r.handle, duration=duration),
                             feedback_callback=(lambda m: feedback.append(m.feedback)) if feedback is not None else None)
    assert client.wait_for(fut.done, 10)
    gh = fut.result()
    assert gh.accepted
    res = gh.get_result_async()
    if before_result is not None:
        before_result(res)
    assert client.wait_for(res.done, 30), "no Execute result:\n" + server.output_tail()
    return res.result().result


@pytest.fixture(scope="module")
def nodes(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("control_process")
    env, sim, server = start(tmp, "child", {})
    try:
        with RosTestClient(env) as client:
            ac = ActionClient(client.node, Execute, f"{SRV}/execute")
            assert client.wait_for(ac.server_is_ready, 60), server.output_tail()
            assert client.wait_for(lambda: "receiving joint_states" in server.output(), 60), server.output_tail()
            yield dict(client=client, ac=ac, server=server, sim=sim, tmp=tmp)
            ac.destroy()
    finally:
        server.stop()
        sim.stop()


def test_child_crash_aborts_the_goal_and_a_new_child_takes_over(nodes):
    client, ac, server = nodes["client"], nodes["ac"], nodes["server"]
    assert client.wait_for(lambda: CHILD.search(server.output()), 30), server.output_tail()
    pid = int(CHILD.findall(server.output())[-1])
    assert alive(pid)
    fb = []

    def crash(res):
        assert client.wait_for(lambda: (fb and fb[-1].phase > 0.1) or res.done(), 20)
        assert not res.done(), res.result().result.message
        os.kill(pid, signal.SIGKILL)

    t0 = time.monotonic()
    res = run_goal(client, ac, server, 6.0, fb, crash)
    assert res.code.value == ResultCode.INTERNAL_ERROR and not res.success
    assert "exited unexpectedly" in res.message and str(pid) in res.message
    assert time.monotonic() - t0 < 6.0  # reported, not waited out
    assert client.wait_for(lambda: len(CHILD.findall(server.output())) >= 2, 30), server.output_tail()
    new = int(CHILD.findall(server.output())[-1])
    assert new != pid and alive(new) and "control process restarted" in server.output()
    # the new child streams: an execution succeeds
    assert client.wait_for(lambda: server.output().count("receiving joint_states") >= 2, 30), server.output_tail()
    res = run_goal(client, ac, server, 1.5)
    assert res.success, res.message


def test_child_dies_with_the_server(nodes):
    server = nodes["server"]
    pid = int(CHILD.findall(server.output())[-1])
    assert alive(pid)
    os.kill(server.pid, signal.SIGKILL)  # no chance to stop it
    end = time.monotonic() + 10
    while alive(pid) and time.monotonic() < end:
        time.sleep(0.05)
    assert not alive(pid), "control process outlived the server"


def test_in_process_loop_still_executes(tmp_path):
    env, sim, server = start(tmp_path, "inproc", {"loop_process": False})
    try:
        with RosTestClient(env) as client:
            ac = ActionClient(client.node, Execute, f"{SRV}/execute")
            assert client.wait_for(ac.server_is_ready, 60), server.output_tail()
            assert client.wait_for(lambda: "receiving joint_states" in server.output(), 60), server.output_tail()
            res = run_goal(client, ac, server, 1.5)
            assert res.success, res.message
            assert "in this process" in server.output() and not CHILD.search(server.output())
            ac.destroy()
    finally:
        server.stop()
        sim.stop()
