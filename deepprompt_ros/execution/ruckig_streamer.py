"""Ruckig streaming with joint limits: one call per control tick turns a primitive's reference
into the next command sample.

:class:`RuckigStreamer` turns the primitive's target into a command that respects velocity,
acceleration and jerk limits (Ruckig, online trajectory generation) and joint position limits.
The community build of ruckig 0.19.4 ignores ``min_position``/``max_position``, so position
limits are guaranteed here, in two layers:

1. **Target clamping.** The target position is clipped into ``[lower + margin, upper - margin]``.
   Where it was clipped, the target velocity and acceleration of that joint are set to zero (a
   clipped target with a velocity pointing outward would otherwise drive the joint through the
   clip). Target velocities are clipped to ±v_max and target accelerations to ±a_max and
   further to |a| ≤ sqrt(2 j_max (v_max - |v|)): a target state with |v| + a²/(2 j_max) > v_max
   can be neither reached nor left without exceeding v_max, and ruckig rejects it.
2. **Braking guard.** Invariant: from the current state every joint can stop inside
   ``[lower, upper]`` with its time-optimal, jerk-limited brake to velocity 0 and
   acceleration 0 (joints independent, closed form in
   :func:`~deepprompt_ros.execution.braking.brake_joint`). Each tick ruckig proposes the next
   sample; for every joint close enough to a limit that it could matter, the exact position
   extrema of the brake from the *proposed* state are computed. A joint whose brake would leave its limits does not take the proposed sample: it takes one tick of the brake from
   the *current* state instead (which is within limits by the invariant, and whose remainder is
   the same brake, so the invariant holds next tick). Both the proposed sample and the brake
   start from the same state and are jerk-limited, so velocity, acceleration and jerk limits are
   kept when a joint switches between them. The produced positions therefore never leave
   ``[lower, upper]`` (up to ``guard_tolerance``), and the clamping margin makes the guard an
   exception rather than the rule: it only acts when the joint arrives at the clipped target
   too fast to stop within the margin.

Retargeting / splicing is natural: the state passes forward tick to tick, so switching to a new
reference at any tick keeps position, velocity and acceleration continuous. Cancelling uses the
same brake as the guard (:meth:`RuckigStreamer.request_stop`).

What is (and is not) guaranteed about the samples, checked by
:func:`~deepprompt_ros.execution.limits.check_limits`: every sample's |qd| ≤ v_max and
|qdd| ≤ a_max, successive samples satisfy |Δq|/dt ≤ v_max, |Δqd|/dt ≤ a_max and
|Δqdd|/dt ≤ j_max (finite-difference jerk of the reported accelerations; the continuous
trajectory between samples is jerk-limited piecewise, this is the per-sample consequence), and
lower ≤ q ≤ upper. The first sample after :meth:`RuckigStreamer.start` is checked against the
measured state given to ``start``. Not guaranteed: anything about a state given to
``start`` that is outside the limits or cannot stop inside them (``start`` raises); and the
exact brake check is skipped for joints farther from their limits than a conservative
stopping-distance bound (see ``_guard_zone``). If ruckig rejects a tick's input, that tick
brakes all joints (status ERROR) and the next tick plans again.

This module is longer than most (one class, about 500 lines): the tracking, approach, guard and
stop paths of :class:`RuckigStreamer` share the per-tick state (plain float lists for speed) and
each tick runs through several of them, so the class is kept whole; the closed-form brake it
checks and executes is :mod:`deepprompt_ros.execution.braking`.
"""
from __future__ import annotations

import enum
import math
from typing import NamedTuple

import numpy as np
from ruckig import InputParameter, Ruckig, RuckigError, Synchronization, Trajectory

from deepprompt_ros.execution.braking import brake_joint
from deepprompt_ros.execution.limits import JointLimits, joint_vector
from deepprompt_ros.execution.reference import ReferenceFn

__all__ = ["StreamStatus", "StreamState", "RuckigStreamer"]

#: ``tuple.__new__(NamedTupleClass, values)`` builds a NamedTuple without its Python-level
#: ``__new__`` (one sample per control tick).
_tuple_new = tuple.__new__


class StreamStatus(enum.IntEnum):
    """What produced a streamed sample."""

    ERROR = -1           #: ruckig rejected the tick's input; all joints braked this tick
    TRACKING = 0         #: following the reference with the look-ahead horizon (or moving to a step target)
    REACHED = 1          #: at the target state of :meth:`RuckigStreamer.step`
    POSITION_GUARD = 2   #: some joints braked to stay inside their position limits
    STOPPING = 3         #: braking after a stop request
    STOPPED = 4          #: at rest after a stop request
    APPROACHING = 5      #: far from the reference: intercepting it at a committed time


# enum members as module constants: a module global is found faster than a class attribute
_TRACKING, _REACHED, _GUARD = StreamStatus.TRACKING, StreamStatus.REACHED, StreamStatus.POSITION_GUARD
_STOPPING, _STOPPED, _ERROR = StreamStatus.STOPPING, StreamStatus.STOPPED, StreamStatus.ERROR
_APPROACHING = StreamStatus.APPROACHING
_F64 = np.dtype(np.float64)


class StreamState(NamedTuple):
    """One streamed sample (the command for the next control tick).

    Attributes
    ----------
    q, qd, qdd : array, shape (d,)
        Position [rad], velocity [rad/s], acceleration [rad/s²].
    status : StreamStatus
    guarded : array of bool, shape (d,)
        Joints whose sample came from the brake (position guard, stop, error) instead of the
        tracking step.
    clamped : array of bool, shape (d,)
        Joints whose target position was clipped into [lower + margin, upper - margin].
        (``guarded`` and ``clamped`` are a shared read-only array when no joint is flagged.)
    error : str
        Ruckig's message when ``status`` is ERROR, else "".
    """

    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    status: StreamStatus
    guarded: np.ndarray
    clamped: np.ndarray
    error: str = ""



class RuckigStreamer:
    """Jerk-limited streaming of a moving reference with velocity, acceleration, jerk and
    position limits (see the module docstring for how position limits are guaranteed).

    Two ways to feed it, both one call per control tick, both producing the state one control
    period ``dt`` after the current one:

    - :meth:`track` (following a primitive): takes the reference as a function of the time
      ahead, ``reference(ahead) -> (q, qd, qdd)``, and plans onto it. Planning onto the
      reference's *current* state every tick (a pursuit of a target that keeps moving)
      oscillates and converges slowly or not at all (measured: a 1 mm offset on a sine grew to
      8 cm), so:

      * TRACKING: the target is the reference ``horizon`` seconds ahead, and ruckig's
        ``minimum_duration`` is set to ``horizon``, so the plan arrives exactly when the
        reference does. On the reference, this reproduces it up to the interpolation error of
        a jerk-limited profile over the horizon (~1e-6 rad for a 0.25 Hz, 0.8 rad sine with
        horizon 10 ms);
      * APPROACHING: when that plan needs longer than ``approach_above`` seconds (the joint
        is far from its reference), the far joints commit to an interception at a common
        time t_a: a few fixed-point iterations of t_a = max_j duration_j(state_j ->
        reference_j(t_a)) give plans that arrive on the reference state exactly when the
        reference is there. Those plans are then *executed*, not re-planned (re-planning
        onto the same target with the remaining time is Bellman-consistent in theory, but
        ruckig then regularly finds the exact remaining time infeasible -- blocked
        intervals -- and jumps to a much longer plan). Every tick checks that the reference
        still passes through the committed target at the committed time; if it changed
        (another reference, a phase-rate change) it re-plans from the current state. At t_a
        the joints continue with TRACKING, already on the reference.

      Each joint is planned by its own 1-DoF ruckig: without synchronization ruckig ignores
      ``minimum_duration``, and with it one joint far from its reference (e.g. a reference
      outside the joint limits, clamped) drags the joints that are on their references off
      them. A joint whose reference is reachable tracks it whatever the other joints do.

    - :meth:`step` (retargeting to a given state): time-optimal plan of all joints together
      (``synchronization``) to the given target state, re-planned every tick; for static or
      slowly changing targets (e.g. moving to the start of a primitive before its clock runs).

    Parameters
    ----------
    limits : JointLimits
    dt : float
        Control period [s].
    horizon : float
        Look-ahead of :meth:`track` [s], >= dt. The tracking error on the reference grows like
        horizon³ · |jerk of the reference|; too short a horizon makes the recovery from a
        deviation oscillate. 10–20 ms at 1 kHz.
    approach_above : float
        Plans longer than this [s] switch from TRACKING to APPROACHING.
    position_margin : float or array, shape (d,)
        Targets are clipped into [lower + margin, upper - margin] [rad]; must be smaller than
        half of each joint's range.
    guard_tolerance : float
        The braking guard keeps positions within [lower - tol, upper + tol]; covers float
        rounding of the brake profile (1e-9 rad by default).
    synchronization : {"time", "phase", "none"}
        Ruckig's synchronization of the joints' profiles in :meth:`step`.
    """

    def __init__(self, limits: JointLimits, dt: float, *, horizon: float = 0.01,
                 approach_above: float = 0.1,
                 position_margin=0.01, guard_tolerance: float = 1e-9,
                 synchronization: str = "time"):
        if not isinstance(limits, JointLimits):
            raise ValueError("limits must be a JointLimits")
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"control period dt must be a finite number > 0 s; got {dt}")
        if not (math.isfinite(horizon) and horizon >= dt):
            raise ValueError(f"horizon must be >= dt = {dt} s; got {horizon}")
        if not (math.isfinite(approach_above) and approach_above > horizon):
            raise ValueError(f"approach_above must be > horizon = {horizon} s; got {approach_above}")
        d = limits.n_joints
        margin = joint_vector("position_margin", position_margin, d)
        half_range = 0.5 * (limits.upper - limits.lower)
        if np.any(margin < 0) or np.any(margin >= half_range):
            raise ValueError(f"position_margin must be in [0, half the joint range) per joint; "
                             f"got {margin.tolist()}, half ranges {half_range.tolist()}")
        sync = {"time": Synchronization.Time, "phase": Synchronization.Phase,
                "none": Synchronization.No}.get(synchronization)
        if sync is None:
            raise ValueError(f"synchronization must be 'time', 'phase' or 'none'; got {synchronization!r}")
        self.limits = limits
        self.dt = float(dt)
        self.n_joints = d
        self.horizon = float(horizon)
        self.approach_above = float(approach_above)
        self.guard_tolerance = float(guard_tolerance)
        self._lo = limits.lower
        self._hi = limits.upper
        self._v = limits.max_velocity
        self._a = limits.max_acceleration
        self._j = limits.max_jerk
        self._t_lo = limits.lower + margin
        self._t_hi = limits.upper - margin
        self._lims = list(zip(self._lo.tolist(), self._hi.tolist(), self._a.tolist(), self._j.tolist()))
        # Upper bound of the braking distance of any state inside the v/a/j limits with
        # |v + a|a|/(2j)| <= v_max (true along every ruckig trajectory): the time-optimal brake
        # lasts at most 2a/j + v/a and its speed stays <= v_max; factor 2 for safety. Joints
        # farther than this from both limits skip the exact brake computation.
        self._guard_zone = (2.0 * self._v * (2.0 * self._a / self._j + self._v / self._a) + 1e-6).tolist()

        self._otg = Ruckig(d)
        self._inp = InputParameter(d)
        self._traj = Trajectory(d)
        self._inp.max_velocity = list(self._v)
        self._inp.max_acceleration = list(self._a)
        self._inp.max_jerk = list(self._j)
        self._inp.synchronization = sync
        self._inp_sync = InputParameter(d)
        self._inp_sync.max_velocity = list(self._v)
        self._inp_sync.max_acceleration = list(self._a)
        self._inp_sync.max_jerk = list(self._j)
        self._inp_sync.synchronization = Synchronization.Time
        # constant per input: step() plans at least one period, track() exactly the horizon
        self._inp.minimum_duration = self.dt
        self._inp_sync.minimum_duration = self.horizon
        self._h_max = self.horizon * (1 + 1e-9)   # a tracking plan at most this long arrives in time
        self._dt_max = self.dt * (1 + 1e-9)       # a step() plan at most this long: REACHED
        # NEVER set intermediate_positions (the community build would call a cloud API).

        self._q = self._qd = self._qdd = None
        self._stopping = False
        # track(): one planner per joint (ruckig ignores minimum_duration per joint without
        # synchronization, and synchronizing would let one joint far from its reference drag
        # the others off theirs)
        self._j_otg = [Ruckig(1) for _ in range(d)]
        self._j_inp = [InputParameter(1) for _ in range(d)]
        for j, ji in enumerate(self._j_inp):
            ji.max_velocity = [float(self._v[j])]
            ji.max_acceleration = [float(self._a[j])]
            ji.max_jerk = [float(self._j[j])]
        self._j_traj = [Trajectory(1) for _ in range(d)]
        self._traj_c = [Trajectory(1) for _ in range(d)]  # committed interception plans
        # while APPROACHING: (time of the committed target after the plans' start, time of the
        # current state after the plans' start, committed target rows, approaching joints)
        self._appr: tuple[float, float, tuple, list[int]] | None = None
        self._no = np.zeros(d, dtype=bool)  # shared by every sample without a flagged joint
        self._no.setflags(write=False)
        self._zero_list = [0.0] * d
        self._shape = (d,)
        self._tlims = list(zip(self._t_lo.tolist(), self._t_hi.tolist(), self._v.tolist(),
                               self._a.tolist(), (2.0 * self._j).tolist()))

    # ---- state -------------------------------------------------------------------------
    @property
    def started(self) -> bool:
        return self._q is not None

    @property
    def state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Current (q, qd, qdd), each shape (d,)."""
        self._require_started()
        return np.array(self._q), np.array(self._qd), np.array(self._qdd)

    @property
    def stopping(self) -> bool:
        """A stop was requested (cleared by :meth:`resume` or :meth:`start`)."""
        return self._stopping

    def at_rest(self, vel_tol: float = 1e-6, acc_tol: float = 1e-5) -> bool:
        """|qd| <= vel_tol and |qdd| <= acc_tol for every joint."""
        if self._q is None:
            self._require_started()
        return max(map(abs, self._qd)) <= vel_tol and max(map(abs, self._qdd)) <= acc_tol

    def _require_started(self):
        if self._q is None:
            raise RuntimeError("RuckigStreamer: call start(q, qd, qdd) with the robot's measured "
                               "joint state before streaming")

    # ---- commands ----------------------------------------------------------------------
    def start(self, q, qd=None, qdd=None) -> None:
        """(Re)start from the robot's measured state (also to resynchronise mid-motion).

        Raises ValueError if the state is outside the limits (position tolerance
        ``guard_tolerance``, velocity/acceleration 1e-9 relative) or if a joint cannot stop
        before its position limit.
        """
        d = self.n_joints
        names = self.limits.names
        q = joint_vector("start position q", q, d).copy()
        qd = np.zeros(d) if qd is None else joint_vector("start velocity qd", qd, d).copy()
        qdd = np.zeros(d) if qdd is None else joint_vector("start acceleration qdd", qdd, d).copy()
        for label, arr in (("position", q), ("velocity", qd), ("acceleration", qdd)):
            if not np.all(np.isfinite(arr)):
                bad = int(np.argmax(~np.isfinite(arr)))
                raise ValueError(f"start {label} of {names[bad]} is {arr[bad]}; expected a finite number")
        tol = self.guard_tolerance
        out = (q < self._lo - tol) | (q > self._hi + tol)
        if np.any(out):
            i = int(np.argmax(out))
            raise ValueError(f"start position of {names[i]} is {q[i]:.6g} rad, outside its limits "
                             f"[{self._lo[i]:.6g}, {self._hi[i]:.6g}] rad")
        for label, arr, lim, unit in (("velocity", qd, self._v, "rad/s"),
                                      ("acceleration", qdd, self._a, "rad/s^2")):
            over = np.abs(arr) > lim * (1 + 1e-9)
            if np.any(over):
                i = int(np.argmax(over))
                raise ValueError(f"start {label} of {names[i]} is {arr[i]:.6g} {unit}; its limit "
                                 f"is ±{lim[i]:.6g} {unit}")
            np.clip(arr, -lim, lim, out=arr)
        np.clip(q, self._lo, self._hi, out=q)
        for i, (lo, hi, amax, jmax) in enumerate(self._lims):
            b_lo, b_hi, _, _, _ = brake_joint(q[i], qd[i], qdd[i], amax, jmax, 0.0)
            if b_lo < lo - tol or b_hi > hi + tol:
                raise ValueError(f"{names[i]} at {q[i]:.6g} rad moving at {qd[i]:.6g} rad/s cannot "
                                 f"stop inside its limits [{lo:.6g}, {hi:.6g}] rad (its brake "
                                 f"reaches [{b_lo:.6g}, {b_hi:.6g}] rad)")
        self._set_state(q.tolist(), qd.tolist(), qdd.tolist())
        self._stopping = False
        self._appr = None

    def request_stop(self) -> None:
        """Cancel: from now on :meth:`step`/:meth:`track` ignore their targets and brake every
        joint (time-optimal, jerk-limited, independently per joint) until at rest, then hold."""
        self._stopping = True

    def resume(self) -> None:
        """Clear a stop request; the next :meth:`step`/:meth:`track` plans from the current state."""
        self._stopping = False
        self._appr = None

    def stop_step(self) -> StreamState:
        """Request a stop and produce one braking tick (for ticks without a reference)."""
        self._require_started()
        self._stopping = True
        return self._brake_tick(_STOPPING)

    def step(self, target_q, target_qd=None, target_qdd=None) -> StreamState:
        """Next sample of the time-optimal motion to a target state (re-planned every tick).

        For static or slowly changing targets (e.g. moving to a primitive's start before its
        clock runs); to follow a moving reference use :meth:`track`.

        Parameters
        ----------
        target_q : array, shape (d,)
        target_qd, target_qdd : array, shape (d,), optional (default zeros)
            Clipped to the limits before being handed to ruckig (see module docstring).

        Returns
        -------
        StreamState
            status REACHED once the sample is the (clamped) target state.
        """
        if self._q is None:
            self._require_started()
        if self._stopping:
            return self._brake_tick(_STOPPING)
        self._appr = None
        target, clamped = self._sanitize(target_q, target_qd, target_qdd)
        try:
            traj = self._plan(target, self._inp)
        except RuckigError as exc:
            return self._brake_tick(_ERROR, clamped, str(exc).strip())
        status = _REACHED if traj.duration <= self._dt_max else _TRACKING
        p, v, a = traj.at_time(self.dt)[:3]
        return self._advance(p, v, a, status, clamped)

    def track(self, reference: ReferenceFn) -> StreamState:
        """Next sample following a moving reference (TRACKING / APPROACHING, see class doc).

        Parameters
        ----------
        reference : callable
            ``reference(ahead)`` returns the reference state (q, qd, qdd), each shape (d,),
            ``ahead`` seconds after the current state's time (ahead >= dt). With a
            :class:`~deepprompt_ros.execution.phase_clock.PhaseClock` that is ticked after
            this call: :func:`~deepprompt_ros.execution.reference.clock_reference`, i.e.
            ``lambda ahead: reference_state(fn, clock.peek(ahead))``. A different callable at
            any tick splices onto another reference; the state stays continuous.

        Returns
        -------
        StreamState
        """
        if self._q is None:
            self._require_started()
        if self._stopping:
            return self._brake_tick(_STOPPING)
        dt = self.dt
        approaching = ()
        try:
            if self._appr is not None:
                # APPROACHING joints follow the committed interception plans while the
                # reference still passes through the committed target at the committed time
                d = self.n_joints
                p, v, a = [0.0] * d, [0.0] * d, [0.0] * d
                clamped = np.zeros(d, dtype=bool)
                ahead_c, elapsed, target_c, joints = self._appr
                self._appr = None
                ahead = ahead_c - elapsed
                if ahead >= dt * (1 + 1e-9):
                    target, clamped_a = self._reference_target(reference, ahead)
                    if self._on_committed(target, target_c, joints):
                        t = elapsed + dt
                        traj_c = self._traj_c
                        for j in joints:
                            pj, vj, aj = traj_c[j].at_time(t)[:3]
                            p[j], v[j], a[j] = pj[0], vj[0], aj[0]
                            clamped[j] = clamped_a[j]
                        approaching = joints
                        self._appr = (ahead_c, t, target_c, joints)
            # TRACKING joints: the reference `horizon` ahead, arriving exactly then
            h = self.horizon
            target, clamped_h = self._reference_target(reference, h)
            if not approaching:
                # fast path: one time-synchronized plan of all joints; when every joint can
                # arrive within the horizon, its duration is the horizon and each joint's
                # profile is the one its own planner would give (per-joint fallback otherwise)
                traj = self._plan(target, self._inp_sync)
                if traj.duration <= self._h_max:
                    p, v, a = traj.at_time(dt)[:3]
                    return self._advance(p, v, a, _TRACKING, clamped_h)
                d = self.n_joints
                p, v, a = [0.0] * d, [0.0] * d, [0.0] * d
                clamped = np.zeros(d, dtype=bool)
            far = []
            approach_above = self.approach_above
            for j in range(self.n_joints):
                if approaching and j in approaching:
                    continue
                traj = self._plan_joint(j, target, h)
                if traj.duration > approach_above:
                    far.append(j)
                else:
                    pj, vj, aj = traj.at_time(dt)[:3]
                    p[j], v[j], a[j] = pj[0], vj[0], aj[0]
                    clamped[j] = clamped_h[j]
            if far:
                self._commit_approach(reference, far, approaching, p, v, a, clamped)
        except RuckigError as exc:
            return self._brake_tick(_ERROR, None, str(exc).strip())
        status = _TRACKING if self._appr is None else _APPROACHING
        return self._advance(p, v, a, status, clamped)

    @staticmethod
    def _on_committed(target, target_c, joints) -> bool:
        """The reference passes through the committed target of every approaching joint
        (position, velocity, acceleration equal up to 1e-9 relative)."""
        for k in range(3):
            row, row_c = target[k], target_c[k]
            for j in joints:
                c = row_c[j]
                if not abs(row[j] - c) <= 1e-9 * (1.0 + abs(c)):
                    return False
        return True

    def _commit_approach(self, reference, far, approaching, p, v, a, clamped):
        """Commit the joints ``far`` (and those already approaching, re-planned with them) to
        a common interception time: fixed point ahead = max_j duration_j(state_j ->
        reference_j(ahead)). Fills p, v, a, clamped of those joints in place."""
        joints = sorted(set(far) | set(approaching))
        ahead = max([self._j_traj[j].duration for j in far]
                    + ([self._appr[0] - self._appr[1]] if self._appr is not None else []))
        for iteration in range(4):
            target, clamped_a = self._reference_target(reference, ahead)
            longest = max(self._plan_joint(j, target, ahead).duration for j in joints)
            if longest <= ahead * (1 + 1e-9):
                break
            if iteration < 3:
                ahead = longest
        # not converged: the plans reach reference(ahead) late; the approach then ends at
        # `ahead` and TRACKING (or a new interception) takes over
        for j in joints:
            self._j_traj[j], self._traj_c[j] = self._traj_c[j], self._j_traj[j]
            pj, vj, aj = self._traj_c[j].at_time(self.dt)[:3]
            p[j], v[j], a[j] = pj[0], vj[0], aj[0]
            clamped[j] = clamped_a[j]
        self._appr = (ahead, self.dt, target, joints)

    # ---- internals ---------------------------------------------------------------------
    def _reference_target(self, reference: ReferenceFn, ahead: float):
        ref = reference(ahead)
        try:
            q, qd, qdd = ref
        except (TypeError, ValueError):
            raise ValueError("reference(ahead) must return (q, qd, qdd), each of shape "
                             f"({self.n_joints},)") from None
        return self._sanitize(q, qd, qdd)

    def _sanitize(self, target_q, target_qd, target_qdd):
        """Layer 1 of the module docstring: clamp the target state (plain floats: faster than
        numpy for d <= 7).

        Returns
        -------
        target : tuple of 3 lists of d floats
            q, qd, qdd handed to ruckig.
        clamped : array of bool, shape (d,)
        """
        tq = self._target_row("position", target_q)
        tv = self._target_row("velocity", target_qd)
        ta = self._target_row("acceleration", target_qdd)
        clamped = None
        i = 0
        # (the rows are fresh lists: values that change are written in place)
        for (lo, hi, vmax, amax, two_j), q, v, a in zip(self._tlims, tq, tv, ta):
            # one test for the three: x * 0 is 0 for a finite x, NaN for inf / NaN (a finite
            # sum that overflows only costs the exact check)
            if (q + v + a) * 0.0 != 0.0 and not (math.isfinite(q) and math.isfinite(v)
                                                  and math.isfinite(a)):
                raise ValueError(f"target state of {self.limits.names[i]} is (q={q}, qd={v}, "
                                 f"qdd={a}); expected finite numbers")
            if q < lo or q > hi:
                tq[i] = lo if q < lo else hi
                tv[i] = ta[i] = 0.0  # velocity and acceleration 0
                if clamped is None:
                    clamped = np.zeros(len(tq), dtype=bool)
                clamped[i] = True
            else:
                if v > vmax:
                    v = tv[i] = vmax
                elif v < -vmax:
                    v = tv[i] = -vmax
                # |v| + a²/(2j) <= v_max: otherwise the velocity before (a opposing v) or after
                # (a along v) the target state exceeds v_max and ruckig rejects the target.
                # (|v| <= v_max here, so the root's argument is >= 0.)
                cap = math.sqrt(two_j * (vmax - abs(v))) * (1.0 - 1e-9)
                if amax < cap:
                    cap = amax
                if a > cap:
                    ta[i] = cap
                elif a < -cap:
                    ta[i] = -cap
            i += 1
        return (tq, tv, ta), (self._no if clamped is None else clamped)

    def _target_row(self, label: str, x) -> list:
        """One target array (d,) as a new list of floats (a shape error names the joints)."""
        if x is None:
            return self._zero_list[:]
        if type(x) is not np.ndarray or x.dtype is not _F64:
            x = np.asarray(x, dtype=float)
        if x.shape != self._shape:
            d = self.n_joints
            raise ValueError(f"target {label} has shape {x.shape}; expected ({d},), one value "
                             f"per joint: {', '.join(self.limits.names)}")
        return x.tolist()

    def _plan(self, target, inp: InputParameter) -> Trajectory:
        """Plan all joints together from the current state (``inp``: the step() input with
        the user's synchronization and minimum duration dt, or the time-synchronized
        tracking input with minimum duration ``horizon``)."""
        inp.current_position = self._q
        inp.current_velocity = self._qd
        inp.current_acceleration = self._qdd
        inp.target_position = target[0]
        inp.target_velocity = target[1]
        inp.target_acceleration = target[2]
        self._otg.calculate(inp, self._traj)
        return self._traj

    def _plan_joint(self, j: int, target, min_duration: float) -> Trajectory:
        inp = self._j_inp[j]
        inp.current_position = [self._q[j]]
        inp.current_velocity = [self._qd[j]]
        inp.current_acceleration = [self._qdd[j]]
        inp.target_position = [target[0][j]]
        inp.target_velocity = [target[1][j]]
        inp.target_acceleration = [target[2][j]]
        inp.minimum_duration = min_duration
        traj = self._j_traj[j]
        self._j_otg[j].calculate(inp, traj)
        return traj

    def _advance(self, p: list, v: list, a: list, status: StreamStatus,
                 clamped: np.ndarray) -> StreamState:
        """Pass the proposed next state (lists of d floats, modified in place) through the
        position guard (layer 2) and make it the current state."""
        guarded = self._no
        i = 0
        for pi, (lo, hi, amax, jmax), z in zip(p, self._lims, self._guard_zone):
            if pi - lo >= z and hi - pi >= z:
                i += 1
                continue
            tol = self.guard_tolerance
            b_lo, b_hi, _, _, _ = brake_joint(pi, v[i], a[i], amax, jmax, 0.0)
            if b_lo < lo - tol or b_hi > hi + tol:
                # brake from the current state instead (within limits by the invariant)
                _, _, p[i], v[i], a[i] = brake_joint(self._q[i], self._qd[i], self._qdd[i],
                                                      amax, jmax, self.dt)
                if guarded is self._no:
                    guarded = self._no.copy()
                guarded[i] = True
            i += 1
        if guarded is not self._no:
            status = _GUARD
            if self._appr is not None:  # guarded joints no longer follow their committed plan
                joints = [j for j in self._appr[3] if not guarded[j]]
                self._appr = self._appr[:3] + (joints,) if joints else None
        self._q, self._qd, self._qdd = p, v, a
        return _tuple_new(StreamState, (np.array(p), np.array(v), np.array(a), status, guarded, clamped, ""))

    def _set_state(self, q: list, qd: list, qdd: list):
        """Current state as lists of floats (cheaper than numpy for d <= 7 in the tick); the
        planners' inputs take it when they plan."""
        self._q, self._qd, self._qdd = q, qd, qdd

    def _brake_tick(self, status: StreamStatus, clamped=None, error: str = "") -> StreamState:
        """One control period of every joint's brake from the current state."""
        if any(self._qd) or any(self._qdd):
            out = [brake_joint(self._q[i], self._qd[i], self._qdd[i], amax, jmax, self.dt)[2:]
                   for i, (_, _, amax, jmax) in enumerate(self._lims)]
            q, qd, qdd = (list(c) for c in zip(*out))
            self._set_state(q, qd, qdd)
        self._appr = None
        moving = any(self._qd) or any(self._qdd)
        if status == _STOPPING and not moving:
            status = _STOPPED
        clamped = self._no.copy() if clamped is None else clamped
        return StreamState(np.array(self._q), np.array(self._qd), np.array(self._qdd), status,
                           np.ones(self.n_joints, dtype=bool), clamped, error)
