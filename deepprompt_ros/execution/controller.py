"""The tick-by-tick state machine of the primitive server's command stream (single-threaded;
no rclpy).

:class:`ExecutionController` keeps a look-ahead buffer of command samples (robot joint order).
Every control tick the loop (:class:`~deepprompt_ros.execution.stream_loop.StreamLoop`) pops the
sample due now (:meth:`~ExecutionController.pop_due`), applies the commands of other threads
(:meth:`~ExecutionController.start_goal`: a new goal splices onto the stream and preempts the
running goal, or ends a braking one for the reason it brakes,
:meth:`~ExecutionController.cancel`: brake, :meth:`~ExecutionController.set_rate`), checks
joint-state staleness and the tracking-error bound (:meth:`~ExecutionController.check_faults`),
and computes ONE new sample ``lookahead_ticks`` periods ahead
(:meth:`~ExecutionController.compute_next`): the phase clock gives x = τ(t), the dense grid of
the executed mean gives the reference (q, q̇, q̈) at x
(:class:`~deepprompt_ros.execution.plan.ExecutionReference`), and Ruckig
(:class:`~deepprompt_ros.execution.ruckig_streamer.RuckigStreamer`) turns it into a command
within the velocity, acceleration, jerk and position limits.

Because the buffer holds the future samples, each JointTrajectory message is a piece of the one
command stream (successive messages agree where they overlap, so a controller that replaces its
trajectory on every message sees no jump), and everything that changes the motion takes effect
``lookahead_ticks`` periods later. Stage of a goal: APPROACH (move to the primitive's start with
the clock held, only when farther than ``approach_tolerance``), RUN (clock running), SETTLE
(clock done, converging onto the end state), STOPPING (cancel, stale joint_states, tracking error:
every joint brakes time-optimally within its limits), then the goal's outcome is delivered when
its last sample has been published.

Over 400 lines: one state machine whose transitions (start, splice, restart from the last command,
cancel, abort, the per-tick stages) all read and change the same buffer, streamer state and
pending outcomes, so they are kept in one class.
"""
from __future__ import annotations

import collections
import enum
import math
import threading
from typing import NamedTuple

import numpy as np

from deepprompt_ros.common.results import Code
from deepprompt_ros.execution.limits import JointLimits
from deepprompt_ros.execution.plan import ExecutionPlan
from deepprompt_ros.execution.ruckig_streamer import RuckigStreamer, StreamStatus
from deepprompt_ros.execution.settings import LoopSettings

__all__ = ["Stage", "Outcome", "Progress", "MeasuredState", "Sample", "Snapshot", "ExecutionGoal",
           "ExecutionController"]


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
    """Shared between the action callback (waits, reads progress, requests cancel) and the loop.

    ``order``: the goal's place in the order the goals were accepted (larger = newer; None = not
    ordered). A goal that reaches the loop while a newer one runs (its planning took longer) does not
    preempt the newer one: it ends PREEMPTED without moving."""

    def __init__(self, plan: ExecutionPlan, goal_id: str = "", order: int | None = None):
        self.plan = plan
        self.goal_id = goal_id
        self.order = order
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
    """Tick-by-tick state machine of the command stream (single-threaded; run by
    :class:`~deepprompt_ros.execution.stream_loop.StreamLoop`).

    Parameters
    ----------
    limits : JointLimits (robot joint order)
    dt : float
    config : LoopSettings
    """

    SETTLE_TIMEOUT = 30.0  # s; a goal that does not come to rest by then ends with INTERNAL_ERROR
    MAX_ERROR_TICKS = 100  # consecutive ruckig failures (each braking one tick) before aborting

    def __init__(self, limits: JointLimits, dt: float, config: LoopSettings):
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
        self.last_command: np.ndarray | None = None  #: position of the sample published last
        self._published_at = -math.inf                #: its ``now`` (time.monotonic())
        self._starting: ExecutionGoal | None = None    #: the goal start_goal is taking over
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
    def start_goal(self, goal: ExecutionGoal, measured: MeasuredState | None, now: float) -> None:
        """Take over ``goal`` at time ``now`` (time.monotonic(), as ``measured.stamp``).

        Where the new goal's commands start from (as ros2_control's JointTrajectoryController
        starts a new trajectory from its last command while it holds one):

        * the stream runs (samples are buffered): it splices onto the last computed sample;
        * the stream ended at most ``stale_timeout`` before ``now``: from its last published
          command, at rest (a stream ends at rest: velocity and acceleration 0) -- the robot's
          controller still holds that command, and a robot lagging behind it must not see its
          setpoint jump back to where it was measured;
        * else (first goal, long idle, after :meth:`abort`): from the measured position at rest.

        A goal accepted before the running one ends PREEMPTED at once (see :class:`ExecutionGoal`)."""
        if self.active is not None and goal.order is not None and self.active.goal.order is not None \
                and goal.order < self.active.goal.order:
            self._deliver_now([(goal, Outcome(Code.PREEMPTED, "preempted by a newer Execute goal, which started "
                                              "first", 0.0, goal.plan.start_phase, 0))])
            return
        self._starting = goal
        if self.active is not None:
            a, old = self.active, self.active.goal
            if a.stage == Stage.STOPPING and a.stop_reason is not None:
                # braking already (canceled, stale state, tracking error): it ends for that reason
                code, msg = a.stop_reason
                msg = f"{msg}; a newer Execute goal took over while braking (phase {a.clock.x:.4f})"
            else:
                code, msg = Code.PREEMPTED, "preempted by a newer Execute goal"
            self.active = None
            # delivered once its last sample is published
            self._attach([(old, Outcome(code, msg, old.max_tracking_error, a.clock.x, a.clock.sample.cycle))])
        if self.buffer:
            # splice: continue from the last computed sample (position, velocity, acceleration)
            if self.streamer.stopping:
                self.streamer.resume()
        else:
            refusal = self._refuse_start(goal, measured)
            if refusal is not None:
                self._starting = None
                self._deliver_now([(goal, refusal)])
                return
            if self.last_command is not None and now - self._published_at <= self.config.stale_timeout:
                q = self.last_command.copy()
            else:
                q = np.clip(measured.q, self.limits.lower, self.limits.upper)
            try:
                self.streamer.start(q)
            except ValueError as exc:
                self._starting = None
                self._deliver_now([(goal, Outcome(Code.LIMIT_VIOLATION, str(exc), 0.0, goal.plan.start_phase, 0))])
                return
            zero = np.zeros(self.limits.n_joints)
            hold = Sample(q, zero, zero, None, None, ())  # the look-ahead starts as a hold of the start
            self.buffer.extend([hold] * self.n_ahead)
        act = _Active(goal, self.dt)
        self._compared, self.tracking_error = None, 0.0
        q_now = np.asarray(self.streamer.state[0])
        if np.max(np.abs(q_now - act.start_q)) <= self.config.approach_tolerance:
            act.stage = Stage.RUN
        goal.stage = act.stage
        self.active = act
        self._starting = None

    def _refuse_start(self, goal: ExecutionGoal, measured: MeasuredState | None) -> Outcome | None:
        """Why a stream cannot start for ``goal`` from rest (no robot state, a measured position
        outside the limits), or None."""
        if measured is None:
            return Outcome(Code.ROBOT_STATE_STALE, "no joint_states received", 0.0, goal.plan.start_phase, 0)
        out = np.abs(np.clip(measured.q, self.limits.lower, self.limits.upper) - measured.q)
        if out.max() > 1e-3:
            j = int(np.argmax(out))
            return Outcome(Code.LIMIT_VIOLATION, f"measured position of {self.limits.names[j]} is "
                           f"{measured.q[j]:.4g} rad, outside its limits [{self.limits.lower[j]:.4g}, "
                           f"{self.limits.upper[j]:.4g}] rad", 0.0, goal.plan.start_phase, 0)
        return None

    def abort(self, reason: str) -> None:
        """The stream is cut where it is (the control loop failed: ``reason``): nothing buffered is
        published and every goal still waiting ends now. The running goal and a goal being taken
        over end with INTERNAL_ERROR, as does a goal whose SUCCESS was waiting for its last samples
        to be published; a goal that had already ended otherwise (PREEMPTED, CANCELED, a fault)
        keeps its code, its message saying that its last commands were not published. The next goal
        starts from the measured state."""
        a = self.active
        running = [g for g in (a.goal if a is not None else None, self._starting) if g is not None]
        pending = [f for s in self.buffer for f in s.finishes]
        self.buffer.clear()
        self.active, self._starting = None, None
        self.last_command, self._published_at = None, -math.inf
        failure = f"control loop failure: {reason}"
        finishes = []
        for goal, outcome in pending:
            if outcome.code == Code.SUCCESS:
                outcome = outcome._replace(code=Code.INTERNAL_ERROR,
                                           message=f"{failure}; the end of the motion was not published")
            else:
                outcome = outcome._replace(message=f"{outcome.message}; then a {failure} (its last commands "
                                                   "were not published)")
            finishes.append((goal, outcome))
        for goal in running:
            phase, cycle = (a.clock.x, a.clock.sample.cycle) if a is not None and goal is a.goal else \
                (goal.plan.start_phase, 0)
            finishes.append((goal, Outcome(Code.INTERNAL_ERROR, f"{failure}; the command stream stopped there",
                                           goal.max_tracking_error, phase, cycle)))
        self._deliver_now(finishes)

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
        self.last_command, self._published_at = s.q, now
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

    def check_faults(self, measured: MeasuredState | None, now: float, refused: str = "") -> None:
        """Stale joint_states and tracking-error bound -> brake with the right code.

        ``refused``: why the robot states received since ``measured`` were refused ('' = none was),
        named in the outcome of a stale stop."""
        a = self.active
        if a is None or a.stage == Stage.STOPPING:
            return
        timeout = self.config.stale_timeout
        if measured is None or now - measured.stamp > timeout:
            age = math.inf if measured is None else now - measured.stamp
            what, why = (("valid joint_states", f"the latest were refused ({refused})") if refused
                         else ("joint_states", "the robot stopped reporting its state"))
            self._stop(Code.ROBOT_STATE_STALE, f"no {what} for {age:.3f} s (stale_timeout {timeout:g} s): "
                       f"{why}; braked to rest")
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
