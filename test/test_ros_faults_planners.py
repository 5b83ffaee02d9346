"""Two planners at once, each a process of its own, over real DDS (LOCALHOST discovery, random
domain) against one primitive_server (shipped ``config/primitive_server.yaml``, stale_timeout raised
to 1 s) and sim_bridge.

Both start at the same moment; in each round a planner conditions the reach on a via-point of its
own (refined) and executes it, then pauses a random while, so their goals overlap and preempt each
other. Checked: every Condition answer is the answer to that planner's request (its preview passes
through that planner's via-point with the error it reports; handles all distinct); every goal ends
SUCCESS (status SUCCEEDED, phase 1) or PREEMPTED (status ABORTED, "preempted by a newer Execute
goal"): each PREEMPTED one by a goal accepted after it, each SUCCESS one with none accepted while it
ran (the order of acceptance decides, not the order in which the server finished planning them); and
the command stream is continuous within the limits across every splice.

Run as ``python test/test_ros_faults_planners.py planner <name> <seed> <rounds> <folder> <duration>``
this file is one planner (what the test starts twice): it writes ``<folder>/<name>.ready`` once it has
found the server, starts when ``<folder>/go`` exists, sends goals of ``<duration>`` s and writes its
results to ``<folder>/<name>.jsonl``.
"""
from __future__ import annotations

import json
import sys
import time

import numpy as np

RESULT_SUCCEEDED, RESULT_ABORTED = 4, 6  # action_msgs/GoalStatus
SRV = "/primitive_server"


# ------------------------------------------------------------------------------------------------
# one planner (a process of its own)
# ------------------------------------------------------------------------------------------------
def planner_main(name: str, seed: int, rounds: int, folder: str, duration: float) -> int:
    """``rounds`` x (Condition with a via-point, Execute of ``duration`` s, a random pause), starting
    when the file ``go`` appears in ``folder``; one JSON line per Condition and per goal into
    ``<name>.jsonl``."""
    import pathlib

    import rclpy
    from deepprompt_msgs.action import Execute
    from deepprompt_msgs.srv import Condition
    from rclpy.action import ActionClient

    from deepprompt_ros.ros import conversions as conv

    rng = np.random.default_rng(seed)
    rclpy.init()
    node = rclpy.create_node(f"planner_{name}")
    cond = node.create_client(Condition, f"{SRV}/condition")
    act = ActionClient(node, Execute, f"{SRV}/execute")

    def wait(fut, timeout):
        rclpy.spin_until_future_complete(node, fut, timeout_sec=timeout)
        if not fut.done():
            raise TimeoutError(f"planner {name}: no answer within {timeout} s")
        return fut.result()

    lines = []
    try:
        assert cond.wait_for_service(timeout_sec=60.0) and act.wait_for_server(timeout_sec=60.0)
        prior = wait(cond.call_async(Condition.Request(primitive="reach", preview_points=101)), 30)
        mean = conv.preview_from_msg(prior.preview).mean
        (pathlib.Path(folder) / f"{name}.ready").touch()
        while not (pathlib.Path(folder) / "go").exists():
            time.sleep(0.005)
        for i in range(rounds):
            target = mean[50] + rng.uniform(-0.015, 0.015, size=mean.shape[1])
            req = Condition.Request(primitive="reach", refine=True, preview_points=101,
                                    via_points=conv.via_points_to_msgs([0.5], [target]))
            r = wait(cond.call_async(req), 30)
            got = conv.preview_from_msg(r.preview).mean[50] if r.success else None
            lines.append({"kind": "condition", "planner": name, "round": i, "success": r.success,
                          "message": r.message, "handle": r.handle, "target": target.tolist(),
                          "preview_at_via": None if got is None else got.tolist(),
                          "refine_max_error": r.refine_max_error, "reachable": r.reachable})
            if not r.success:
                continue
            t_send = time.time()
            gh = wait(act.send_goal_async(Execute.Goal(handle=r.handle, duration=duration)), 30)
            t_accept = time.time()
            res = wait(gh.get_result_async(), 60)
            lines.append({"kind": "goal", "planner": name, "round": i, "accepted": gh.accepted,
                          "t_send": t_send, "t_accept": t_accept, "t_result": time.time(), "status": res.status,
                          "code": res.result.code.value, "message": res.result.message,
                          "final_phase": res.result.final_phase})
            time.sleep(rng.uniform(0.0, 1.0))
    finally:
        with open(pathlib.Path(folder) / f"{name}.jsonl", "w") as f:
            f.writelines(json.dumps(line) + "\n" for line in lines)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__" and len(sys.argv) == 7 and sys.argv[1] == "planner":
    sys.exit(planner_main(sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5], float(sys.argv[6])))


# ------------------------------------------------------------------------------------------------
# the test
# ------------------------------------------------------------------------------------------------
import pytest  # noqa: E402
from deepprompt_msgs.msg import ResultCode  # noqa: E402

from deepprompt_ros.execution.limits import check_limits  # noqa: E402
from deepprompt_ros.robots.spec import load_robot  # noqa: E402
from deepprompt_ros.ros.testing import JointStateTap, NodeProcess, RosTestClient  # noqa: E402
from deepprompt_ros.server.config import ServerConfig, robot_limits  # noqa: E402
from served_reach import reach_timing  # noqa: E402

SPEC = load_robot("gen3_lite")
LIMITS = robot_limits(SPEC, ServerConfig())
DT = 1e-3
ROUNDS = 3


@pytest.fixture(scope="module")
def nodes(ros_env, repo_root):
    procs = {}
    try:
        procs["sim"] = NodeProcess.start_module("deepprompt_ros.ros.sim_bridge", ros_env, params={
            "camera.enabled": False, "publish_clock": False, "rate_hz": 250.0})
        procs["server"] = NodeProcess.start_module("deepprompt_ros.ros.primitive_server", ros_env,
                                                   params_files=[repo_root / "config" / "primitive_server.yaml"],
                                                   params={"stale_timeout": 1.0})
        yield procs
    finally:
        for p in procs.values():
            p.stop()


def assert_segments_ok(stamps, q, qd):
    """Split where the stream paused at rest (a goal ended; the next one starts from the measured
    state); within each piece every consecutive pair of commands within the limits, splices included;
    the stream ends at rest. Returns the number of pieces."""
    assert np.all(np.isfinite(q)) and np.all(np.isfinite(qd)) and np.all(np.diff(stamps) > 0)
    at_rest = np.all(qd == 0.0, axis=1)
    cuts = np.flatnonzero((np.diff(stamps) > 5_000_000) & at_rest[:-1]) + 1
    for seg in np.split(np.arange(len(stamps)), cuts):
        rep = check_limits(q[seg], qd[seg], None, DT, LIMITS)  # accelerations: from the velocities
        assert rep.ok(rtol=1e-6), rep
    assert at_rest[-1], "the stream ends moving"
    return len(cuts) + 1


def test_two_planners_condition_and_execute_at_once(ros_env, nodes, tmp_path):
    server = nodes["server"]
    with RosTestClient(ros_env) as client:
        tap = JointStateTap(client, "joint_command")
        # the planners' goal duration: executable within the velocity limits for every via-point drawn (they
        # lie within 0.015 rad of the prior mean, which the ordinary margin over its shortest duration covers)
        duration = reach_timing(client, timeout=60.0).ordinary  # (the server may still be starting)
        assert client.wait_for(tap.matched, 60), server.output_tail()  # the control process's command publisher
        planners = {}
        try:
            for name, seed in (("a", 1), ("b", 2)):
                planners[name] = NodeProcess([sys.executable, __file__, "planner", name, str(seed), str(ROUNDS),
                                              str(tmp_path), str(duration)], ros_env, tmp_path / f"planner_{name}.log")
            assert client.wait_for(lambda: all((tmp_path / f"{n}.ready").exists() or not p.running()
                                               for n, p in planners.items()), 60), server.output_tail()
            (tmp_path / "go").touch()  # both at once
            end = time.monotonic() + 90.0
            while any(p.running() for p in planners.values()) and time.monotonic() < end:
                client.spin_for(0.05)
                tap.take()
            for name, p in planners.items():
                assert p.returncode == 0, p.output_tail() + server.output_tail()
        finally:
            for p in planners.values():
                p.stop()
        client.spin_for(0.3)
        tap.take()
        stamps, q, qd = tap.arrays(SPEC.joint_names)
        tap.close()
    lines = [json.loads(line) for name in planners for line in (tmp_path / f"{name}.jsonl").read_text().splitlines()]
    conds = [x for x in lines if x["kind"] == "condition"]
    goals = [x for x in lines if x["kind"] == "goal"]
    assert len(conds) == 2 * ROUNDS and len(goals) == 2 * ROUNDS, lines

    # every Condition answer belongs to its request
    for c in conds:
        assert c["success"], c
        err = np.abs(np.array(c["preview_at_via"]) - c["target"]).max()
        assert err == pytest.approx(c["refine_max_error"], abs=1e-9), c
        assert c["reachable"] == (err <= 1e-6), c
    assert len({c["handle"] for c in conds}) == len(conds)

    # every goal ends with a clear code consistent with the other planner's goals
    for g in goals:
        assert g["accepted"], g
        others = [o for o in goals if o is not g]
        # accepted after g while g ran (the acceptance times of two processes: 50 ms of slack for their order)
        overlapped = any(g["t_accept"] + 0.05 < o["t_accept"] < g["t_result"] - 0.1 for o in others)
        newer = any(g["t_accept"] - 0.05 < o["t_accept"] < g["t_result"] + 0.1 for o in others)
        if g["code"] == ResultCode.SUCCESS:
            assert g["status"] == RESULT_SUCCEEDED and g["final_phase"] == 1.0, g
            assert not overlapped, ("a goal accepted during this one did not preempt it", g, others)
        else:
            assert g["code"] == ResultCode.PREEMPTED and g["status"] == RESULT_ABORTED, g
            assert "preempted by a newer Execute goal" in g["message"], g
            assert newer, ("preempted with no newer goal", g, others)
    codes = [g["code"] for g in goals]
    assert ResultCode.PREEMPTED in codes and ResultCode.SUCCESS in codes, codes
    n = assert_segments_ok(stamps, q, qd)
    print(f"{codes.count(ResultCode.PREEMPTED)} preempted, {codes.count(ResultCode.SUCCESS)} succeeded, "
          f"{len(stamps)} commands in {n} segment(s)")
    assert "Traceback" not in server.output()
