"""The control-rate execution loop of the primitive server (no rclpy import: publishing is
injected as callables, so the loop runs and is tested without ROS).

Per control tick (period dt = 1 / control rate):

1. the sample that is due now is popped from the look-ahead buffer and published on the
   per-tick command output (``publish_command``);
2. commands from other threads are applied (new goal -> splice, cancel -> brake, phase-rate
   change), joint-state staleness and the tracking-error bound are checked;
3. ONE new sample, ``lookahead_ticks`` periods ahead, is computed: the phase clock gives
   x = τ(t), the dense grid of the executed mean gives the reference (q, q̇, q̈) at x
   (:class:`~deepprompt_ros.execution.plan.ExecutionReference`), and Ruckig
   (:class:`~deepprompt_ros.execution.ruckig_streamer.RuckigStreamer`) turns it into a command within the
   velocity, acceleration, jerk and position limits;
4. every 1/trajectory_rate a snapshot of the buffered future samples goes to a second thread that
   builds the JointTrajectory message (slow in Python: ~0.1 ms per point) off the critical path.

Because the buffer holds the future samples, each JointTrajectory message is a piece of the one
command stream (successive messages agree where they overlap, so a controller that replaces its
trajectory on every message sees no jump), and everything that changes the motion takes effect
``lookahead_ticks`` periods later. Stage of a goal: APPROACH (move to the primitive's start with
the clock held, only when farther than ``approach_tolerance``), RUN (clock running), SETTLE
(clock done, converging onto the end state), STOPPING (cancel, stale joint_states, tracking error:
every joint brakes time-optimally within its limits), then the goal's outcome is delivered when
its last sample has been published.

Timing: the 'thread' mode paces ticks on absolute time.perf_counter deadlines (no drift). A tick
that starts more than one period late is not made up with a burst: the deadlines restart from
now, so on an overloaded machine the motion stretches in time while every sample still keeps the
limits with respect to the one before it (commands carry the nominal tick time as header.stamp,
so a consumer can see the gap). The robot state is read from the node's subscription every
``state_poll`` seconds in this thread (see :class:`StreamLoop`).
"""
from __future__ import annotations

import collections
import enum
import math
import threading
import time
from typing import Callable, NamedTuple

import numpy as np

from deepprompt_ros.execution.plan import ExecutionPlan
from deepprompt_ros.server.config import ServerConfig
from deepprompt_ros.server.requests import Code, RequestError
from deepprompt_ros.execution.limits import JointLimits
from deepprompt_ros.execution.ruckig_streamer import RuckigStreamer, StreamStatus

__all__ = ["Stage", "Outcome", "Progress", "MeasuredState", "Sample", "Snapshot", "ExecutionGoal",
           "ExecutionController", "StreamLoop", "LoopStats", "BrakeTail", "trajectory_points"]


class Stage(enum.Enum):
    APPROACH = "approach"
    RUN = "run"
    SETTLE = "settle"
    STOPPING = "stopping"
    DONE = "done"


class Outcome(NamedTuple):
    """Result of one goal (the Execute result fields)."""

    code: Code
    message: str
    max_tracking_error: float
    final_phase: float
    cycles_completed: int


class Progress(NamedTuple):
    """Execute feedback: phase and cycle of the sample published last."""

    phase: float
    cycle: int
    phase_rate: float
    tracking_error: float


class MeasuredState(NamedTuple):
    """Robot joint state in robot joint order; ``stamp`` = time.monotonic() at reception."""

    q: np.ndarray
    qd: np.ndarray | None
    stamp: float


class Sample(NamedTuple):
    """One command sample (robot joint order) and what it belongs to."""

    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    goal: "ExecutionGoal | None"
    progress: Progress | None
    finishes: tuple  # ((goal, Outcome), ...) delivered once this sample is published


class Snapshot(NamedTuple):
    """Future samples for one JointTrajectory message: sample i is due at t0 + times[i]."""

    t0: float                   # time.perf_counter() of the first sample's due time minus dt
    times: np.ndarray           # (P,) seconds after t0, strictly increasing
    q: np.ndarray               # (P, d)
    qd: np.ndarray
    qdd: np.ndarray


class ExecutionGoal:
    """Shared between the action callback (waits, reads progress, requests cancel) and the loop."""

    def __init__(self, plan: ExecutionPlan, goal_id: str = ""):
        self.plan = plan
        self.goal_id = goal_id
        self.done = threading.Event()
        self.outcome: Outcome | None = None
        self._progress = Progress(plan.start_phase, 0, 0.0, 0.0)  # of the sample published last
        self._tracking_error = 0.0                                # at that sample
        self.stage = Stage.APPROACH
        self.max_tracking_error = 0.0

    @property
    def progress(self) -> Progress:
        """Phase, cycle, phase rate and tracking error of the sample published last."""
        p, e = self._progress, self._tracking_error  # (may pair a sample with its predecessor's error)
        return p if p.tracking_error == e else p._replace(tracking_error=e)

    def _finish(self, outcome: Outcome) -> None:
        if self.outcome is None:
            self.outcome = outcome
            self.stage = Stage.DONE
            self.done.set()


class _Active:
    """Loop-side state of the running goal."""

    def __init__(self, goal: ExecutionGoal, dt: float):
        self.goal = goal
        self.plan = goal.plan
        self.clock = goal.plan.make_clock(dt)
        self.stage = Stage.APPROACH
        self.stop_reason: tuple[Code, str] | None = None
        self.settle_ticks = 0
        self.error_ticks = 0
        self.start_q = self.plan.reference.state(self.plan.start_phase, 0.0, 0.0)[0]

    def reference(self, ahead: float):
        """(q, q̇, q̈) of the reference ``ahead`` seconds after the clock's current tick."""
        p = self.clock.peek(ahead)
        return self.plan.reference.state(p.x, p.x_dot, p.x_ddot)


class ExecutionController:
    """Tick-by-tick state machine of the command stream (single-threaded; see StreamLoop).

    Parameters
    ----------
    limits : JointLimits (robot joint order)
    dt : float
    config : ServerConfig
    """

    SETTLE_TIMEOUT = 30.0  # s; a goal that does not come to rest by then ends with INTERNAL_ERROR
    MAX_ERROR_TICKS = 100  # consecutive ruckig failures (each braking one tick) before aborting

    def __init__(self, limits: JointLimits, dt: float, config: ServerConfig):
        self.limits = limits
        self.dt = float(dt)
        self.config = config
        self.n_ahead = int(config.lookahead_ticks)
        self.streamer = RuckigStreamer(limits, dt, horizon=max(config.tracking_horizon, dt),
                                       approach_above=max(0.1, 2 * config.tracking_horizon),
                                       position_margin=np.minimum(
                                           config.position_margin,
                                           0.49 * (np.asarray(limits.upper) - np.asarray(limits.lower))))
        self.buffer: collections.deque[Sample] = collections.deque()
        self.active: _Active | None = None
        self.last_command: np.ndarray | None = None
        self.tracking_error = 0.0
        self._compared: MeasuredState | None = None
        self.errors = 0          # ticks on which ruckig rejected the input (braked instead)
        self.last_error = ""

    # ------------------------------------------------------------------ state
    @property
    def idle(self) -> bool:
        """No goal, nothing left to publish, at rest: the loop can sleep."""
        return self.active is None and not self.buffer

    @property
    def active_goal(self) -> ExecutionGoal | None:
        a = self.active
        return a.goal if a is not None else None

    # ------------------------------------------------------------------ commands (loop thread)
    def start_goal(self, goal: ExecutionGoal, measured: MeasuredState | None) -> None:
        """Take over ``goal``: splice onto the current stream, or start from the measured state."""
        finishes = []
        if self.active is not None:
            old = self.active.goal
            finishes.append((old, Outcome(Code.PREEMPTED, "preempted by a newer Execute goal",
                                          old.max_tracking_error, self.active.clock.x,
                                          self.active.clock.sample.cycle)))
            self.active = None
        if self.buffer or (self.streamer.started and not self.streamer.at_rest()):
            # splice: continue from the last computed sample (position, velocity, acceleration)
            if self.streamer.stopping:
                self.streamer.resume()
        else:
            if measured is None:
                finishes.append((goal, Outcome(Code.ROBOT_STATE_STALE, "no joint_states received", 0.0,
                                               goal.plan.start_phase, 0)))
                self._deliver_now(finishes)
                return
            q = np.clip(measured.q, self.limits.lower, self.limits.upper)
            out = np.abs(q - measured.q)
            if out.max() > 1e-3:
                j = int(np.argmax(out))
                finishes.append((goal, Outcome(
                    Code.LIMIT_VIOLATION, f"measured position of {self.limits.names[j]} is {measured.q[j]:.4g} rad, "
                    f"outside its limits [{self.limits.lower[j]:.4g}, {self.limits.upper[j]:.4g}] rad", 0.0,
                    goal.plan.start_phase, 0)))
                self._deliver_now(finishes)
                return
            try:
                self.streamer.start(q)
            except ValueError as exc:
                finishes.append((goal, Outcome(Code.LIMIT_VIOLATION, str(exc), 0.0, goal.plan.start_phase, 0)))
                self._deliver_now(finishes)
                return
            zero = np.zeros(self.limits.n_joints)
            hold = Sample(q.copy(), zero, zero, None, None, ())
            self.buffer.extend([hold] * self.n_ahead)
            self.last_command = q.copy()
        act = _Active(goal, self.dt)
        self._compared, self.tracking_error = None, 0.0
        q_now = np.asarray(self.streamer.state[0])
        if np.max(np.abs(q_now - act.start_q)) <= self.config.approach_tolerance:
            act.stage = Stage.RUN
        goal.stage = act.stage
        self.active = act
        if finishes:
            self._attach(finishes)

    def cancel(self, goal: ExecutionGoal) -> None:
        a = self.active
        if a is not None and a.goal is goal:
            self._stop(Code.CANCELED, "canceled")

    def set_rate(self, goal: ExecutionGoal, rate: float) -> None:
        """Phase rate of ``goal`` in its own direction (> 0 onward, < 0 back, 0 hold)."""
        a = self.active
        if a is not None and a.goal is goal and a.stage != Stage.STOPPING:
            a.clock.set_rate(rate, self.config.phase_rate_ramp_time)

    def _stop(self, code: Code, message: str) -> None:
        a = self.active
        if a is not None and a.stage != Stage.STOPPING:
            a.stop_reason = (code, message)
            a.stage = a.goal.stage = Stage.STOPPING
            self.streamer.request_stop()

    def _attach(self, finishes) -> None:
        """Deliver outcomes when the newest buffered sample is published."""
        last = self.buffer.pop() if self.buffer else None
        if last is None:
            self._deliver_now(finishes)
        else:
            self.buffer.append(last._replace(finishes=last.finishes + tuple(finishes)))

    @staticmethod
    def _deliver_now(finishes) -> None:
        for goal, outcome in finishes:
            goal._finish(outcome._replace(
                max_tracking_error=max(outcome.max_tracking_error, goal.max_tracking_error)))

    # ------------------------------------------------------------------ per tick
    def pop_due(self, measured: MeasuredState | None, now: float) -> Sample | None:
        """The sample due now (None when idle); updates progress, tracking error, outcomes."""
        if not self.buffer:
            return None
        s = self.buffer.popleft()
        self.last_command = s.q
        g = s.goal
        if g is not None:
            if measured is not None and measured is not self._compared:
                # a new robot state: compare it with the command due now
                self._compared = measured
                self.tracking_error = float(np.abs(s.q - measured.q).max())
                g.max_tracking_error = max(g.max_tracking_error, self.tracking_error)
            if s.progress is not None:  # (the tuple is completed with the tracking error when read)
                g._progress, g._tracking_error = s.progress, self.tracking_error
        if s.finishes:
            self._deliver_now(s.finishes)
        return s

    def check_faults(self, measured: MeasuredState | None, now: float) -> None:
        """Stale joint_states and tracking-error bound -> brake with the right code."""
        a = self.active
        if a is None or a.stage == Stage.STOPPING:
            return
        timeout = self.config.stale_timeout
        if measured is None or now - measured.stamp > timeout:
            age = math.inf if measured is None else now - measured.stamp
            self._stop(Code.ROBOT_STATE_STALE, f"no joint_states for {age:.3f} s (stale_timeout {timeout:g} s): "
                       "the robot stopped reporting its state; braked to rest")
            return
        bound = self.config.max_tracking_error
        if bound > 0 and self.tracking_error > bound:
            self._stop(Code.LIMIT_VIOLATION, f"tracking error {self.tracking_error:.4g} rad exceeded "
                       f"max_tracking_error {bound:g} rad; braked to rest")

    def compute_next(self) -> None:
        """Append the sample ``lookahead_ticks`` periods ahead (nothing when idle)."""
        a = self.active
        if a is None:
            return
        clock = a.clock
        finishes = []
        if a.stage == Stage.APPROACH:
            st = self.streamer.step(a.start_q)
            if st.status == StreamStatus.REACHED:
                a.stage = a.goal.stage = Stage.RUN
        else:
            st = self.streamer.track(a.reference)
            if a.stage == Stage.RUN:
                clock.tick()
                if clock.done:
                    a.stage = a.goal.stage = Stage.SETTLE
            elif a.stage == Stage.SETTLE:
                a.settle_ticks += 1
                if self.streamer.at_rest():
                    zero = np.zeros_like(st.qd)  # exactly at rest (a controller checks |v| <= machine epsilon)
                    st = st._replace(qd=zero, qdd=zero)
                    finishes.append((a.goal, Outcome(
                        Code.SUCCESS, f"executed '{a.plan.primitive}' ({a.plan.cycles} cycle(s))"
                        if a.plan.rhythmic else f"executed '{a.plan.primitive}'",
                        a.goal.max_tracking_error, clock.x, a.plan.cycles)))
                elif a.settle_ticks * self.dt > self.SETTLE_TIMEOUT:
                    self._stop(Code.INTERNAL_ERROR, f"did not come to rest within {self.SETTLE_TIMEOUT:g} s "
                               "after the end of the primitive; braked")
        if st.status == StreamStatus.ERROR:
            # ruckig rejected this tick's input: the streamer braked for one tick (within the
            # limits) and plans again from there next tick; only a persistent failure aborts
            self.errors += 1
            self.last_error = st.error
            a.error_ticks += 1
            if a.error_ticks > self.MAX_ERROR_TICKS and a.stage != Stage.STOPPING:
                self._stop(Code.INTERNAL_ERROR, f"trajectory generation failed for {a.error_ticks} ticks in a "
                           f"row ({st.error.splitlines()[0] if st.error else 'ruckig error'}); braked to rest")
        else:
            a.error_ticks = 0
        if a.stage == Stage.STOPPING and st.status == StreamStatus.STOPPED:
            code, msg = a.stop_reason
            finishes.append((a.goal, Outcome(code, f"{msg}; stopped at phase {clock.x:.4f}",
                                             a.goal.max_tracking_error, clock.x, clock.sample.cycle)))
        prog = Progress(clock.x, clock.sample.cycle, clock.rate, 0.0)
        self.buffer.append(Sample(st.q, st.qd, st.qdd, a.goal, prog, tuple(finishes)))
        if finishes:
            self.active = None

    def snapshot(self, t_first: float, n_points: int) -> Snapshot | None:
        """``n_points`` buffered samples evenly spread over the look-ahead (the last one included);
        sample k of the buffer is due at t_first + k dt."""
        n = len(self.buffer)
        if n == 0:
            return None
        idx = sorted({min(n - 1, max(0, round(n * (i + 1) / n_points) - 1)) for i in range(n_points)})
        rows = [self.buffer[i] for i in idx]
        return Snapshot(t_first - self.dt, (np.array(idx, dtype=float) + 1.0) * self.dt,
                        np.array([r.q for r in rows]), np.array([r.qd for r in rows]),
                        np.array([r.qdd for r in rows]))


class LoopStats:
    """Counters of the control loop (read by the node for its status log and by benchmarks)."""

    RING = 1 << 16

    def __init__(self):
        self.ticks = 0
        self.late = 0           # ticks that started more than one period after their deadline
        self.max_tick_s = 0.0   # longest tick (work, not waiting)
        self._pub_times = np.zeros(self.RING)  # perf_counter() of the last command publications
        self._n_pub = 0
        self.cpu_s = 0.0        # CPU time of the control thread spent in ticks (time.thread_time)
        self.work_ticks = 0     # ticks that computed a sample (not idle)

    def published(self, t: float) -> None:
        self._pub_times[self._n_pub % self.RING] = t
        self._n_pub += 1

    def publish_intervals(self) -> np.ndarray:
        """Intervals between consecutive command publications (latest RING), in seconds; gaps
        while idle (no goal) are excluded by the caller's choice of window (see node log)."""
        n = min(self._n_pub, self.RING)
        k = self._n_pub % self.RING
        t = np.concatenate([self._pub_times[k:n], self._pub_times[:k]]) if self._n_pub > self.RING else \
            self._pub_times[:n]
        return np.diff(t)

    def period_summary(self, dt: float) -> str:
        """'p50/p99 |interval - dt| and intervals > 1.5 dt' of the command publications while
        streaming (intervals > 1 s, i.e. idle time between goals, are left out)."""
        iv = self.publish_intervals()
        iv = iv[iv < 1.0]
        if iv.size == 0:
            return "no commands published yet"
        err = np.abs(iv - dt) * 1e3
        return (f"publish period error p50 {np.percentile(err, 50):.3f} ms, p99 {np.percentile(err, 99):.3f} ms, "
                f"{int((iv > 1.5 * dt).sum())} of {iv.size} intervals > 1.5 periods")


class StreamLoop:
    """Runs an :class:`ExecutionController` at the control rate and publishes its samples.

    Parameters
    ----------
    controller : ExecutionController
    publish_command : callable (q, qd, qdd, due) -> None, or None
        Called every tick with the due sample (robot joint order); ``due`` is the
        time.perf_counter() at which it is due (the tick's deadline).
    publish_trajectory : callable (Snapshot) -> None, or None
        Called from a separate thread at ``config.trajectory_rate_hz``.
    on_error : callable (str) -> None
        Receives a message if a publish callable raises (the loop keeps running).
    poll_measured : callable () -> None, or None
        Called at the start of every tick and every ``idle_poll`` s while idle, in the loop's
        thread; it reads the newest robot state and calls :meth:`update_measured` (the node
        takes joint_states from its subscription here instead of through an executor callback:
        at 1 kHz, executor dispatch alone costs most of a CPU core in Python).
    thread_setup : callable (name, fifo_priority) -> str, or None
        Called first in each thread the loop starts: ``("control_loop", config.realtime_priority)``
        and ``("jtc_publisher", 0)``; it names the thread and asks for SCHED_FIFO when the priority
        is > 0, and returns '' or why the priority was refused (:attr:`priority_error`). The nodes
        pass :func:`deepprompt_ros.ros.fastpath.realtime.prepare_thread`; None: nothing is changed.
    """

    idle_poll = 0.01
    #: seconds between two reads of the robot state while streaming (taking a JointState message
    #: costs ~0.1 ms in Python: every tick would be a tenth of a 1 kHz period)
    state_poll = 0.01

    def __init__(self, controller: ExecutionController, config: ServerConfig,
                 publish_command: Callable | None = None, publish_trajectory: Callable | None = None,
                 on_error: Callable[[str], None] = lambda msg: None, poll_measured: Callable | None = None,
                 thread_setup: Callable[[str, int], str] | None = None):
        self.ctl = controller
        self.config = config
        self.dt = controller.dt
        self._pub_cmd = publish_command
        self._pub_traj = publish_trajectory
        self._on_error = on_error
        self._poll = poll_measured
        self._thread_setup = thread_setup or (lambda name, fifo_priority: "")
        self._measured: MeasuredState | None = None
        self._commands: collections.deque = collections.deque()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._traj_thread: threading.Thread | None = None
        self._traj_cv = threading.Condition()
        self._traj_pending: Snapshot | None = None
        self._traj_every = max(1, int(round(1.0 / (config.trajectory_rate_hz * self.dt))))
        self._poll_every = max(1, int(round(self.state_poll / self.dt)))
        self._next = 0.0
        self.stats = LoopStats()
        self.priority_error = ""
        self.started = threading.Event()  #: set once the control thread runs (priority_error is final)

    # ------------------------------------------------------------------ inputs (any thread)
    def update_measured(self, q: np.ndarray, qd: np.ndarray | None = None) -> None:
        self._measured = MeasuredState(q, qd, time.monotonic())

    @property
    def measured(self) -> MeasuredState | None:
        return self._measured

    def measured_age(self) -> float:
        m = self._measured
        return math.inf if m is None else time.monotonic() - m.stamp

    @property
    def active_goal(self) -> ExecutionGoal | None:
        return self.ctl.active_goal

    def execute(self, goal: ExecutionGoal) -> ExecutionGoal:
        """Queue ``goal``; it preempts the running one at the next tick."""
        self._commands.append(("start", goal))
        self._wake.set()
        return goal

    def cancel(self, goal: ExecutionGoal) -> None:
        self._commands.append(("cancel", goal))

    def set_rate(self, rate: float) -> ExecutionGoal:
        """Change the running goal's phase rate; RequestError(NO_ACTIVE_EXECUTION) when none runs."""
        goal = self.ctl.active_goal
        if goal is None or goal.stage in (Stage.STOPPING, Stage.DONE):
            raise RequestError(Code.NO_ACTIVE_EXECUTION, "no Execute goal is running; SetPhaseRate changes the "
                               "rate of a running goal")
        self._commands.append(("rate", goal, float(rate)))
        return goal

    def summary(self) -> str:
        """One line about the loop so far (ticks, late ticks, longest tick, CPU per tick, pacing)."""
        st = self.stats
        return (f"{st.ticks} ticks, {st.late} late by > 1 period, longest tick {st.max_tick_s * 1e3:.2f} ms, "
                f"{self.ctl.errors} ruckig errors, {st.cpu_s / max(st.work_ticks, 1) * 1e6:.0f} us CPU per tick; "
                f"{st.period_summary(self.dt)}")

    # ------------------------------------------------------------------ one tick
    def tick(self, next_due: float | None = None) -> None:
        """One control period: publish the due sample, apply commands, compute the next sample.

        ``next_due``: time.perf_counter() at which the next tick is due (default now + dt)."""
        ctl = self.ctl
        if self.stats.ticks % self._poll_every == 0:
            self.poll()
        now = time.monotonic()
        measured = self._measured
        s = ctl.pop_due(measured, now)
        if s is not None and self._pub_cmd is not None:
            try:
                self._pub_cmd(s.q, s.qd, s.qdd, next_due - self.dt if next_due is not None else time.perf_counter())
                self.stats.published(time.perf_counter())
            except Exception as exc:  # a publisher failure must not stop the loop
                self._on_error(f"command publish failed: {exc!r}")
        while self._commands:
            cmd = self._commands.popleft()
            if cmd[0] == "start":
                ctl.start_goal(cmd[1], measured)
            elif cmd[0] == "cancel":
                ctl.cancel(cmd[1])
            elif cmd[0] == "rate":
                ctl.set_rate(cmd[1], cmd[2])
        ctl.check_faults(measured, now)
        ctl.compute_next()
        self.stats.ticks += 1
        if self._pub_traj is not None and self.stats.ticks % self._traj_every == 0 and ctl.buffer:
            snap = ctl.snapshot(time.perf_counter() + self.dt if next_due is None else next_due,
                                self.config.trajectory_points)
            with self._traj_cv:
                self._traj_pending = snap
                self._traj_cv.notify()

    # ------------------------------------------------------------------ thread mode
    def start(self, threaded: bool = True) -> None:
        """Start the JointTrajectory thread and, if ``threaded``, the control thread (else call
        :meth:`timer_tick` from a timer)."""
        if self._pub_traj is not None:
            self._traj_thread = threading.Thread(target=self._traj_worker, name="jtc_publisher", daemon=True)
            self._traj_thread.start()
        if threaded:
            self._thread = threading.Thread(target=self._run, name="control_loop", daemon=True)
            self._thread.start()

    def shutdown(self, timeout: float = 2.0) -> None:
        self._stop.set()
        self._wake.set()
        with self._traj_cv:
            self._traj_cv.notify()
        for t in (self._thread, self._traj_thread):
            if t is not None:
                t.join(timeout)

    def poll(self) -> None:
        """Read the robot state (``poll_measured``); errors are reported, never raised."""
        if self._poll is not None:
            try:
                self._poll()
            except Exception as exc:
                self._on_error(f"reading the robot state failed: {exc!r}")

    def timer_tick(self) -> None:
        """Timer mode: one tick per timer callback (while idle: only the state is read)."""
        if self.ctl.idle and not self._commands:
            self.poll()
            return
        t0 = time.perf_counter()
        self.tick()
        self.stats.max_tick_s = max(self.stats.max_tick_s, time.perf_counter() - t0)

    def _run(self) -> None:
        self.priority_error = self._thread_setup("control_loop", self.config.realtime_priority)
        self.started.set()
        dt = self.dt
        spin = self.config.spin_wait
        perf = time.perf_counter
        while not self._stop.is_set():
            if self.ctl.idle and not self._commands:
                self.poll()
                self._wake.wait(self.idle_poll)
                self._wake.clear()
                self._next = perf()
                continue
            # absolute deadlines: no drift; a late tick is not made up by bursts beyond one period
            self._next += dt
            now = perf()
            if now > self._next + dt:
                self.stats.late += 1
                self._next = now
            else:
                remaining = self._next - now
                if remaining > spin:
                    time.sleep(remaining - spin)
                while perf() < self._next:
                    pass
            t0 = perf()
            c0 = time.thread_time()
            try:
                self.tick(self._next + dt)
            except Exception as exc:  # never let the control thread die
                self._on_error(f"control loop tick failed: {exc!r}")
                self._emergency_stop(exc)
            self.stats.max_tick_s = max(self.stats.max_tick_s, perf() - t0)
            self.stats.cpu_s += time.thread_time() - c0
            self.stats.work_ticks += 1

    def _emergency_stop(self, exc: Exception) -> None:
        a = self.ctl.active
        if a is not None:
            a.goal._finish(Outcome(Code.INTERNAL_ERROR, f"control loop failure: {exc!r}",
                                   a.goal.max_tracking_error, a.clock.x, a.clock.sample.cycle))
            self.ctl.active = None
        self.ctl.buffer.clear()

    def _traj_worker(self) -> None:
        self._thread_setup("jtc_publisher", 0)
        while not self._stop.is_set():
            with self._traj_cv:
                while self._traj_pending is None and not self._stop.is_set():
                    self._traj_cv.wait(0.5)
                snap, self._traj_pending = self._traj_pending, None
            if snap is None:
                continue
            try:
                self._pub_traj(snap)
            except Exception as exc:
                self._on_error(f"trajectory publish failed: {exc!r}")


class BrakeTail:
    """Time-optimal, jerk-limited brake of every joint to rest (Ruckig velocity interface, joints
    independent): the end of each JointTrajectory message, so that every message is a complete
    trajectory ending at rest (a controller that receives no further message stops smoothly, and
    a JointTrajectoryController accepts it without allow_nonzero_velocity_at_trajectory_end).
    From a state produced by RuckigStreamer this brake stays inside the position limits (the
    streamer's invariant)."""

    REST = 1e-9  #: |qd|, |qdd| at or below this count as at rest (no tail; zeroed in messages)

    def __init__(self, limits: JointLimits):
        from ruckig import ControlInterface, InputParameter, Ruckig, Synchronization, Trajectory

        d = limits.n_joints
        self._otg, self._traj, self._inp = Ruckig(d), Trajectory(d), InputParameter(d)
        self._inp.control_interface = ControlInterface.Velocity
        self._inp.synchronization = Synchronization.No
        self._inp.max_velocity = list(map(float, limits.max_velocity))
        self._inp.max_acceleration = list(map(float, limits.max_acceleration))
        self._inp.max_jerk = list(map(float, limits.max_jerk))
        self._inp.target_velocity = [0.0] * d
        self._inp.target_acceleration = [0.0] * d
        self._lower, self._upper = np.asarray(limits.lower), np.asarray(limits.upper)
        self._vmax, self._amax = np.asarray(limits.max_velocity), np.asarray(limits.max_acceleration)

    def __call__(self, q, qd, qdd, n_points: int = 3):
        """Brake from (q, qd, qdd) (d,) each.

        Returns
        -------
        times : array, shape (m,), seconds after the given state (m = 0 when already at rest)
        q, qd, qdd : array, shape (m, d); the last row has qd = qdd = 0 exactly.
        """
        qd = np.clip(np.asarray(qd, dtype=float), -self._vmax, self._vmax)
        qdd = np.clip(np.asarray(qdd, dtype=float), -self._amax, self._amax)
        d = qd.shape[0]
        if not (np.any(np.abs(qd) > self.REST) or np.any(np.abs(qdd) > self.REST)):
            return np.zeros(0), np.zeros((0, d)), np.zeros((0, d)), np.zeros((0, d))
        inp = self._inp
        inp.current_position = np.asarray(q, dtype=float).tolist()
        inp.current_velocity = qd.tolist()
        inp.current_acceleration = qdd.tolist()
        self._otg.calculate(inp, self._traj)
        dur = max(self._traj.duration, 1e-6)
        times = dur * np.arange(1, n_points + 1) / n_points
        rows = [self._traj.at_time(float(t))[:3] for t in times]
        pq = np.clip(np.array([r[0] for r in rows]), self._lower, self._upper)
        pv = np.array([r[1] for r in rows])
        pa = np.array([r[2] for r in rows])
        pv[-1] = 0.0
        pa[-1] = 0.0
        return times, pq, pv, pa


def trajectory_points(snap: Snapshot, tail: BrakeTail):
    """Points of one JointTrajectory message: the snapshot's future samples, then the brake to
    rest from the last of them. The last point has velocity and acceleration exactly 0.

    Returns
    -------
    times : array, shape (P,), seconds after ``snap.t0``, strictly increasing
    q, qd, qdd : array, shape (P, d)
    """
    tt, tq, tv, ta = tail(snap.q[-1], snap.qd[-1], snap.qdd[-1])
    times = np.concatenate([snap.times, snap.times[-1] + tt])
    q = np.concatenate([snap.q, tq])
    qd = np.concatenate([snap.qd, tv])
    qdd = np.concatenate([snap.qdd, ta])
    qd[-1] = 0.0
    qdd[-1] = 0.0
    return times, q, qd, qdd
