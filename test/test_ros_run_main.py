"""`make run` (deepprompt_ros.run_main) as a real process over DDS (localhost discovery, random
domain): the demo's nodes (deepprompt_ros.bringup) start with their default parameters, the server
serves every primitive of the robot's primitives file without a refusal (the Gen3 lite by default,
and the WAM with --robot wam), robot_state_publisher is skipped with one line where it is not
installed, and Ctrl-C stops everything cleanly."""
import sys

import pytest
from deepprompt_msgs.srv import ListPrimitives

from deepprompt_ros import bringup
from deepprompt_ros.ros.testing import NodeProcess, RosTestClient, isolated_ros_env


@pytest.mark.parametrize("robot, options, primitive, sim_line", [
    ("gen3_lite", [], "reach", "robot gen3_lite (joint_1..joint_6), 1000 Hz"),
    ("wam", ["--robot", "wam"], "shake", "robot wam (wam_j1..wam_j7), 500 Hz"),
])
def test_make_run_serves_the_robots_primitives_without_refusal(tmp_path, robot, options, primitive, sim_line):
    env = isolated_ros_env(tmp_path / "log")
    proc = NodeProcess([sys.executable, "-m", "deepprompt_ros.run_main", *options], env, tmp_path / "run.log")
    try:
        with RosTestClient(env) as client:
            service = "/primitive_server/list_primitives"
            assert client.wait_for_service(ListPrimitives, service, 120.0), proc.output_tail()
            res = client.call(ListPrimitives, service, ListPrimitives.Request(), timeout=30.0)
            assert res.success and [p.name for p in res.primitives] == [primitive], res.message
            assert client.wait_for(lambda: f"serving 1 primitive(s) [{primitive}] for robot '{robot}'" in proc.output(),
                                   30.0), proc.output_tail()
        out = proc.output()
        assert sim_line in out, proc.output_tail()  # the sim of the demo
        assert "refused" not in out and "Traceback" not in out, out
    finally:
        rc = proc.stop(sigint_timeout=20.0)  # run_main stops its nodes first
    assert rc == 0, proc.output_tail()
    assert "[run] started sim_bridge" in proc.output() and "[run] started primitive_server" in proc.output()
    # the environment of run_main is this one's: the same robot_state_publisher (or none) is found
    installed = bringup.find_executable("robot_state_publisher", "robot_state_publisher") is not None
    rsp_line = "[run] started robot_state_publisher" if installed else "[run] robot_state_publisher skipped: "
    assert rsp_line in proc.output(), proc.output_tail()
