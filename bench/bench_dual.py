"""Two arms streaming at once against one arm alone, in the same run: does a second robot's server
disturb the first one's command stream?

    python bench/bench_dual.py            # 30 s of stream per phase
    python bench/bench_dual.py --quick    # 2 s per phase (smoke run)

Processes: per arm a sim_bridge (PyBullet Gen3 lite, joint_states at 1 kHz) and a primitive_server
(with its control process) under the arm's namespace (``/arm_a``, ``/arm_b``; the nodes and
parameters of bench_ros.py, started with ``-r __ns:=/<arm>``), a stream subscriber per arm
(bench_ros.py's, SCHED_FIFO ``--subscriber-priority`` as a controller runs, started in the arm's
namespace), and this orchestrator, the one planner (an Execute action client per server). Both arms
are Gen3 lites serving the same reach, so that the two phases differ only by the second arm.

1. One arm alone: only ``/arm_a``'s nodes run; one long Execute goal; its subscriber records the
   joint_command arrivals for the phase's seconds.
2. Two arms: ``/arm_b``'s nodes start beside ``/arm_a``'s; both get one long goal at once, and both
   subscribers record the same seconds.

Each goal: a random context, no via-point (bench_ros.py's phase 1), ``RUN_THROUGH`` s longer than the
recording and at most 1/1.3 of the speed the velocity limits allow (its preview on the execution grid);
canceled once the recording ends.

Figures (last line), from the arrival instants as bench_ros.py measures them
(``bench_ros.stream_metrics``: ``stream_hz`` the commands per second, ``stream_missed`` the arrivals
more than 1.5 periods after the one before):

* ``dual_stream_hz_min`` -- the lower of the two arms' stream_hz in phase 2;
* ``dual_missed_ratio`` -- (the larger of the two arms' stream_missed in phase 2 + 1) / (stream_missed
  of the arm alone in phase 1 + 1): 1 when the second arm costs the first nothing;
* ``alone_stream_hz``, ``alone_missed`` and, per arm of phase 2, ``dual_<arm>_stream_hz``,
  ``dual_<arm>_missed``, ``dual_<arm>_p99_err_ms``; ``goals_through``: the goals (of 3) that were still
  running when the recording ended (canceled then; another result code, e.g. ROBOT_STATE_STALE after a
  paused simulation, ended a stream early and makes its figures not the stream's: 3 for figures to trust);
  ``foreign_nodes`` as in bench_ros.py.
"""
from __future__ import annotations

import argparse
import os
import pathlib
import signal
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench.bench_ros import (_condition_request, _load, _wait_file, min_duration, primitives_file,  # noqa: E402
                             quiet_domain_env, role_subscriber, stream_metrics)

ARMS = ("arm_a", "arm_b")
#: s without joint_states before a server stops its goal (ROBOT_STATE_STALE): the simulations paused for
#: more than bench_ros.py's 1 s at load 12 on 2 cores, which ended goals before their streams' recording did
STALE_TIMEOUT = 5.0
#: s a goal lasts beyond the recording's seconds (it is canceled when the recording ends): on a loaded
#: machine the recording started more than 1.5 s after a goal, which then ended before it
RUN_THROUGH = 10.0
#: the nodes of this benchmark; any other node in its domain belongs to another run (see bench_ros.py)
OWN_NODES = {"sim_bridge", "primitive_server", "primitive_server_control", "bench_stream_subscriber",
             "bench_dual_planner"}


class Planner:
    """The one planner: Condition and an Execute action client per arm (an rclpy executor spun here)."""

    def __init__(self, env):
        from deepprompt_ros.ros.testing import RosTestClient

        self.c = RosTestClient(env, "bench_dual_planner")
        self.actions = {}

    def connect(self, arm: str) -> None:
        from deepprompt_msgs.action import Execute
        from rclpy.action import ActionClient

        self.actions[arm] = ac = ActionClient(self.c.node, Execute, f"/{arm}/primitive_server/execute")
        if not self.c.wait_for(ac.server_is_ready, 60):
            raise RuntimeError(f"/{arm}/primitive_server/execute is not available")

    def long_goal(self, arm: str, rng, home, seconds: float, limits, config):
        """Send ``arm`` a goal of a random context that lasts longer than ``seconds``; its goal handle."""
        from deepprompt_msgs.action import Execute
        from deepprompt_msgs.srv import Condition

        req = _condition_request(rng, home, 0)
        req.preview_points = config.execution_grid_points
        r = self.c.call(Condition, f"/{arm}/primitive_server/condition", req, timeout=30.0)
        if not r.success:
            raise RuntimeError(f"/{arm}: Condition failed: {r.message}")
        duration = max(seconds + RUN_THROUGH, 1.3 * min_duration(r.preview, limits, config))
        fut = self.actions[arm].send_goal_async(Execute.Goal(handle=r.handle, duration=duration))
        if not self.c.wait_for(fut.done, 10) or not fut.result().accepted:
            raise RuntimeError(f"/{arm}: the Execute goal was not accepted")
        return fut.result()

    def cancel(self, goals) -> dict:
        """Cancel ``goals`` (arm -> goal handle); arm -> result code."""
        futs = {arm: gh.get_result_async() for arm, gh in goals.items()}
        for gh in goals.values():
            gh.cancel_goal_async()
        self.c.wait_for(lambda: all(f.done() for f in futs.values()), 30)
        return {arm: int(f.result().result.code.value) if f.done() else -1 for arm, f in futs.items()}

    def close(self) -> None:
        for ac in self.actions.values():
            ac.destroy()
        self.c.close()


def start_arm(arm: str, env, prim_file, procs: list, log_dir: pathlib.Path):
    """sim_bridge and primitive_server in namespace ``/arm`` (bench_ros.py's parameters); the server."""
    from deepprompt_ros.ros.testing import NodeProcess

    ns = ["-r", f"__ns:=/{arm}"]
    procs.append(NodeProcess.start_module("deepprompt_ros.ros.sim_bridge", env, params={
        "camera.enabled": False, "publish_clock": False}, ros_args=ns, name=f"sim_bridge_{arm}", log_dir=log_dir))
    # stale_timeout STALE_TIMEOUT: the streams are measured, not the simulations, which pause on a loaded machine
    server = NodeProcess.start_module("deepprompt_ros.ros.primitive_server", env, ros_args=[
        "-p", f"primitives_file:={prim_file}", "-p", f"stale_timeout:={STALE_TIMEOUT}", *ns],
        name=f"primitive_server_{arm}", log_dir=log_dir)
    procs.append(server)
    return server


def wait_serving(server, timeout: float = 120.0) -> None:
    end = time.monotonic() + timeout
    while "receiving joint_states" not in server.output():
        if time.monotonic() > end or not server.running():
            raise RuntimeError("primitive_server receives no joint_states:\n" + server.output_tail())
        time.sleep(0.1)


def stream_phase(name: str, arms, planner, env, tmp: pathlib.Path, args, procs: list, spec, limits, config,
                 rng) -> dict:
    """One long goal on each of ``arms`` at once, their commands recorded for the phase's seconds by a
    subscriber each; arm -> bench_ros.stream_metrics with ``code``, the goal's result (CANCELED: it ran
    through the recording)."""
    from deepprompt_ros.ros.testing import NodeProcess

    seconds = 2.0 if args.quick else args.seconds
    dt = 1.0 / spec.control_rate_hz
    gates = {arm: tmp / f"{name}_{arm}" for arm in arms}
    subs = {}
    for arm, gate in gates.items():
        cmd = [sys.executable, str(pathlib.Path(__file__).resolve()), "--role", "subscriber", "--out",
               f"{gate}.npz", "--gate", str(gate), "--priority", str(args.subscriber_priority),
               "--ros-args", "-r", f"__ns:=/{arm}"]
        subs[arm] = NodeProcess(cmd, env, tmp / f"{gate.name}.log")
        procs.append(subs[arm])
    for gate in gates.values():
        _wait_file(pathlib.Path(f"{gate}.ready"))
    goals = {arm: planner.long_goal(arm, rng, spec.home, seconds, limits, config) for arm in arms}
    planner.c.spin_for(0.5)  # past the goals' start
    for gate in gates.values():
        pathlib.Path(f"{gate}.go").write_text("go")
    planner.c.spin_for(seconds)
    for gate in gates.values():
        pathlib.Path(f"{gate}.stop").write_text("stop")
    codes = planner.cancel(goals)
    out = {arm: stream_metrics(_load(pathlib.Path(f"{gates[arm]}.npz"), subs[arm], 60), dt) for arm in arms}
    for arm in arms:
        out[arm]["code"] = codes[arm]
    NodeProcess.stop_all(subs.values())
    return out


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="2 s of stream per phase instead of --seconds")
    ap.add_argument("--seconds", type=float, default=30.0, help="seconds of stream recorded per phase")
    ap.add_argument("--model", help="model file to serve as 'reach' (6 Gen3 lite joints, context 'object'); "
                    "default: models/gen3_lite_reach.safetensors, else a tiny model trained here")
    ap.add_argument("--subscriber-priority", type=int, default=50, metavar="P",
                    help="SCHED_FIFO priority of the stream subscribers (as bench_ros.py; 0 = normal scheduling)")
    ap.add_argument("--priority", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--role", choices=("subscriber",), help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    ap.add_argument("--gate", help=argparse.SUPPRESS)
    # a role's namespace follows --ros-args (read by rclpy.init from sys.argv)
    args = ap.parse_args(argv[:argv.index("--ros-args")] if "--ros-args" in argv else argv)
    if args.role:  # SIGINT (the orchestrator's stop) ends a role even if it was started with SIGINT ignored
        signal.signal(signal.SIGINT, signal.default_int_handler)
        role_subscriber(args.out, args.gate, False, args.priority)
        return 0

    from deepprompt_msgs.msg import ResultCode

    from deepprompt_ros.robots.spec import load_robot
    from deepprompt_ros.ros.testing import NodeProcess
    from deepprompt_ros.server.config import ServerConfig, robot_limits

    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))  # the finally stops every process
    load_before = os.getloadavg()[0]
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="bench_dual_"))
    env = quiet_domain_env(tmp / "log")
    spec = load_robot("gen3_lite")
    config = ServerConfig()
    limits = robot_limits(spec, config)
    rng = np.random.default_rng(0)
    procs, planner = [], None
    t_start = time.monotonic()
    try:
        prim_file = primitives_file(tmp, args.model, 100 if args.quick else 300)
        planner = Planner(env)
        first = start_arm(ARMS[0], env, prim_file, procs, tmp)
        wait_serving(first)
        planner.connect(ARMS[0])
        alone = stream_phase("alone", ARMS[:1], planner, env, tmp, args, procs, spec, limits, config, rng)
        second = start_arm(ARMS[1], env, prim_file, procs, tmp)
        wait_serving(second)
        planner.connect(ARMS[1])
        dual = stream_phase("dual", ARMS, planner, env, tmp, args, procs, spec, limits, config, rng)
        foreign = sorted(set(planner.c.node.get_node_names()) - OWN_NODES)
    finally:
        if planner is not None:
            planner.close()
        NodeProcess.stop_all(procs)
    a = alone[ARMS[0]]
    metrics = dict(alone_stream_hz=a["stream_hz"], alone_missed=a["stream_missed"],
                   alone_p99_err_ms=a["stream_period_p99_err_ms"], alone_code=a["code"])
    for arm in ARMS:
        d = dual[arm]
        metrics.update({f"dual_{arm}_stream_hz": d["stream_hz"], f"dual_{arm}_missed": d["stream_missed"],
                        f"dual_{arm}_p99_err_ms": d["stream_period_p99_err_ms"], f"dual_{arm}_code": d["code"]})
    metrics.update(dual_stream_hz_min=min(dual[arm]["stream_hz"] for arm in ARMS),
                   dual_missed_ratio=(max(dual[arm]["stream_missed"] for arm in ARMS) + 1) / (a["stream_missed"] + 1),
                   goals_through=sum(code == ResultCode.CANCELED for code in (a["code"], *(dual[arm]["code"] for arm in ARMS))),
                   foreign_nodes=len(foreign), foreign_node_names=",".join(foreign) or "-",
                   wall_s=time.monotonic() - t_start)
    print(f"two arms against one ({'quick' if args.quick else 'full'}, {2.0 if args.quick else args.seconds:g} s "
          f"per phase; load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs, 1-min load average before "
          f"the start {load_before:.2f})")
    print(f"{'metric':40s} value")
    for k, v in metrics.items():
        print(f"{k:40s} {v:.4g}" if isinstance(v, float) else f"{k:40s} {v}")
    print(" ".join(f"{k}={metrics[k]:.4g}" for k in ("dual_stream_hz_min", "dual_missed_ratio")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
