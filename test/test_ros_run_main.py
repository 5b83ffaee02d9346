"""`make run` (deepprompt_ros.run_main) as a real process over DDS (localhost discovery, random
domain): the demo's nodes (deepprompt_ros.bringup) start with their default parameters, the server
serves every primitive of the default primitives file on the default robot without a refusal, and
Ctrl-C stops everything cleanly."""
import sys

from deepprompt_msgs.srv import ListPrimitives

from deepprompt_ros.ros.testing import NodeProcess, RosTestClient, isolated_ros_env


def test_make_run_serves_the_default_primitives_without_refusal(tmp_path):
    env = isolated_ros_env(tmp_path / "log")
    proc = NodeProcess([sys.executable, "-m", "deepprompt_ros.run_main"], env, tmp_path / "run.log")
    try:
        with RosTestClient(env) as client:
            service = "/primitive_server/list_primitives"
            assert client.wait_for_service(ListPrimitives, service, 120.0), proc.output_tail()
            res = client.call(ListPrimitives, service, ListPrimitives.Request(), timeout=30.0)
            assert res.success and [p.name for p in res.primitives] == ["reach"], res.message
            assert client.wait_for(lambda: "serving 1 primitive(s) [reach]" in proc.output(), 30.0), proc.output_tail()
        out = proc.output()
        assert "robot gen3_lite (joint_1..joint_6), 1000 Hz" in out, proc.output_tail()  # the sim of the demo
        assert "refused" not in out and "Traceback" not in out, out
    finally:
        rc = proc.stop(sigint_timeout=20.0)  # run_main stops its nodes first
    assert rc == 0, proc.output_tail()
    assert "[run] started sim_bridge" in proc.output() and "[run] started primitive_server" in proc.output()
