"""`make run`: the simulated Gen3 lite (sim_bridge) and primitive_server with the shipped primitives,
ready for service calls (see README, "Task-planner example"). Ctrl-C stops both.

Both nodes run as separate processes (their own DDS participants) with LOCALHOST discovery.
"""
from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time

from deepprompt_ros.paths import config_dir


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--robot", default="gen3_lite", help="robot of the sim bridge (gen3_lite | wam | example-robot-data name)")
    ap.add_argument("--real-time-factor", type=float, default=1.0)
    ap.add_argument("--stale-timeout", type=float, default=1.0,
                    help="primitive_server stale_timeout (s) for the simulated robot (the server default 0.2 s suits a real arm)")
    args = ap.parse_args(argv)
    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault("OPENBLAS_NUM_THREADS", "1")  # small matrices: no BLAS threads competing with the 1 kHz loop
    cfg = config_dir()
    nodes = {
        "sim_bridge": [sys.executable, "-m", "deepprompt_ros.ros.sim_bridge", "--ros-args",
                       "--params-file", str(cfg / "sim_bridge.yaml"),
                       "-p", f"robot:={args.robot}", "-p", f"real_time_factor:={args.real_time_factor}"],
        "primitive_server": [sys.executable, "-m", "deepprompt_ros.ros.primitive_server", "--ros-args",
                             "--params-file", str(cfg / "primitive_server.yaml"), "-p", f"robot:={args.robot}",
                             # the Python simulation can pause for a few hundred ms on a busy machine
                             "-p", f"stale_timeout:={args.stale_timeout}"],
    }
    procs = {}

    def _terminate(signum, _frame):  # SIGTERM (e.g. from `timeout` or a supervisor): stop the nodes too
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, _terminate)
    try:
        for name, cmd in nodes.items():
            procs[name] = subprocess.Popen(cmd, env=env, start_new_session=True)
            print(f"[run] started {name} (pid {procs[name].pid})", flush=True)
        print("[run] ready for service calls, e.g. `.venv/bin/python examples/planner_client.py`; Ctrl-C to stop",
              flush=True)
        while True:
            for name, p in procs.items():
                if p.poll() is not None:
                    print(f"[run] {name} exited with code {p.returncode}", flush=True)
                    return p.returncode or 1
            time.sleep(0.5)
    except KeyboardInterrupt:
        return 0
    finally:
        for p in procs.values():
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGINT)
        deadline = time.time() + 5
        for p in procs.values():
            try:
                p.wait(timeout=max(0.1, deadline - time.time()))
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)


if __name__ == "__main__":
    sys.exit(main())
