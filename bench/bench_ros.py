"""Benchmark of primitive_server over real DDS, every party in its own process.

    python bench/bench_ros.py            # full: per mode 40 s stream, >= 1000 Condition calls, then random
                                         # executions (1000 with the fast path, 100 with plain rclpy)
    python bench/bench_ros.py --quick    # smoke run: per mode 2 s stream, 20 calls, 20 random executions
    python bench/bench_ros.py --sim-param joint_states_rate_hz:=250 --param gil_switch_interval:=0.0005

Processes: sim_bridge (PyBullet Gen3 lite, joint_states at 1 kHz), primitive_server (and, with
its default ``loop_process: true``, its control-loop child process), two stream subscribers, a
service client, a bare reference loop, and this orchestrator (action client).

Both modes of the server are measured in one run, one after the other against the same simulated
robot: ``fast_path: true`` (the default; the figures below without suffix) and ``fast_path: false``
(plain rclpy; the same figures with the suffix ``_plain``). ``<figure>_fast_over_plain`` is the
ratio of the two for the service round trip and the stream's period error (< 1: the fast path is
better), so the fast path has to keep earning its place.

The machine's own floor is measured in the same run, beside the figures it bounds: a near-empty
service (ListPrimitives) called by the same client between the Condition calls, and a bare
real-time loop running beside the stream. The ``*_ratio`` figures compare the server with it.

Metrics (last line: space-separated name=value pairs; the headline figures of both modes and the
ratios):

* ``srv_p50_ms``, ``srv_p99_ms`` -- Condition round trip (request with 5 via-points and the
  'object' context, preview 100 points) measured by the client process, which calls every 40 ms
  (25 calls/s) while the stream runs: from just before sending to the response taken (the client
  waits on an rcl wait set of its own, see role_client);
* ``srv_list_p50_ms``, ``srv_list_p99_ms`` -- the same client's ListPrimitives round trip, called
  half-way between two Condition calls (a handler that does next to nothing: the transport's and
  the server's dispatch share of a round trip under the same load);
  ``srv_floor_ratio`` = srv_p50_ms / srv_list_p50_ms (target <= 1.5);
* ``srv_handler_p50_ms``, ``srv_handler_p99_ms`` -- time inside the server's Condition callback
  (its log): the computation, without transport and executor dispatch;
* ``stream_hz`` -- joint_command messages received per second by the subscriber during one long
  Execute goal (arrival = the instant the subscriber process's DDS layer received the message,
  see role_subscriber: the Python measuring code neither delays nor loads the stream). The
  subscribers run as a real-time consumer (a controller) would: SCHED_FIFO ``--subscriber-priority``
  (default 50; 0 = normal scheduling); ``subscriber_fifo_priority`` says what it got (0 if refused);
* ``stream_period_p99_err_ms`` -- p99 over inter-arrival intervals of |interval - dt| (dt = 1 ms);
* ``stream_missed`` -- intervals longer than 1.5 dt (each is a command that arrived at least half a
  period late or not at all); ``stream_lost`` -- gaps in the commands' header.stamp (the nominal
  time of the tick, k dt): commands lost on the way plus the periods the server skipped after a tick
  that started more than a period late (its deadlines then restart from now, see execution.stream_loop);
* ``ref_loop_period_p99_err_ms``, ``ref_loop_missed`` (of ``ref_loop_intervals``) -- the same two
  figures for a bare 1 kHz Python loop (no ROS, no work, paced like the server's control thread,
  SCHED_FIFO at ``--subscriber-priority``) run in its own process during the stream: the machine's
  own floor for a real-time loop under this load; ``stream_missed_ratio`` = (stream_missed + 1) /
  (ref_loop_missed + 1) and ``stream_p99_ratio`` = stream_period_p99_err_ms /
  ref_loop_period_p99_err_ms (targets <= 1.5);
* ``server_period_p99_err_ms``, ``server_missed`` -- the same two figures from the server's own
  publication instants (its log): pacing alone, without transport and subscriber scheduling;
* ``cpu_<process>_pct`` -- CPU time of each process (user + system, /proc) per wall-clock second
  while the stream and the client ran, in % of one core (the machine has os.cpu_count());
  ``cpu_control_pct`` is the server's control-loop child process (``loop_process: true``);
* ``server_gc_count``, ``server_gc_max_ms`` -- cyclic garbage collections in the server and the
  longest (each holds the interpreter lock);
* ``executions``, ``executions_ok``, ``executions_expected_refused`` -- phase 2's random executions
  (see SCENARIOS and random_executions): goals sent, goals that ended with the result their scenario
  expects (SUCCESS, CANCELED or PREEMPTED), and goals sent to be refused (too fast for the velocity
  limits; ``executions_refused_ok`` of them were, with LIMIT_VIOLATION). executions_ok =
  executions - executions_expected_refused when every execution ended as expected
  (``exec_unexpected`` lists the others by scenario and code); ``exec_duration_p50_s``,
  ``exec_duration_max_s`` -- their goals' durations (1.3-1.6 times the shortest each handle allows);
* ``limit_violations`` -- every joint_command of both phases checked against the limits, each
  against the one received before it, across gaps too (limit_check: positions, velocities,
  accelerations and jerks from consecutive commands, a gap of k periods allowing k periods of
  motion), plus measured joint_states samples outside the URDF position limits by > 1e-4 rad;
  ``start_jumps`` are the violations where a stream starts again after it stopped at rest;
* ``max_jump_ratio`` -- largest |Δq| / (v_max Δt) over consecutive commands (Δt from their stamps;
  target <= 1);
* ``foreign_nodes`` -- nodes of other runs seen in this run's ROS domain after each phase (the domain
  is drawn at random among those where no node is seen at the start; another run drawing it later
  could answer this one's calls): 0 for figures to trust.

Length: over 400 lines because the script starts itself again for each measuring role
(``--role subscriber | client | reference_loop``, each in its own process): the orchestrator, the
roles, phase 2's scenarios and the figures computed from their recordings share its command line
and constants, and ``python bench/bench_ros.py`` stays the one thing to run. The rclpy internals
it relies on are in :mod:`deepprompt_ros.ros.fastpath` (``polled.take_all``,
``service_client.BlockingClient``).
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

    stamp, q, qd = _decode_joint_states([b for _, b in rec["cmd"]])
    _save(out, t=np.array([t for t, _ in rec["cmd"]], dtype=np.int64) * 1e-9, stamp=stamp, q=q, qd=qd,
          js=_decode_joint_states([b for _, b in rec.get("js", [])])[1])
    node.destroy_node()
    rclpy.try_shutdown()


def _decode_joint_states(records: list, width: int = 6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Serialized sensor_msgs/JointState messages (one joint-name layout, that of the first) -> header
    stamps in ns (N,), positions and velocities (N, width; velocities NaN where a message has none).
    Read in place with ros.fastpath.wire.CommandReader (a phase-2 recording holds millions of messages)."""
    import struct

    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState

    from deepprompt_ros.ros.fastpath.wire import CommandReader

    stamp = np.zeros(len(records), dtype=np.int64)
    q = np.full((len(records), width), np.nan)
    qd = np.full((len(records), width), np.nan)
    if records:
        read = CommandReader(list(deserialize_message(records[0], JointState).name), "the recorded joints")
        for i, data in enumerate(records):
            sec, nanosec = struct.unpack_from("<iI", data, 4)  # after the CDR encapsulation header
            stamp[i] = sec * 1_000_000_000 + nanosec
            q[i], v = read(data)
            if v is not None:
                qd[i] = v
    return stamp, q, qd


#: where the 'object' contexts are drawn (x, y, z ranges in m, base frame): the box of the shipped reach's
#: demonstrations (sim.tasks.kinematic_reach.reach_demos), the objects a planner asks it to reach
OBJECT_BOX = ((0.25, 0.45), (-0.2, 0.2), (0.02, 0.15))


def _random_context(rng):
    """An 'object' context (deepprompt_msgs/Context) uniform in :data:`OBJECT_BOX`."""
    from deepprompt_msgs.msg import Context

    return Context(modality="object", values=[float(rng.uniform(lo, hi)) for lo, hi in OBJECT_BOX])


def _condition_request(rng, home, n_via: int = 5):
    """Condition 'reach' on ``n_via`` random via-points near ``home`` (N(0, 0.05) rad per joint, phases
    U(0, 1)) and a random context (:func:`_random_context`); a 100-point preview. The client's timed
    request (the cost of conditioning does not depend on where the via-points are: its handle is never
    executed) and, with no via-point, phase 1's execution."""
    from deepprompt_msgs.srv import Condition

    from deepprompt_ros.ros import conversions as conv

    x = np.sort(rng.uniform(0, 1, n_via))
    y = home + rng.normal(0, 0.05, (n_via, 6))
    return Condition.Request(primitive="reach", via_points=conv.via_points_to_msgs(x, y),
                             contexts=[_random_context(rng)], preview_points=100)


CALL_PERIOD = 0.04  # s between the starts of two Condition calls (25 calls/s, a busy planner)


def role_client(out: str, gate: str, seconds: float, min_calls: int) -> None:
    """From the file <gate>.go on, call Condition every CALL_PERIOD s and, half a period after each,
    ListPrimitives (a handler that does next to nothing: the transport's and the server's dispatch
    share of a round trip), for ``seconds`` and at least ``min_calls`` Condition calls (back to back
    when calls take longer); record the round trips of both.

    Interleaved, the two services see the same machine and the same load at the same time, so
    the ratio of their round trips says how much of a Condition call is the handler's own. Round
    trip: from just before the request is sent to the moment its response has been taken in this
    process. The client waits on its own rcl wait set (what an rclpy executor does inside, without
    the executor's per-wake bookkeeping; see ros.fastpath.service_client) and sleeps between calls.
    """
    from deepprompt_msgs.srv import Condition, ListPrimitives

    from deepprompt_ros.robots.spec import load_robot
    from deepprompt_ros.ros.fastpath.service_client import BlockingClient

    rclpy, node, _ = _role_node("bench_condition_client")  # its executor is never spun: the client waits itself
    clients = {name: BlockingClient(node, srv_type, f"{SERVER}/{name}")
               for name, srv_type in (("condition", Condition), ("list_primitives", ListPrimitives))}
    for cli in clients.values():
        cli.wait_for_service(timeout=60)
    home = load_robot("gen3_lite").home

    pathlib.Path(gate + ".ready").write_text("ready")
    _wait_file(pathlib.Path(gate + ".go"))
    rng = np.random.default_rng(1)
    rtt = {name: [] for name in clients}
    fails = {name: 0 for name in clients}
    end = time.monotonic() + seconds
    next_call = time.monotonic()
    while time.monotonic() < end or len(rtt["condition"]) < min_calls:
        for name, cli in clients.items():
            req = _condition_request(rng, home) if name == "condition" else ListPrimitives.Request()
            time.sleep(max(0.0, next_call - time.monotonic()))
            next_call += CALL_PERIOD / 2
            t0 = time.perf_counter()
            res = cli.call(req)
            rtt[name].append(time.perf_counter() - t0)
            fails[name] += not res.success
    _save(out, rtt=np.array(rtt["condition"]), fails=fails["condition"], rtt_list=np.array(rtt["list_primitives"]),
          fails_list=fails["list_primitives"])
    for cli in clients.values():
        cli.destroy()
    node.destroy_node()
    rclpy.try_shutdown()


# ------------------------------------------------------------------------------------------------
# orchestrator
# ------------------------------------------------------------------------------------------------
class Orchestrator:
    """The benchmark's own client: Condition, Blend, SetPhaseRate and the Execute action (an
    rclpy executor spun in this thread)."""

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

    def blend(self, handle_a, handle_b, phases=(), weights=(), preview_points=100):
        from deepprompt_msgs.srv import Blend

        return self.c.call(Blend, f"{SERVER}/blend", Blend.Request(
            handle_a=handle_a, handle_b=handle_b, schedule_phases=list(phases), schedule_weights=list(weights),
            preview_points=preview_points))

    def set_rate(self, rate):
        from deepprompt_msgs.srv import SetPhaseRate

        return self.c.call(SetPhaseRate, f"{SERVER}/set_phase_rate", SetPhaseRate.Request(phase_rate=rate))

    def send(self, handle, duration, reverse=False, feedback=None):
        """Send a goal (accepted by the server, which ends a refused one at once with its code);
        returns (goal handle, result future)."""
        fut = self.ac.send_goal_async(self.Execute.Goal(handle=handle, duration=duration, reverse=reverse),
                                      feedback_callback=feedback)
        if not self.c.wait_for(fut.done, 10):
            raise RuntimeError("the Execute goal was not answered within 10 s")
        gh = fut.result()
        return gh, gh.get_result_async()

    def wait(self, res_fut, timeout):
        self.c.wait_for(res_fut.done, timeout)
        return res_fut.result().result if res_fut.done() else None

    def close(self):
        self.ac.destroy()
        self.c.close()


# ------------------------------------------------------------------------------------------------
# phase 2: random executions
# ------------------------------------------------------------------------------------------------
#: scenario of a random execution -> probability. What each does and the result it expects:
#: finish / reverse -- run to the end (reverse: phase 1 -> 0): SUCCESS;
#: cancel -- canceled 0.05-0.4 s after it was sent (at most half its duration): CANCELED;
#: preempt -- the next execution's goal is sent 0.05-0.4 s after it (at most half its duration): PREEMPTED;
#: rate -- once moving, SetPhaseRate to a random rate (negative: a reversal; the server refuses one
#:   too fast for the velocity limits and the goal keeps its rate), then canceled (CANCELED, 7 in 10) or given
#:   back its own rate and run to the end (SUCCESS); the waits keep the phase below about 0.6 before
#:   the last request, so the goal still runs when it arrives;
#: too_fast -- a duration half the shortest the velocity limits allow: refused, LIMIT_VIOLATION (the
#:   one scenario expected to fail; the running goal, if any, is not affected).
SCENARIOS = {"finish": 0.04, "reverse": 0.02, "cancel": 0.35, "preempt": 0.4, "rate": 0.14, "too_fast": 0.05}


def min_duration(preview, limits, config, periodic: bool = False) -> float:
    """Shortest duration the server accepts for a handle whose preview (deepprompt_msgs/Preview) was
    asked on its execution grid (``config.execution_grid_points`` phases): the velocity check of
    plan_execution on the same trajectory (execution.plan.ExecutionReference's differences, the joints
    matched by name). A coarser preview (at least 3 phases) gives an estimate, lower by the peaks its
    grid misses. ``periodic``: a rhythmic primitive's preview."""
    from deepprompt_ros.execution.plan import ExecutionReference

    mean = np.array(preview.mean, dtype=float).reshape(preview.n_points, preview.n_joints)
    v_max = dict(zip(limits.names, limits.max_velocity))
    ref = ExecutionReference(mean, periodic, config.derivative_step)
    return ref.shortest_duration([v_max[name] for name in preview.joint_names])


class _Execution:
    """One goal of phase 2: its scenario, expected result code and latest feedback."""

    def __init__(self, kind: str, expected: int, duration: float):
        self.kind, self.expected, self.duration = kind, expected, duration
        self.phase = None   # latest feedback phase (None before the first)
        self.gh = self.fut = None

    def feedback(self, msg) -> None:
        self.phase = float(msg.feedback.phase)

    def moving(self) -> bool:
        """The phase clock has left its start (the approach to the primitive's start is over)."""
        start = 1.0 if self.kind == "reverse" else 0.0
        return self.phase is not None and abs(self.phase - start) > 1e-9


#: a planner's via-points in phase 2 (planner_request): at most this many per request
PLANNER_MAX_VIA = 3
#: ... each at least this far (rad) inside the position limits
PLANNER_VIA_MARGIN = 0.05


def planner_request(orch, rng, limits, config):
    """A Condition request as a planner makes one to adapt the motion it is about to execute: a random
    context (:func:`_random_context`) and 1-:data:`PLANNER_MAX_VIA` via-points near the motion that
    context gives, asked of the server first (Condition with the context alone, a 101-point preview).

    Each via-point is at a random phase inside its own n-th of [0.05, 0.95] (its middle half: the
    via-points are well apart, as a planner's waypoints are) and is the context's mean there plus
    N(0, std²) per joint (std: the preview's at that phase, the spread the primitive itself gives the
    motion), at least :data:`PLANNER_VIA_MARGIN` rad inside the position limits. The offsets follow
    the primitive's own spread, not a fixed size: the served reach meets via-points exactly (its
    linear latent block is conditioned exactly), and given its context its spread is a few mrad, so a
    via-point a few 0.01 rad off is met with a detour that needs tens of seconds at the velocity limits.

    Returns the request (context and via-points, a preview on the execution grid: the shortest
    duration the server accepts, exactly)."""
    from deepprompt_msgs.srv import Condition

    from deepprompt_ros.ros import conversions as conv

    context = _random_context(rng)
    r = orch.condition(Condition.Request(primitive="reach", contexts=[context], preview_points=101))
    if not r.success:
        raise RuntimeError(f"Condition with a context alone failed: {r.message}")
    prev = conv.preview_from_msg(r.preview)
    n = int(rng.integers(1, PLANNER_MAX_VIA + 1))
    edges = np.linspace(0.05, 0.95, n + 1)
    x = edges[:-1] + (edges[1:] - edges[:-1]) * rng.uniform(0.25, 0.75, n)
    mean = np.stack([np.interp(x, prev.phases, prev.mean[:, j]) for j in range(prev.mean.shape[1])], axis=1)
    std = np.stack([np.interp(x, prev.phases, prev.std[:, j]) for j in range(prev.std.shape[1])], axis=1)
    index = [list(limits.names).index(name) for name in prev.joint_names]  # the preview's (model's) order
    y = np.clip(mean + rng.standard_normal(mean.shape) * std, limits.lower[index] + PLANNER_VIA_MARGIN,
                limits.upper[index] - PLANNER_VIA_MARGIN)
    return Condition.Request(primitive="reach", via_points=conv.via_points_to_msgs(x, y), contexts=[context],
                             preview_points=config.execution_grid_points)


def random_executions(orch, rng, n: int, limits, config) -> dict:
    """``n`` random executions, one after the other (a preempting goal is the next execution), each
    conditioned as a planner conditions (:func:`planner_request`: a random context and 1-3 via-points
    near the motion it gives), a quarter of them blended with the previous handle (Blend, linear
    hand-over); scenarios from SCENARIOS, durations 1.3-1.6 times the shortest the handle's preview
    allows. Returns the figures: executions, executions_ok (ended with the code their scenario
    expects, SUCCESS / CANCELED / PREEMPTED), executions_expected_refused (too_fast),
    executions_refused_ok (of those, refused with LIMIT_VIOLATION), exec_unexpected (scenario:code
    counts of the others), exec_codes (all result codes), set_rate_codes (SetPhaseRate responses),
    exec_duration_p50_s / exec_duration_max_s (of the goals not sent too fast), exec_wall_s."""
    from deepprompt_msgs.msg import ResultCode as RC

    kinds, probs = list(SCENARIOS), np.array(list(SCENARIOS.values()))
    expect = {"finish": RC.SUCCESS, "reverse": RC.SUCCESS, "cancel": RC.CANCELED, "preempt": RC.PREEMPTED,
              "too_fast": RC.LIMIT_VIOLATION}
    done, codes, rate_codes = [], {}, {}
    last_handle, preempted = None, None
    t0 = time.monotonic()

    def count(table, key):
        table[key] = table.get(key, 0) + 1

    def spin(seconds):
        orch.c.spin_for(seconds)

    def finish(ex, timeout):
        res = orch.wait(ex.fut, timeout)
        ex.code = int(res.code.value) if res is not None else -1
        done.append(ex)

    for i in range(n):
        kind = str(rng.choice(kinds, p=probs / probs.sum()))
        if kind == "too_fast" and preempted is not None:
            kind = "finish"  # a refused goal would not preempt the running one
        if kind == "preempt" and i == n - 1:
            kind = "cancel"  # the last execution has no successor
        # the preview on the execution grid: the shortest duration the server accepts, exactly
        r = orch.condition(planner_request(orch, rng, limits, config))
        if not r.success:
            raise RuntimeError(f"Condition failed: {r.message}")
        handle, preview = r.handle, r.preview
        if last_handle is not None and rng.random() < 0.25:
            b = orch.blend(r.handle, last_handle, preview_points=config.execution_grid_points)
            if not b.success:
                raise RuntimeError(f"Blend failed: {b.message}")
            handle, preview = b.handle, b.preview
        last_handle = r.handle
        t_min = min_duration(preview, limits, config)
        duration = 0.5 * t_min if kind == "too_fast" else t_min * float(rng.uniform(1.3, 1.6))
        ex = _Execution(kind, expect.get(kind, RC.SUCCESS), duration)
        ex.gh, ex.fut = orch.send(handle, duration, reverse=kind == "reverse", feedback=ex.feedback)
        if preempted is not None:  # its result (PREEMPTED) is collected at the end
            done.append(preempted)
            preempted = None
        if kind == "too_fast":
            finish(ex, 10.0)
        elif kind in ("finish", "reverse"):
            finish(ex, 3 * duration + 20.0)
        elif kind in ("cancel", "preempt"):
            spin(min(float(rng.uniform(0.05, 0.4)), 0.5 * duration))
            if kind == "preempt":
                preempted = ex
                continue
            ex.gh.cancel_goal_async()
            finish(ex, 20.0)
        else:  # rate
            orch.c.wait_for(ex.moving, 20.0)
            spin(min(float(rng.uniform(0.05, 0.2)), 0.2 * duration))
            res = orch.set_rate(float(rng.uniform(-1.5, 1.5)) / duration)
            count(rate_codes, str(res.code.value))
            spin(min(float(rng.uniform(0.05, 0.2)), 0.2 * duration))
            if rng.random() < 0.7:
                ex.expected = RC.CANCELED
                ex.gh.cancel_goal_async()
                finish(ex, 20.0)
            else:
                res = orch.set_rate(1.0 / duration)
                count(rate_codes, str(res.code.value))
                finish(ex, 3 * duration + 20.0)
    for ex in done:
        if ex.kind == "preempt":  # ended when its successor started
            res = orch.wait(ex.fut, 10.0)
            ex.code = int(res.code.value) if res is not None else -1
    for ex in done:
        count(codes, str(ex.code))
    refused = [ex for ex in done if ex.kind == "too_fast"]
    ok = [ex for ex in done if ex.kind != "too_fast" and ex.code == ex.expected]
    refused_ok = [ex for ex in refused if ex.code == ex.expected]
    unexpected = {}
    for ex in done:
        if ex.code != ex.expected:
            count(unexpected, f"{ex.kind}:{ex.code}")
    durations = [ex.duration for ex in done if ex.kind != "too_fast"] or [float("nan")]
    return dict(executions=len(done), executions_ok=len(ok), executions_expected_refused=len(refused),
                executions_refused_ok=len(refused_ok), executions_unexpected=len(done) - len(ok) - len(refused_ok),
                exec_unexpected=json.dumps(unexpected, sort_keys=True).replace(" ", ""),
                exec_codes=json.dumps(codes, sort_keys=True).replace(" ", ""),
                set_rate_codes=json.dumps(rate_codes, sort_keys=True).replace(" ", ""),
                exec_duration_p50_s=float(np.median(durations)), exec_duration_max_s=float(np.max(durations)),
                exec_wall_s=time.monotonic() - t0)


#: the nodes this benchmark starts; any other node in its ROS domain belongs to another run that drew
#: the same random domain (its calls could reach the wrong server)
OWN_NODES = {"sim_bridge", "primitive_server", "primitive_server_control", "bench_stream_subscriber",
             "bench_condition_client", "bench_orchestrator"}


def quiet_domain_env(log_dir: pathlib.Path, tries: int = 5) -> dict:
    """isolated_ros_env on a random ROS domain in which no node is discovered within 2 s (another
    run on the machine may have drawn the same domain); the last one tried if every one is busy."""
    from deepprompt_ros.ros.testing import RosTestClient, isolated_ros_env

    for _ in range(tries):
        env = isolated_ros_env(log_dir)
        probe = RosTestClient(env, "bench_domain_probe")
        try:
            probe.spin_for(2.0)
            others = [n for n in probe.node.get_node_names() if n != "bench_domain_probe"]
        finally:
            probe.close()
        if not others:
            break
        print(f"ROS domain {env['ROS_DOMAIN_ID']} is in use ({', '.join(sorted(others)[:5])}); trying another",
              flush=True)
    return env


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


def limit_check(data, dt, limits, measured: bool = True) -> dict:
    """Limits of a recorded joint_command stream, every command against the one received before
    it, across gaps too (execution.limits.check_limits with the commands' stamps as sample times:
    a gap of k periods -- between executions, or where commands were lost or the control loop
    skipped ticks -- allows k dt v_max of motion), and, if ``measured``, the recorded joint_states
    against the URDF position limits (1e-4 rad).

    The time between two commands is their stamps' difference in whole periods (at least one):
    the stamps are the ticks' nominal times, k dt apart when k - 1 commands were lost, and more than
    two periods apart after a tick that started late (one period of motion then); rounding down
    allows no more motion than the stamps do. A stamp not after the one before is a violation too
    (that command is left out of the check).

    Returns violations (commanded samples beyond a limit + disordered stamps), the measured ones,
    the commands checked, max_jump_ratio (largest |Δq| / (v_max Δt) between consecutive commands),
    start_jumps (of the violations, commands that start a stream again after it stopped at rest --
    both at zero velocity, more than one period apart -- farther from the last command than the
    velocity limits allow in between) with the largest such jump, and the report's other ratios."""
    from deepprompt_ros.execution.limits import check_limits

    q, qd, stamp = data["q"], data["qd"], data["stamp"]
    out = dict(commands=int(q.shape[0]), violations=0, max_jump_ratio=0.0, start_jumps=0, start_jump_max_rad=0.0,
               velocity_ratio=0.0, fd_acceleration_ratio=0.0, jerk_ratio=0.0, position_excess=0.0)
    if q.shape[0] >= 2:
        keep = np.r_[True, stamp[1:] > np.maximum.accumulate(stamp)[:-1]]
        q, qd, stamp = q[keep], qd[keep], stamp[keep]
        periods = np.maximum(np.round(np.diff(stamp) / (dt * 1e9)), 1.0)
        t = np.r_[0.0, np.cumsum(periods)] * dt
        rep = check_limits(q, qd, None, dt, limits, t=t)
        jump = np.abs(np.diff(q, axis=0)) / (periods[:, None] * dt) / limits.max_velocity
        start = (periods > 1) & ~qd[:-1].any(1) & ~qd[1:].any(1)
        bad_start = start & (jump > 1 + 1e-6).any(1)
        out.update(violations=rep.violations + int((~keep).sum()), max_jump_ratio=rep.fd_velocity_ratio,
                   start_jumps=int(bad_start.sum()),
                   start_jump_max_rad=float(np.abs(np.diff(q, axis=0))[bad_start].max()) if bad_start.any() else 0.0,
                   velocity_ratio=rep.velocity_ratio, fd_acceleration_ratio=rep.fd_acceleration_ratio,
                   jerk_ratio=rep.jerk_ratio, position_excess=rep.position_excess)
    if measured:
        js = data["js"]
        excess = np.maximum(np.maximum(limits.lower - js, js - limits.upper), 0.0).max(1) if js.size else np.zeros(0)
        out.update(measured_violations=int((excess > 1e-4).sum()),
                   measured_position_excess=float(excess.max()) if excess.size else 0.0)
    return out


#: the figures printed for both modes and compared as fast path / plain rclpy (last line)
COMPARED = ("srv_p50_ms", "srv_p99_ms", "stream_period_p99_err_ms")


def floor_ratios(m: dict) -> dict:
    """The figures as fractions of the machine's floor measured beside them (targets <= 1.5):
    srv_floor_ratio = Condition p50 / ListPrimitives p50 (same client, interleaved);
    stream_missed_ratio = (stream missed + 1) / (reference loop missed + 1);
    stream_p99_ratio = stream p99 period error / the reference loop's."""
    ref = m["ref_loop_period_p99_err_ms"]
    return dict(srv_floor_ratio=m["srv_p50_ms"] / m["srv_list_p50_ms"] if m["srv_list_p50_ms"] > 0 else float("nan"),
                stream_missed_ratio=(m["stream_missed"] + 1) / (m["ref_loop_missed"] + 1),
                stream_p99_ratio=m["stream_period_p99_err_ms"] / ref if ref > 0 else float("nan"))


def measure(args, env, tmp: pathlib.Path, prim_file: pathlib.Path, spec, limits, fast_path: bool,
            procs: list) -> dict:
    """One primitive_server (``fast_path`` as given) measured against the running sim_bridge: phase 1
    (one long execution; the stream subscriber, the Condition / ListPrimitives client and the
    reference loop, each in its own process) and phase 2 (random executions, limits). Every process
    started here is appended to ``procs`` and stopped before returning."""
    from deepprompt_ros.ros.testing import NodeProcess
    from deepprompt_ros.server.config import ServerConfig

    dt = 1.0 / spec.control_rate_hz
    # the server's execution grid (its defaults unless --param sets them): phase 2's shortest durations
    given = dict(p.split(":=", 1) for p in args.param)
    server_config = ServerConfig(**{k: type(getattr(ServerConfig, k))(given[k])
                                    for k in ("execution_grid_points", "derivative_step") if k in given})
    stream_s, calls = (2.0, 20) if args.quick else (40.0, 1000)
    n_exec = args.executions if fast_path else args.executions_plain
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
        g_sub, g_cli, g_sub2, g_ref = tmp / "stream", tmp / "client", tmp / "limits", tmp / "reference"
        prio = ["--priority", str(args.subscriber_priority)]
        sub = start_role("subscriber", tmp / "stream.npz", g_sub, prio)
        cli = start_role("client", tmp / "client.npz", g_cli, ["--seconds", str(stream_s), "--calls", str(calls)])
        sub2 = start_role("subscriber", tmp / "limits.npz", g_sub2, ["--states"] + prio)
        ref = start_role("reference_loop", tmp / "reference.npz", g_ref, prio)
        orch = Orchestrator(env)
        end = time.monotonic() + 60
        while "receiving joint_states" not in server.output():
            if time.monotonic() > end:
                raise RuntimeError("primitive_server receives no joint_states:\n" + server.output_tail() + "\n"
                                   + procs[0].output_tail())
            time.sleep(0.1)

        # ---- phase 1: one long execution; subscriber, client and reference loop in their own processes
        for g in (g_sub, g_cli, g_sub2, g_ref):
            wait_ready(g)
        rng = np.random.default_rng(0)
        # a random context and no via-point: random via-points can take a reach that follows them exactly
        # outside the position limits (refused), and this execution must stream
        req = _condition_request(rng, spec.home, 0)
        req.preview_points = server_config.execution_grid_points
        r = orch.condition(req)
        assert r.success, r.message
        go(g_sub)
        go(g_ref)
        # long enough for the stream's measurement, and at most 1/1.3 of the speed the limits allow
        duration = max(stream_s + 1.5, 1.3 * min_duration(r.preview, limits, server_config))
        gh, res_fut = orch.send(r.handle, duration)
        orch.c.spin_for(0.5)
        roles = {"sim_bridge": procs[0], "server": server, "subscriber": sub, "client": cli, "reference_loop": ref}
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
        res = orch.wait(res_fut, duration + 30)
        go(g_sub, "stop")
        go(g_ref, "stop")
        stream = _load(tmp / "stream.npz", sub, 60)
        metrics = stream_metrics(stream, dt)
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
        if found:
            metrics.update(srv_handler_p50_ms=float(found[-1][0]), srv_handler_p99_ms=float(found[-1][1]))
        found = re.findall(r"(\d+) garbage collections .*?, ([\d.]+) ms in total, longest ([\d.]+) ms", server.output())
        if found:  # in the server process since its start-up objects were frozen
            metrics.update(server_gc_count=int(found[-1][0]), server_gc_max_ms=float(found[-1][2]))
        rtt, rtt_list = client["rtt"] * 1e3, client["rtt_list"] * 1e3
        metrics.update(srv_p50_ms=float(np.percentile(rtt, 50)), srv_p99_ms=float(np.percentile(rtt, 99)),
                       srv_calls=int(rtt.size), srv_failures=int(client["fails"]),
                       srv_list_p50_ms=float(np.percentile(rtt_list, 50)),
                       srv_list_p99_ms=float(np.percentile(rtt_list, 99)),
                       srv_list_calls=int(rtt_list.size), srv_list_failures=int(client["fails_list"]),
                       long_goal_code=int(res.code.value) if res is not None else -1,
                       **{f"cpu_{k}_pct": 100 * v for k, v in cpu.items()})
        metrics.update(floor_ratios(metrics))
        foreign = set(orch.c.node.get_node_names()) - OWN_NODES

        # ---- phase 2: random executions; the second subscriber records commands and joint states
        go(g_sub2)
        metrics.update(random_executions(orch, rng, n_exec, limits, server_config))
        orch.c.spin_for(0.5)
        go(g_sub2, "stop")
        # another run's nodes in this domain (drawn at random; seen after each phase) make every figure suspect
        foreign = sorted(foreign | (set(orch.c.node.get_node_names()) - OWN_NODES))
        metrics.update(foreign_nodes=len(foreign), foreign_node_names=",".join(foreign) or "-")
        # every command of both phases checked (phase 1's long execution and phase 2's recording)
        checks = [limit_check(stream, dt, limits, measured=False),
                  limit_check(_load(tmp / "limits.npz", sub2, 120 + 0.2 * n_exec), dt, limits)]
        metrics.update(limit_violations=sum(c["violations"] for c in checks) + checks[1]["measured_violations"],
                       limit_violations_measured=checks[1]["measured_violations"],
                       commands_checked=sum(c["commands"] for c in checks),
                       max_jump_ratio=max(c["max_jump_ratio"] for c in checks),
                       start_jumps=sum(c["start_jumps"] for c in checks),
                       start_jump_max_rad=max(c["start_jump_max_rad"] for c in checks),
                       **{f"worst_{k}": max(c[k] for c in checks) for k in (
                           "velocity_ratio", "fd_acceleration_ratio", "jerk_ratio", "position_excess")},
                       worst_measured_position_excess=checks[1]["measured_position_excess"])
        return metrics
    finally:
        if orch is not None:
            orch.close()
        NodeProcess.stop_all(mine)


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
    ap.add_argument("--executions", type=int, metavar="N",
                    help="random executions of phase 2 with the fast path (default 1000; --quick: 20)")
    ap.add_argument("--executions-plain", type=int, metavar="N",
                    help="random executions of phase 2 with plain rclpy (default 100; --quick: 20)")
    ap.add_argument("--priority", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--role", choices=("subscriber", "client", "reference_loop"), help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    ap.add_argument("--seconds", type=float, default=0.0, help=argparse.SUPPRESS)
    ap.add_argument("--calls", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--gate", help=argparse.SUPPRESS)
    ap.add_argument("--states", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.executions is None:
        args.executions = 20 if args.quick else 1000
    if args.executions_plain is None:
        args.executions_plain = 20 if args.quick else 100
    if args.role:  # SIGINT (the orchestrator's stop) ends a role even if it was started with SIGINT ignored
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if args.role == "subscriber":
        role_subscriber(args.out, args.gate, args.states, args.priority)
        return 0
    if args.role == "reference_loop":
        role_reference_loop(args.out, args.gate, args.priority, 1e-3)
        return 0
    if args.role == "client":
        role_client(args.out, args.gate, args.seconds, args.calls)
        return 0

    from deepprompt_ros.robots.spec import load_robot
    from deepprompt_ros.server.config import ServerConfig, robot_limits
    from deepprompt_ros.ros.testing import NodeProcess

    # SIGTERM (kill, timeout) ends the run like an error: the finally below stops every process started
    # (rclpy, initialized later by the Orchestrator, calls this handler from its own)
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))

    load_before = os.getloadavg()[0]  # other work on the machine (this benchmark adds ~1 when it runs)
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="bench_ros_"))
    env = quiet_domain_env(tmp / "log")
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
        NodeProcess.stop_all(procs)
    metrics.update({f"{k}_plain": v for k, v in plain.items()})
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
    keys = ["srv_p50_ms", "srv_p99_ms", "srv_list_p50_ms", "srv_floor_ratio", "stream_hz", "stream_period_p99_err_ms",
            "stream_missed", "stream_lost", "ref_loop_period_p99_err_ms", "ref_loop_missed", "stream_missed_ratio",
            "stream_p99_ratio", "limit_violations", "max_jump_ratio", "executions", "executions_ok",
            "executions_expected_refused"]
    keys += [f"{k}_plain" for k in keys] + [f"{k}_fast_over_plain" for k in COMPARED]
    print(" ".join(f"{k}={metrics[k]:.4g}" if isinstance(metrics[k], float) else f"{k}={metrics[k]}" for k in keys))
    return 0


if __name__ == "__main__":
    sys.exit(main())
