"""Benchmark of primitive_server over real DDS, every party in its own process.

    python bench/bench_ros.py            # full: per mode 40 s stream, >= 1000 Condition calls, 30 random executions
    python bench/bench_ros.py --quick    # smoke run: per mode 2 s stream, 20 calls, limits checked on that stream
    python bench/bench_ros.py --sim-param joint_states_rate_hz:=250 --param gil_switch_interval:=0.0005

Processes: sim_bridge (PyBullet Gen3 lite, joint_states at 1 kHz), primitive_server (and, with
its default ``loop_process: true``, its control-loop child process), a stream subscriber, a
Condition client, and this orchestrator (action client).

Both modes of the server are measured in one run, one after the other against the same simulated
robot: ``fast_path: true`` (the default; the figures below without suffix) and ``fast_path: false``
(plain rclpy; the same figures with the suffix ``_plain``). ``<figure>_fast_over_plain`` is the
ratio of the two for the service round trip and the stream's period error (< 1: the fast path is
better), so the fast path has to keep earning its place.

Metrics (last line: space-separated name=value pairs; the fast path's headline figures, the plain
ones and the ratios):

* ``srv_p50_ms``, ``srv_p99_ms`` -- Condition round trip (request with 5 via-points and the
  'object' context, preview 100 points) measured by the client process, which calls every 40 ms
  (25 calls/s) while the stream runs: from just before sending to the response taken (the client
  waits on an rcl wait set of its own, see role_client);
* ``--service list_primitives``: the client calls ListPrimitives instead (a handler that does next to
  nothing): ``srv_*`` is then the transport's share of a round trip under the same load (``srv_service``
  says which was called);
* ``--reference-loop``: ``ref_loop_period_p99_err_ms``, ``ref_loop_missed`` (of ``ref_loop_intervals``)
  -- the same two figures for a bare 1 kHz Python loop (no ROS, no work, paced like the server's control
  thread, SCHED_FIFO at ``--subscriber-priority``) run in its own process during the stream: the
  machine's own floor for a real-time loop under this load;
* ``srv_handler_p50_ms``, ``srv_handler_p99_ms`` -- time inside the server's Condition callback
  (its log): the computation, without transport and executor dispatch;
* ``stream_hz`` -- joint_command messages received per second by the subscriber during one long
  Execute goal (arrival = the instant the subscriber process's DDS layer received the message,
  see role_subscriber: the Python measuring code neither delays nor loads the stream). The
  subscriber runs as a real-time consumer (a controller) would: SCHED_FIFO ``--subscriber-priority``
  (default 50; 0 = normal scheduling); ``subscriber_fifo_priority`` says what it got (0 if refused);
* ``stream_period_p99_err_ms`` -- p99 over inter-arrival intervals of |interval - dt| (dt = 1 ms);
* ``stream_missed`` -- intervals longer than 1.5 dt (each is a command that arrived at least half a
  period late or not at all); ``stream_lost`` -- gaps in the commands' header.stamp (the nominal
  time of the tick, k dt): commands lost on the way plus the periods the server skipped after a tick
  that started more than a period late (its deadlines then restart from now, see execution.stream_loop);
* ``server_period_p99_err_ms``, ``server_missed`` -- the same two figures from the server's own
  publication instants (its log): pacing alone, without transport and subscriber scheduling;
* ``cpu_<process>_pct`` -- CPU time of each process (user + system, /proc) per wall-clock second
  while the stream and the Condition client ran, in % of one core (the machine has os.cpu_count());
  ``cpu_control_pct`` is the server's control-loop child process (``loop_process: true``);
* ``server_gc_count``, ``server_gc_max_ms`` -- cyclic garbage collections in the server and the
  longest (each holds the interpreter lock);
* ``limit_violations`` -- over random executions in the sim (random via-points, durations,
  preemptions, cancels, phase-rate changes): commanded samples violating a limit
  (execution.limits.check_limits on the joint_command stream: positions, velocities, and the
  finite-difference accelerations / jerks of consecutive commands; segments split at lost
  messages) plus measured joint_states samples outside the URDF position limits by > 1e-4 rad.

Length: over 400 lines because the script starts itself again for each measuring role
(``--role subscriber | client | reference_loop``, each in its own process): the orchestrator, the
roles and the figures computed from their recordings share its command line and constants, and
``python bench/bench_ros.py`` stays the one thing to run. The rclpy internals it relies on are in
:mod:`deepprompt_ros.ros.fastpath` (``polled.take_all``, ``service_client.BlockingClient``).
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import re
import signal
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

SERVER = "/primitive_server"


# ------------------------------------------------------------------------------------------------
# model: the shipped reach primitive, or a tiny one trained here
# ------------------------------------------------------------------------------------------------
def tiny_reach_model(path: pathlib.Path, steps: int = 300) -> pathlib.Path:
    """A small 6-joint Gen3 lite primitive with context 'object' (3), trained in seconds on
    :func:`~deepprompt_ros.sim.tasks.kinematic_reach.context_reach_demos`."""
    from deepprompt_ros.sim.tasks.kinematic_reach import context_reach_demos
    from deepprompt_ros.training.config import TrainConfig
    from deepprompt_ros.training.loop import train

    train(context_reach_demos(n_demos=40, n_points=50, seed=0),
          TrainConfig(steps=steps, latent_dim=8, hidden=32, val_every=steps, n_points=50, max_via_points=5,
                      threads=1), out_path=path, log=lambda m: None)
    return path


def primitives_file(tmp: pathlib.Path, model: str | None = None, steps: int = 300) -> pathlib.Path:
    """Serve ``model``, else the shipped models/gen3_lite_reach.safetensors, else a tiny one."""
    from deepprompt_ros import paths

    if model is None:
        try:
            model = paths.find_data_file("models", "gen3_lite_reach.safetensors")
        except FileNotFoundError:
            model = tiny_reach_model(tmp / "tiny_reach.safetensors", steps)
    f = tmp / "primitives.yaml"
    f.write_text(f"primitives:\n  - name: reach\n    model: {model}\n")
    return f


# ------------------------------------------------------------------------------------------------
# roles running in their own processes
# ------------------------------------------------------------------------------------------------
def _realtime(priority: int, who: str) -> str:
    """SCHED_FIFO ``priority`` for this process (0: none asked); '' if granted, else why not (printed)."""
    from deepprompt_ros.ros.fastpath.realtime import set_fifo_priority

    why = set_fifo_priority(priority) if priority > 0 else "normal scheduling asked"
    if why and priority > 0:
        print(f"{who}: {why}", flush=True)
    return why


def _role_node(name):
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)  # SIGINT (the orchestrator's stop) ends it
    node = rclpy.create_node(name)
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    return rclpy, node, ex


def _save(out: str, **arrays) -> None:
    """np.savez to a temporary name, then rename: the file appears complete."""
    tmp = pathlib.Path(out + ".part.npz")
    np.savez(tmp, **arrays)
    tmp.replace(out)


def _load(path: pathlib.Path, proc, timeout: float) -> dict:
    """Wait for a role's result file (not for its process to exit); fail with its log."""
    end = time.monotonic() + timeout
    while not path.exists():
        if time.monotonic() > end or not proc.running():
            if not path.exists():
                raise RuntimeError(f"no {path.name}:\n{proc.output_tail()}")
        time.sleep(0.05)
    return dict(np.load(path))


_PARENT = os.getppid()  # a role process's orchestrator


def _check_parent() -> None:
    """A role process ends when its orchestrator is gone (killed before it could stop its roles)."""
    if os.getppid() != _PARENT:
        raise SystemExit("bench_ros: the orchestrator is gone; stopping")


def _wait_file(path: pathlib.Path, ex=None) -> None:
    while not path.exists():
        _check_parent()
        if ex is not None:
            ex.spin_once(timeout_sec=0.02)
        else:
            time.sleep(0.02)


SUB_POLL = 0.02  # s between two reads of the subscriber's queues (it records DDS reception times)


def role_subscriber(out: str, gate: str, states: bool, priority: int = 0) -> None:
    """Record joint_command (arrival time, stamp, q, qd) and, if ``states``, joint_states (q),
    between the files <gate>.go and <gate>.stop (messages before are dropped); <gate>.ready once
    subscribed.

    Cheap measurement: no executor callback per message (in Python that alone costs most of a core
    at 2 kHz). Messages are taken as serialized bytes every SUB_POLL s from queues deep enough for
    1 s; the arrival time of each is the instant the DDS layer of this process received it
    (message info ``received_timestamp``, system clock), not the instant Python got to it. They are
    decoded after the run.

    ``priority`` > 0: SCHED_FIFO at that priority for the whole process, set before rclpy starts so
    the DDS threads that receive (and time-stamp) the messages inherit it — as a controller process
    on a real-time setup runs.
    """
    _realtime(priority, "subscriber")
    from rclpy.qos import QoSProfile
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState

    from deepprompt_ros.ros.fastpath.polled import NotExecuted, take_all

    rclpy, node, _ = _role_node("bench_stream_subscriber")  # its executor is never spun: messages are taken
    qos, group = QoSProfile(depth=1000), NotExecuted()
    subs = {"cmd": node.create_subscription(JointState, "joint_command", lambda m: None, qos, raw=True,
                                            callback_group=group)}
    if states:
        subs["js"] = node.create_subscription(JointState, "joint_states", lambda m: None, qos, raw=True,
                                              callback_group=group)
    rec = {k: [] for k in subs}

    def take(keep: bool) -> None:
        for k, sub in subs.items():
            for data, info in take_all(sub):
                if keep:
                    rec[k].append((info["received_timestamp"] or time.time_ns(), data))

    pathlib.Path(gate + ".ready").write_text("ready")
    go, stop = pathlib.Path(gate + ".go"), pathlib.Path(gate + ".stop")
    while not go.exists():
        _check_parent()
        take(False)
        time.sleep(0.02)
    while not stop.exists():
        _check_parent()
        take(True)
        time.sleep(SUB_POLL)
    take(True)

    cmd = [deserialize_message(b, JointState) for _, b in rec["cmd"]]
    js = [deserialize_message(b, JointState).position for _, b in rec.get("js", [])]

    def rows(values, width=6):
        return np.array(values, dtype=np.float64).reshape(len(values), width)

    _save(out, t=np.array([t for t, _ in rec["cmd"]], dtype=np.int64) * 1e-9,
          stamp=np.array([m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in cmd], dtype=np.int64),
          q=rows([m.position for m in cmd]), qd=rows([m.velocity for m in cmd]), js=rows(js))
    node.destroy_node()
    rclpy.try_shutdown()


def _condition_request(rng, home):
    from deepprompt_msgs.msg import Context
    from deepprompt_msgs.srv import Condition

    from deepprompt_ros.ros import conversions as conv

    x = np.sort(rng.uniform(0, 1, 5))
    y = home + rng.normal(0, 0.05, (5, 6))
    return Condition.Request(primitive="reach", via_points=conv.via_points_to_msgs(x, y),
                             contexts=[Context(modality="object", values=rng.uniform(-0.3, 0.3, 3).tolist())],
                             preview_points=100)


CALL_PERIOD = 0.04  # s between the starts of two Condition calls (25 calls/s, a busy planner)


def role_client(out: str, gate: str, seconds: float, min_calls: int, service: str = "condition") -> None:
    """From the file <gate>.go on, call Condition (``service`` "list_primitives": ListPrimitives, whose
    handler does next to nothing — the transport's share under the same load) every CALL_PERIOD s (back
    to back when a call takes longer) for ``seconds`` and at least ``min_calls`` calls; record round trips.

    Round trip: from just before the request is sent to the moment its response has been taken in
    this process. The client waits on its own rcl wait set (what an rclpy executor does inside, without
    the executor's per-wake bookkeeping; see ros.fastpath.service_client) and sleeps between calls.
    """
    from deepprompt_msgs.srv import Condition, ListPrimitives

    from deepprompt_ros.robots.spec import load_robot
    from deepprompt_ros.ros.fastpath.service_client import BlockingClient

    rclpy, node, _ = _role_node("bench_condition_client")  # its executor is never spun: the client waits itself
    srv_type = ListPrimitives if service == "list_primitives" else Condition
    cli = BlockingClient(node, srv_type, f"{SERVER}/{service}")
    cli.wait_for_service(timeout=60)
    home = load_robot("gen3_lite").home

    pathlib.Path(gate + ".ready").write_text("ready")
    _wait_file(pathlib.Path(gate + ".go"))
    rng = np.random.default_rng(1)
    rtt, fails = [], 0
    end = time.monotonic() + seconds
    next_call = time.monotonic()
    while time.monotonic() < end or len(rtt) < min_calls:
        req = _condition_request(rng, home) if srv_type is Condition else ListPrimitives.Request()
        time.sleep(max(0.0, next_call - time.monotonic()))
        next_call += CALL_PERIOD
        t0 = time.perf_counter()
        res = cli.call(req)
        rtt.append(time.perf_counter() - t0)
        fails += not res.success
    _save(out, rtt=np.array(rtt), fails=fails)
    cli.destroy()
    node.destroy_node()
    rclpy.try_shutdown()


# ------------------------------------------------------------------------------------------------
# orchestrator
# ------------------------------------------------------------------------------------------------
class Orchestrator:
    def __init__(self, env):
        from rclpy.action import ActionClient

        from deepprompt_msgs.action import Execute
        from deepprompt_ros.ros.testing import RosTestClient

        self.c = RosTestClient(env, "bench_orchestrator")
        self.Execute = Execute
        self.ac = ActionClient(self.c.node, Execute, f"{SERVER}/execute")
        if not self.c.wait_for(self.ac.server_is_ready, 60):
            raise RuntimeError("execute action server not available")

    def condition(self, req):
        from deepprompt_msgs.srv import Condition

        return self.c.call(Condition, f"{SERVER}/condition", req)

    def set_rate(self, rate):
        from deepprompt_msgs.srv import SetPhaseRate

        return self.c.call(SetPhaseRate, f"{SERVER}/set_phase_rate", SetPhaseRate.Request(phase_rate=rate))

    def send(self, handle, duration):
        """Send a goal; if the server refuses the duration as too fast for the velocity limits
        (LIMIT_VIOLATION "use a duration >= T s"), send it again with 1.2 T."""
        for _ in range(2):
            fut = self.ac.send_goal_async(self.Execute.Goal(handle=handle, duration=duration))
            self.c.wait_for(fut.done, 10)
            gh = fut.result()
            res = gh.get_result_async()
            self.c.wait_for(res.done, 0.3)
            if res.done():
                m = re.search(r"use a duration >= ([\d.e+-]+) s", res.result().result.message)
                if m:
                    duration = 1.2 * float(m[1])
                    continue
            break
        return gh, res

    def wait(self, res_fut, timeout):
        self.c.wait_for(res_fut.done, timeout)
        return res_fut.result().result if res_fut.done() else None

    def close(self):
        self.ac.destroy()
        self.c.close()


class _Pid:
    """A process that is not ours to stop (the server's control process), for cpu_seconds."""

    def __init__(self, pid: int):
        self.pid = pid

    def running(self) -> bool:
        return pathlib.Path(f"/proc/{self.pid}").exists()


def cpu_seconds(pid: int | str = "self") -> float:
    """User + system CPU time of a process so far (Linux /proc), in seconds."""
    fields = pathlib.Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def role_reference_loop(out: str, gate: str, priority: int, dt: float) -> None:
    """A bare 1/dt Hz loop (no ROS, no work) paced like the server's control thread — absolute
    perf_counter deadlines, ``time.sleep`` until each — at SCHED_FIFO ``priority``, between the files
    <gate>.go and <gate>.stop: what this machine's scheduler allows a real-time Python loop under the
    benchmark's load (its wake instants are recorded)."""
    why = _realtime(priority, "reference loop")
    pathlib.Path(gate + ".ready").write_text("ready")
    _wait_file(pathlib.Path(gate + ".go"))
    stop = pathlib.Path(gate + ".stop")
    wake = []
    t = time.perf_counter()
    while True:
        for _ in range(1000):  # the stop file is checked once a second
            t += dt
            remaining = t - time.perf_counter()
            if remaining > 0:
                time.sleep(remaining)
            wake.append(time.perf_counter())
        if stop.exists():
            break
        _check_parent()
    _save(out, t=np.array(wake), fifo=np.array(0 if why else priority))


def _interval_figures(iv: np.ndarray, dt: float) -> tuple[float, int, float]:
    """Of intervals ``iv`` (s) meant to be ``dt``: p99 of |iv − dt| (ms), the number longer than
    1.5 dt (missed periods), the longest (ms)."""
    return float(np.percentile(np.abs(iv - dt), 99) * 1e3), int((iv > 1.5 * dt).sum()), float(iv.max() * 1e3)


def reference_loop_metrics(data, dt) -> dict:
    iv = np.diff(data["t"])
    p99, missed, longest = _interval_figures(iv, dt)
    return dict(ref_loop_period_p99_err_ms=p99, ref_loop_missed=missed, ref_loop_intervals=int(iv.size),
                ref_loop_interval_max_ms=longest, ref_loop_fifo_priority=int(data["fifo"]))


def stream_metrics(data, dt):
    t, stamp = data["t"] - data["t"][:1], data["stamp"]
    if t.size < 3:
        return dict(stream_hz=0.0, stream_period_p99_err_ms=float("nan"), stream_missed=-1, stream_lost=-1)
    p99, missed, longest = _interval_figures(np.diff(t), dt)
    steps = np.round(np.diff(stamp) / (dt * 1e9)).astype(int)
    return dict(stream_hz=float((t.size - 1) / (t[-1] - t[0])), stream_period_p99_err_ms=p99, stream_missed=missed,
                stream_lost=int(np.maximum(steps - 1, 0).sum()), stream_interval_max_ms=longest)


def limit_check(data, dt, limits):
    """Violations in the commanded stream (segments between lost messages) and measured states."""
    from deepprompt_ros.execution.limits import check_limits

    q, qd, stamp = data["q"], data["qd"], data["stamp"]
    viol, worst = 0, {}
    if q.shape[0] > 2:
        steps = np.round(np.diff(stamp) / (dt * 1e9)).astype(int)
        cuts = np.flatnonzero(steps != 1) + 1
        for seg in np.split(np.arange(q.shape[0]), cuts):
            if seg.size < 4:
                continue
            # qdd of sample k: (qd[k] - qd[k-1]) / dt, the mean acceleration over the period before it
            qs, vs = q[seg][1:], qd[seg][1:]
            acc = np.diff(qd[seg], axis=0) / dt
            rep = check_limits(qs, vs, acc, dt, limits)
            # per-sample counts (the report gives maxima): positions, velocities, accelerations, jerks
            bad = ((qs < limits.lower - 1e-9) | (qs > limits.upper + 1e-9)).any(1)
            bad |= (np.abs(vs) > limits.max_velocity * (1 + 1e-6)).any(1)
            bad |= (np.abs(acc) > limits.max_acceleration * (1 + 1e-6)).any(1)
            bad[1:] |= (np.abs(np.diff(acc, axis=0)) / dt > limits.max_jerk * (1 + 1e-6)).any(1)
            viol += int(bad.sum())
            for k in ("velocity_ratio", "fd_acceleration_ratio", "jerk_ratio", "position_excess"):
                worst[k] = max(worst.get(k, 0.0), float(getattr(rep, k)))
    js = data["js"]
    excess = np.maximum(np.maximum(limits.lower - js, js - limits.upper), 0.0).max(1) if js.size else np.zeros(0)
    js_viol = int((excess > 1e-4).sum())
    worst["measured_position_excess"] = float(excess.max()) if excess.size else 0.0
    return viol, js_viol, worst


#: the figures printed for both modes and compared as fast path / plain rclpy (last line)
COMPARED = ("srv_p50_ms", "srv_p99_ms", "stream_period_p99_err_ms")


def measure(args, env, tmp: pathlib.Path, prim_file: pathlib.Path, spec, limits, fast_path: bool,
            procs: list) -> dict:
    """One primitive_server (``fast_path`` as given) measured against the running sim_bridge: phase 1
    (one long execution with the stream subscriber and the Condition client, each in its own process)
    and phase 2 (random executions, limits). Every process started here is appended to ``procs``
    and stopped before returning."""
    from deepprompt_ros.ros.testing import NodeProcess

    dt = 1.0 / spec.control_rate_hz
    stream_s, calls, n_exec = (2.0, 20, 0) if args.quick else (40.0, 1000, 30)
    mode = "fast" if fast_path else "plain"
    tmp = tmp / mode
    tmp.mkdir()
    mine: list = []

    def started(p):
        procs.append(p)
        mine.append(p)
        return p

    orch = None
    try:
        # stale_timeout 1 s: on a loaded machine the Python sim pauses; this benchmark measures the stream
        ros_args = ["-p", f"primitives_file:={prim_file}", "-p", f"loop_mode:={args.loop_mode}",
                    "-p", "stale_timeout:=1.0", "-p", f"fast_path:={str(fast_path).lower()}"]
        for p in args.param:
            ros_args += ["-p", p]
        server = started(NodeProcess.start_module("deepprompt_ros.ros.primitive_server", env, ros_args=ros_args,
                                                  name=f"primitive_server_{mode}"))

        def start_role(role, out, gate, extra=()):
            cmd = [sys.executable, str(pathlib.Path(__file__).resolve()), "--role", role, "--out", str(out),
                   "--gate", str(gate), *extra]
            return started(NodeProcess(cmd, env, tmp / f"{pathlib.Path(gate).name}.log"))

        def wait_ready(gate):
            _wait_file(pathlib.Path(str(gate) + ".ready"))

        def go(gate, what="go"):
            pathlib.Path(f"{gate}.{what}").write_text(what)

        # measuring processes start now, in parallel with the server
        g_sub, g_cli, g_sub2 = tmp / "stream", tmp / "client", tmp / "limits"
        # quick: no random executions; the limits are checked on the phase-1 stream (+ joint states)
        prio = ["--priority", str(args.subscriber_priority)]
        sub = start_role("subscriber", tmp / "stream.npz", g_sub, (["--states"] if args.quick else []) + prio)
        cli = start_role("client", tmp / "client.npz", g_cli, ["--seconds", str(stream_s), "--calls", str(calls),
                                                               "--service", args.service])
        sub2 = None if args.quick else start_role("subscriber", tmp / "limits.npz", g_sub2, ["--states"] + prio)
        g_ref = tmp / "reference"
        ref = start_role("reference_loop", tmp / "reference.npz", g_ref, prio) if args.reference_loop else None
        orch = Orchestrator(env)
        end = time.monotonic() + 60
        while "receiving joint_states" not in server.output():
            if time.monotonic() > end:
                raise RuntimeError("primitive_server receives no joint_states:\n" + server.output_tail())
            time.sleep(0.1)

        # ---- phase 1: one long execution; subscriber + Condition client in their own processes
        for g in (g_sub, g_cli) + (() if sub2 is None else (g_sub2,)) + (() if ref is None else (g_ref,)):
            wait_ready(g)
        rng = np.random.default_rng(0)
        r = orch.condition(_condition_request(rng, spec.home))
        assert r.success, r.message
        go(g_sub)
        if ref is not None:
            go(g_ref)
        gh, res_fut = orch.send(r.handle, stream_s + 1.5)
        orch.c.spin_for(0.5)
        roles = {"sim_bridge": procs[0], "server": server, "subscriber": sub, "client": cli}
        child = re.findall(r"control loop running in its own process \(pid (\d+)\)", server.output())
        if child:  # loop_process: the control loop's own process (cpu_server_pct is then the rest)
            roles["control"] = _Pid(int(child[-1]))
        cpu0 = {k: cpu_seconds(p.pid) for k, p in roles.items()}
        cpu0["orchestrator"], w0 = cpu_seconds(), time.monotonic()
        go(g_cli)
        client = _load(tmp / "client.npz", cli, stream_s * 10 + 120)
        # share of one core used by each process while the stream and the client ran
        wall = time.monotonic() - w0
        cpu = {k: (cpu_seconds(p.pid) - cpu0[k]) / wall for k, p in roles.items() if p.running()}
        cpu["orchestrator"] = (cpu_seconds() - cpu0["orchestrator"]) / wall
        if args.quick:  # enough stream measured: brake now (also exercises cancel)
            gh.cancel_goal_async()
        res = orch.wait(res_fut, stream_s + 30)
        go(g_sub, "stop")
        stream = _load(tmp / "stream.npz", sub, 60)
        metrics = stream_metrics(stream, dt)
        if ref is not None:
            go(g_ref, "stop")
            metrics.update(reference_loop_metrics(_load(tmp / "reference.npz", ref, 60), dt))
        # the subscriber's scheduling as it ran (a refused SCHED_FIFO leaves it at normal priority)
        metrics["subscriber_fifo_priority"] = (0 if args.subscriber_priority <= 0 or "refused" in sub.output()
                                               else args.subscriber_priority)
        # the server's own view (publication instants, no transport / subscriber scheduling)
        found = re.findall(r"publish period error p50 ([\d.]+) ms, p99 ([\d.]+) ms, (\d+) of (\d+) intervals",
                           server.output())
        if found:
            metrics.update(server_period_p99_err_ms=float(found[-1][1]), server_missed=int(found[-1][2]))
        # time inside the server's Condition callback (the rest of a round trip: transport, executors)
        found = re.findall(r"condition handled in p50 ([\d.]+) ms, p99 ([\d.]+) ms", server.output())
        if found and args.service == "condition":  # (list_primitives: only the orchestrator's one call)
            metrics.update(srv_handler_p50_ms=float(found[-1][0]), srv_handler_p99_ms=float(found[-1][1]))
        found = re.findall(r"(\d+) garbage collections .*?, ([\d.]+) ms in total, longest ([\d.]+) ms", server.output())
        if found:  # in the server process since its start-up objects were frozen
            metrics.update(server_gc_count=int(found[-1][0]), server_gc_max_ms=float(found[-1][2]))
        rtt = client["rtt"] * 1e3
        metrics.update(srv_service=args.service,
                       srv_p50_ms=float(np.percentile(rtt, 50)), srv_p99_ms=float(np.percentile(rtt, 99)),
                       srv_calls=int(rtt.size), srv_failures=int(client["fails"]),
                       long_goal_code=int(res.code.value) if res is not None else -1,
                       **{f"cpu_{k}_pct": 100 * v for k, v in cpu.items()})

        # ---- phase 2: random executions; the subscriber records commands and joint states
        codes = {}
        if sub2 is not None:
            go(g_sub2)
        for i in range(n_exec):
            r = orch.condition(_condition_request(rng, spec.home))
            if not r.success:
                codes["condition_failed"] = codes.get("condition_failed", 0) + 1
                continue
            gh, fut = orch.send(r.handle, float(rng.uniform(2.0, 2.5 if args.quick else 4.0)))
            action = rng.choice(["finish", "preempt", "cancel", "rate"])
            orch.c.spin_for(float(rng.uniform(0.3, 1.5)))
            if action == "cancel":
                gh.cancel_goal_async()
            elif action == "rate":
                orch.set_rate(float(rng.uniform(-0.2, 0.6)))
            elif action == "preempt":
                r2 = orch.condition(_condition_request(rng, spec.home))
                if r2.success:
                    gh, fut = orch.send(r2.handle, float(rng.uniform(2.0, 4.0)))
            if action == "rate":
                orch.c.spin_for(1.0)
                gh.cancel_goal_async()
            res = orch.wait(fut, 30.0)
            name = str(res.code.value) if res is not None else "timeout"
            codes[name] = codes.get(name, 0) + 1
        if sub2 is not None:
            orch.c.spin_for(0.5)
            go(g_sub2, "stop")
            viol, js_viol, worst = limit_check(_load(tmp / "limits.npz", sub2, 60), dt, limits)
        else:
            viol, js_viol, worst = limit_check(stream, dt, limits)
        metrics.update(limit_violations=viol + js_viol, limit_violations_measured=js_viol,
                       executions=n_exec, **{f"worst_{k}": v for k, v in worst.items()})
        metrics["exec_codes"] = json.dumps(codes, sort_keys=True).replace(" ", "")
        return metrics
    finally:
        if orch is not None:
            orch.close()
        _stop_all(mine)


def _stop_all(procs) -> None:
    """SIGINT every running process of ``procs`` at once, then wait for each (SIGKILL after 5 s)."""
    for p in procs:
        if p.running():
            try:
                os.killpg(p.pid, signal.SIGINT)
            except ProcessLookupError:
                pass
    for p in procs:
        p.stop()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="a few seconds instead of a few minutes")
    ap.add_argument("--loop-mode", default="thread", choices=("thread", "timer"))
    ap.add_argument("--param", action="append", default=[], help="extra primitive_server parameter name:=value")
    ap.add_argument("--sim-param", action="append", default=[],
                    help="extra sim_bridge parameter name:=value (e.g. joint_states_rate_hz:=250)")
    ap.add_argument("--model", help="model file to serve as 'reach' (6 Gen3 lite joints, context 'object'); "
                    "default: models/gen3_lite_reach.safetensors, else a tiny model trained here")
    ap.add_argument("--subscriber-priority", type=int, default=50, metavar="P",
                    help="SCHED_FIFO priority of the stream subscriber processes, as a real-time consumer of the "
                    "stream runs (default 50, the server's realtime_priority default; 0 = normal scheduling; "
                    "refused without CAP_SYS_NICE -> normal, said in the output)")
    ap.add_argument("--service", default="condition", choices=("condition", "list_primitives"),
                    help="what the client process calls (default condition; list_primitives: a near-empty "
                    "handler, i.e. the transport's share of srv_* under the same load)")
    ap.add_argument("--reference-loop", action="store_true",
                    help="also run, during the stream, a bare 1 kHz Python loop (no ROS, no work) at the "
                    "subscribers' SCHED_FIFO priority in a process of its own: ref_loop_* say what the machine's "
                    "scheduler allows a real-time loop under the same load")
    ap.add_argument("--priority", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--role", choices=("subscriber", "client", "reference_loop"), help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    ap.add_argument("--seconds", type=float, default=0.0, help=argparse.SUPPRESS)
    ap.add_argument("--calls", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--gate", help=argparse.SUPPRESS)
    ap.add_argument("--states", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.role:  # SIGINT (the orchestrator's stop) ends a role even if it was started with SIGINT ignored
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if args.role == "subscriber":
        role_subscriber(args.out, args.gate, args.states, args.priority)
        return 0
    if args.role == "reference_loop":
        role_reference_loop(args.out, args.gate, args.priority, 1e-3)
        return 0
    if args.role == "client":
        role_client(args.out, args.gate, args.seconds, args.calls, args.service)
        return 0

    from deepprompt_ros.robots.spec import load_robot
    from deepprompt_ros.server.config import ServerConfig, robot_limits
    from deepprompt_ros.ros.testing import NodeProcess, isolated_ros_env

    # SIGTERM (kill, timeout) ends the run like an error: the finally below stops every process started
    # (rclpy, initialized later by the Orchestrator, calls this handler from its own)
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))

    load_before = os.getloadavg()[0]  # other work on the machine (this benchmark adds ~1 when it runs)
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="bench_ros_"))
    env = isolated_ros_env(tmp / "log")
    spec = load_robot("gen3_lite")
    limits = robot_limits(spec, ServerConfig())
    procs = []
    t_start = time.monotonic()
    try:
        prim_file = primitives_file(tmp, args.model, 100 if args.quick else 300)
        sim_ros_args = [a for p in args.sim_param for a in ("-p", p)]
        procs.append(NodeProcess.start_module("deepprompt_ros.ros.sim_bridge", env, params={
            "camera.enabled": False, "publish_clock": False}, ros_args=sim_ros_args))
        # the same measurement of the fast path, then of plain rclpy, against the same simulated robot
        metrics = measure(args, env, tmp, prim_file, spec, limits, True, procs)
        plain = measure(args, env, tmp, prim_file, spec, limits, False, procs)
    finally:
        _stop_all(procs)
    metrics.update({f"{k}_plain": v for k, v in plain.items() if k not in ("srv_service",)})
    for k in COMPARED:  # fast path / plain rclpy: < 1 where the fast path is faster
        a, b = metrics[k], plain[k]
        metrics[f"{k}_fast_over_plain"] = float(a / b) if b else float("nan")
    metrics["wall_s"] = time.monotonic() - t_start

    print(f"primitive_server benchmark ({'quick' if args.quick else 'full'}, loop_mode={args.loop_mode}, "
          f"fast_path true then false, load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs; 1-min "
          f"load average before the start {load_before:.2f}" + "".join(f", server {p}" for p in args.param)
          + "".join(f", sim_bridge {p}" for p in args.sim_param)
          + (f", subscribers SCHED_FIFO {args.subscriber_priority}" if args.subscriber_priority > 0 else "") + ")")
    print(f"{'metric':40s} value")
    for k, v in metrics.items():
        print(f"{k:40s} {v:.4g}" if isinstance(v, float) else f"{k:40s} {v}")
    keys = ["srv_p50_ms", "srv_p99_ms", "stream_hz", "stream_period_p99_err_ms", "stream_missed", "stream_lost",
            "limit_violations", "srv_p50_ms_plain", "srv_p99_ms_plain", "stream_period_p99_err_ms_plain",
            "stream_missed_plain", "limit_violations_plain"] + [f"{k}_fast_over_plain" for k in COMPARED]
    print(" ".join(f"{k}={metrics[k]:.4g}" if isinstance(metrics[k], float) else f"{k}={metrics[k]}" for k in keys))
    return 0


if __name__ == "__main__":
    sys.exit(main())
