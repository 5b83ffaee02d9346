"""`make run`: the simulated arm (sim_bridge; the Gen3 lite by default) and primitive_server with the
robot's shipped primitives, ready for service calls (see README). Ctrl-C stops the nodes (SIGINT, even
when this process was started with it ignored); a SIGKILL of this process stops them too (SIGTERM).

The nodes and their parameters are those of ``ros2 launch deepprompt_ros demo.launch.py``: both
come from :mod:`deepprompt_ros.bringup` (launch ``demo``), and the options below are its launch
arguments. ``--launch dual_arm`` (``make run-dual``) starts that launch's nodes instead, two arms
in two namespaces, with its arguments as options. Each node runs as its own process (its own DDS participant), with LOCALHOST discovery
unless ``ROS_AUTOMATIC_DISCOVERY_RANGE`` says otherwise. An optional node of the description
(robot_state_publisher, TF for RViz) whose executable is in no prefix of ``AMENT_PREFIX_PATH`` is
skipped with one line saying so.
"""
from __future__ import annotations

import argparse
import ctypes
import os
import signal
import subprocess
import sys
import time

from deepprompt_ros import bringup
from deepprompt_ros.common.params import ConfigError

#: The launches run_main starts (``--launch``); the first is the default.
LAUNCHES = ("demo", "dual_arm")


def parser(launch: str = LAUNCHES[0]) -> argparse.ArgumentParser:
    """``--launch`` and options ``--<argument>`` (``_`` written ``-``) for every argument of ``launch``."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--launch", default=LAUNCHES[0], choices=LAUNCHES, help="the launch whose nodes are started")
    for spec in bringup.arguments(launch):
        unit = f" ({spec.unit})" if spec.unit else ""
        ap.add_argument("--" + spec.name.replace("_", "-"), dest=spec.name, default=bringup.argument_text(spec),
                        help=spec.description + unit)
    return ap


def _stop_with(parent_pid: int):
    """A Popen ``preexec_fn``: the node gets SIGTERM when ``parent_pid`` (this process) ends without
    stopping it (SIGKILL; Linux PR_SET_PDEATHSIG, kept across exec), not left running on its own."""
    def preexec() -> None:
        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM), 0, 0, 0)  # 1 = PR_SET_PDEATHSIG
        if os.getppid() != parent_pid:  # the parent ended before the prctl
            os.kill(os.getpid(), signal.SIGTERM)
    return preexec


def main(argv=None) -> int:
    launch = parser().parse_known_args(argv)[0].launch  # its options are the chosen launch's arguments
    ap = parser(launch)
    args = vars(ap.parse_args(argv))
    del args["launch"]
    try:
        nodes = bringup.nodes(launch, args)
    except (ConfigError, FileNotFoundError) as exc:
        ap.error(str(exc))
    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    procs = {}

    def _terminate(signum, _frame):  # SIGTERM (e.g. from `timeout` or a supervisor): stop the nodes too
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, _terminate)
    # Ctrl-C / SIGINT stops the nodes even when this process was started with SIGINT ignored (a background
    # job of a non-interactive shell, or a parent that ignores it, passes SIG_IGN on, and Python then
    # installs no KeyboardInterrupt handler); the nodes, started after this, get SIGINT's default back
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        for node in nodes:
            try:
                cmd = node.command(sys.executable)
            except FileNotFoundError as exc:
                if not node.optional:
                    raise
                print(f"[run] {node.name} skipped: {exc}; {node.optional}", flush=True)
                continue
            node_env = {**env, **dict(node.environment)}
            label = f"{node.namespace}/{node.name}" if node.namespace else node.name
            procs[label] = subprocess.Popen(cmd, env=node_env, start_new_session=True,
                                            preexec_fn=_stop_with(os.getpid()))
            print(f"[run] started {label} (pid {procs[label].pid})", flush=True)
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
