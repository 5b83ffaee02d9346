"""The control-rate execution loop of the primitive server (no rclpy import: publishing is
injected as callables, so the loop runs and is tested without ROS): it runs an
:class:`~deepprompt_ros.execution.controller.ExecutionController` at the control rate.

Per control tick (period dt = 1 / control rate):

1. the sample that is due now is popped from the look-ahead buffer and published on the
   per-tick command output (``publish_command``);
2. commands from other threads are applied (new goal -> splice, cancel -> brake, phase-rate
   change), joint-state staleness and the tracking-error bound are checked;
3. ONE new sample, ``lookahead_ticks`` periods ahead, is computed (the phase clock, the
   executed mean's reference and Ruckig within the limits; the stages of a goal and why the
   look-ahead: :mod:`deepprompt_ros.execution.controller`);
4. every 1/trajectory_rate a snapshot of the buffered future samples goes to a second thread that
   builds the JointTrajectory message (its points: :mod:`deepprompt_ros.execution.brake_tail`;
   building a message point by point is slow in Python) off the critical path.

Timing: the 'thread' mode paces ticks on absolute time.perf_counter deadlines (no drift). A tick
that starts more than one period late is not made up with a burst: the deadlines restart from
now, so on an overloaded machine the motion stretches in time while every sample still keeps the
limits with respect to the one before it (commands carry the nominal tick time as header.stamp,
so a consumer can see the gap). The robot state is read from the node's subscription every
``state_poll`` seconds in this thread (see :class:`StreamLoop`).
"""
from __future__ import annotations

import collections
import dataclasses
import math
import threading
import time
from typing import Callable

import numpy as np

from deepprompt_ros.common.results import Code, RequestError
from deepprompt_ros.execution.controller import (ExecutionController, ExecutionGoal, MeasuredState, Snapshot,
                                                  Stage)
from deepprompt_ros.execution.settings import LoopSettings

__all__ = ["StreamLoop", "LoopStats"]


# The commands other threads queue for the control thread (applied at the start of its next tick, in
# the order they were queued).
@dataclasses.dataclass(frozen=True)
class _Start:
    """Start ``goal``; it preempts the running one."""

    goal: ExecutionGoal


@dataclasses.dataclass(frozen=True)
class _Cancel:
    """Brake ``goal`` to rest if it runs."""

    goal: ExecutionGoal


@dataclasses.dataclass(frozen=True)
class _SetRate:
    """Phase rate ``rate`` for ``goal`` if it runs."""

    goal: ExecutionGoal
    rate: float


_Command = _Start | _Cancel | _SetRate


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
    config : LoopSettings
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
        dispatching every message through the executor is costly in Python at a 1 kHz rate).
    thread_setup : callable (name, fifo_priority) -> str, or None
        Called first in each thread the loop starts: ``("control_loop", config.realtime_priority)``
        and ``("jtc_publisher", 0)``; it names the thread and asks for SCHED_FIFO when the priority
        is > 0, and returns '' or why the priority was refused (:attr:`priority_error`). The nodes
        pass :func:`deepprompt_ros.ros.fastpath.realtime.prepare_thread`; None: nothing is changed.
    """

    idle_poll = 0.01
    #: seconds between two reads of the robot state while streaming (taking a JointState message
    #: is costly in Python, so it is not done every tick)
    state_poll = 0.01

    def __init__(self, controller: ExecutionController, config: LoopSettings,
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
        self._refused: tuple[str, float] | None = None  # (reason, time.monotonic()) of the latest refusal
        self._commands: collections.deque[_Command] = collections.deque()
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

    def refuse_measured(self, reason: str) -> None:
        """A robot state arrived and was refused (``reason``: what was wrong with it). It does not
        refresh the state; a goal stopped for stale joint states while the latest ones are refused
        says why in its outcome."""
        self._refused = (reason, time.monotonic())

    def state_refusal(self) -> str:
        """Why the robot states received since the latest accepted one were refused ('' = none was)."""
        r, m = self._refused, self._measured
        return r[0] if r is not None and (m is None or r[1] > m.stamp) else ""

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
        self._commands.append(_Start(goal))
        self._wake.set()
        return goal

    def cancel(self, goal: ExecutionGoal) -> None:
        self._commands.append(_Cancel(goal))

    def set_rate(self, rate: float) -> ExecutionGoal:
        """Change the running goal's phase rate; RequestError(NO_ACTIVE_EXECUTION) when none runs."""
        goal = self.ctl.active_goal
        if goal is None or goal.stage in (Stage.STOPPING, Stage.DONE):
            raise RequestError(Code.NO_ACTIVE_EXECUTION, "no Execute goal is running; SetPhaseRate changes the "
                               "rate of a running goal")
        self.set_goal_rate(goal, rate)
        return goal

    def set_goal_rate(self, goal: ExecutionGoal, rate: float) -> None:
        """Queue a phase-rate change of ``goal``: applied at the next tick if ``goal`` then runs (after
        the goals queued before it have started), ignored otherwise."""
        self._commands.append(_SetRate(goal, float(rate)))

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
            match self._commands.popleft():
                case _Start(goal):
                    ctl.start_goal(goal, measured, now)
                case _Cancel(goal):
                    ctl.cancel(goal)
                case _SetRate(goal, rate):
                    ctl.set_rate(goal, rate)
        ctl.check_faults(measured, now, self.state_refusal())
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
        self._guarded_tick(None)
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
            self._guarded_tick(self._next + dt)
            self.stats.max_tick_s = max(self.stats.max_tick_s, perf() - t0)
            self.stats.cpu_s += time.thread_time() - c0
            self.stats.work_ticks += 1

    def _guarded_tick(self, next_due: float | None) -> None:
        """:meth:`tick`; if it raises, the error is reported, the stream is cut and every goal waiting
        in it ends (:meth:`ExecutionController.abort`): the loop itself keeps running."""
        try:
            self.tick(next_due)
        except Exception as exc:  # never let the control thread (or the timer's executor) die
            self._on_error(f"control loop tick failed: {exc!r}")
            self.ctl.abort(repr(exc))

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
