"""Control-rate trajectory streaming: phase clock, primitive reference, Ruckig with joint limits.

A streaming node calls this module from its control timer (e.g. 1 kHz)::

    clock = PhaseClock.linear(dt, duration)            # or rhythmic_clock / from_tau / ...
    streamer = RuckigStreamer(limits, dt)
    streamer.start(q_measured, qd_measured)
    reference = clock_reference(mean_fn, clock)        # reference(ahead) -> (q, qd, qdd)
    # every tick:
    out = streamer.track(reference)
    clock.tick()                                       # clock time = time of out
    publish(out.q, out.qd, out.qdd)                    # the limited command

``mean_fn`` maps phases (k,) to joint positions (k, d) (e.g. a primitive's conditioned mean);
:func:`reference_state` turns it into the target position, velocity and acceleration at the
phase ``ahead`` seconds later, by the chain rule through the clock's phase rate.

Temporal modulation (paper Sec. III-C): the phase is x = τ(t). :class:`PhaseClock` supports the
linear map τ(t) = t/T (or a phase rate 1/T), any τ given as a callable or as knots, reversal
(x runs 1 → 0), rhythmic cycles (x wraps over [0, 1); the rhythmic decoder sees
[sin 2πx, cos 2πx], so the wrap is seamless) and a live change of the speed that keeps x
continuous.

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
   acceleration 0 (joints independent, closed form in ``_brake_joint``). Each tick ruckig
   proposes the next sample; for every joint close enough to a limit that it could matter,
   the exact position extrema of the brake from the *proposed* state are computed. A joint whose brake
   would leave its limits does not take the proposed sample: it takes one tick of the brake from
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

What is (and is not) guaranteed about the samples, checked by :func:`check_limits`: every
sample's |qd| ≤ v_max and |qdd| ≤ a_max, successive samples satisfy
|Δq|/dt ≤ v_max, |Δqd|/dt ≤ a_max and |Δqdd|/dt ≤ j_max (finite-difference jerk of the reported
accelerations; the continuous trajectory between samples is jerk-limited piecewise, this is the
per-sample consequence), and lower ≤ q ≤ upper. The first sample after :meth:`start` is checked
against the measured state given to ``start``. Not guaranteed: anything about a state given to
``start`` that is outside the limits or cannot stop inside them (``start`` raises); and the
exact brake check is skipped for joints farther from their limits than a conservative
stopping-distance bound (see ``_guard_zone``). If ruckig rejects a tick's input, that tick
brakes all joints (status ERROR) and the next tick plans again.
"""
from __future__ import annotations

import dataclasses
import enum
import math
from typing import Callable, NamedTuple, Sequence

import numpy as np
from ruckig import InputParameter, Ruckig, RuckigError, Synchronization, Trajectory

#: ``tuple.__new__(NamedTupleClass, values)`` builds a NamedTuple without its Python-level
#: ``__new__`` (~0.3 µs less per sample on the control-rate paths).
_tuple_new = tuple.__new__

__all__ = [
    "JointLimits",
    "PhaseSample",
    "PhaseClock",
    "ReferenceState",
    "reference_state",
    "clock_reference",
    "StreamStatus",
    "StreamState",
    "RuckigStreamer",
    "LimitReport",
    "check_limits",
]


def _vector(name: str, value, n: int | None = None) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0 and n is not None:
        arr = np.full(n, float(arr))
    if arr.ndim != 1:
        raise ValueError(f"{name} must be a 1-D array of length {n if n is not None else 'd'}; "
                         f"got shape {arr.shape}")
    if n is not None and arr.shape[0] != n:
        raise ValueError(f"{name} has {arr.shape[0]} values; expected {n} (one per joint)")
    return arr


# --------------------------------------------------------------------------------------------
# Joint limits
# --------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class JointLimits:
    """Per-joint kinematic limits, all arrays of shape (d,).

    Attributes
    ----------
    lower, upper : array, shape (d,)
        Position limits [rad]. ``-inf``/``inf`` for continuous joints.
    max_velocity, max_acceleration, max_jerk : array, shape (d,)
        Symmetric limits [rad/s, rad/s², rad/s³], finite and positive.
    names : tuple of str
        Joint names used in messages (default ``joint_1..joint_d``).
    """

    lower: np.ndarray
    upper: np.ndarray
    max_velocity: np.ndarray
    max_acceleration: np.ndarray
    max_jerk: np.ndarray
    names: tuple[str, ...] = ()

    def __post_init__(self):
        lower = _vector("lower", self.lower)
        d = lower.shape[0]
        if d == 0:
            raise ValueError("JointLimits needs at least one joint; got 0")
        upper = _vector("upper", self.upper, d)
        fields = {"lower": lower, "upper": upper}
        for name in ("max_velocity", "max_acceleration", "max_jerk"):
            arr = _vector(name, getattr(self, name), d)
            if not np.all(np.isfinite(arr)) or np.any(arr <= 0):
                raise ValueError(f"{name} must be finite and > 0 for every joint; got {arr.tolist()}")
            fields[name] = arr
        if np.any(np.isnan(lower)) or np.any(np.isnan(upper)):
            raise ValueError("position limits must not be NaN (use -inf/inf for continuous joints)")
        if np.any(lower >= upper):
            bad = int(np.argmax(lower >= upper))
            raise ValueError(f"joint {bad + 1}: lower limit {lower[bad]} must be < upper limit {upper[bad]}")
        names = tuple(self.names) if self.names else tuple(f"joint_{i + 1}" for i in range(d))
        if len(names) != d:
            raise ValueError(f"names has {len(names)} entries; expected {d} (one per joint)")
        for key, arr in fields.items():
            arr.setflags(write=False)
            object.__setattr__(self, key, arr)
        object.__setattr__(self, "names", names)

    @property
    def n_joints(self) -> int:
        """d, the number of joints."""
        return int(self.lower.shape[0])


# --------------------------------------------------------------------------------------------
# Phase clock (temporal modulation x = τ(t), paper Sec. III-C)
# --------------------------------------------------------------------------------------------
class PhaseSample(NamedTuple):
    """Phase at one control tick.

    Attributes
    ----------
    t : float
        Wall time since the clock started [s] (ticks · dt).
    x : float
        Phase in [0, 1] (rhythmic: in [0, 1), wraps every cycle).
    x_dot, x_ddot : float
        dx/dt [1/s] and d²x/dt² [1/s²] (0 once done).
    cycle : int
        Completed cycles (rhythmic), 0 for discrete primitives.
    done : bool
        The end of the motion (x = 1, or x = 0 reversed, or the last cycle) was reached.
    """

    t: float
    x: float
    x_dot: float
    x_ddot: float
    cycle: int
    done: bool


class _Pchip:
    """Monotone piecewise-cubic Hermite interpolant (Fritsch & Carlson 1980, SIAM J. Numer.
    Anal. 17(2)) of knots (t_i, x_i): C¹, no overshoot, monotone wherever the knots are."""

    def __init__(self, t: np.ndarray, x: np.ndarray):
        self.t, self.x = t, x
        h = np.diff(t)
        delta = np.diff(x) / h
        m = np.zeros_like(x)
        if len(t) == 2:
            m[:] = delta[0]
        else:
            for i in range(1, len(t) - 1):
                if delta[i - 1] * delta[i] > 0:
                    w1 = 2 * h[i] + h[i - 1]
                    w2 = h[i] + 2 * h[i - 1]
                    m[i] = (w1 + w2) / (w1 / delta[i - 1] + w2 / delta[i])
            for end, (h0, h1, d0, d1) in ((0, (h[0], h[1], delta[0], delta[1])),
                                          (-1, (h[-1], h[-2], delta[-1], delta[-2]))):
                mm = ((2 * h0 + h1) * d0 - h0 * d1) / (h0 + h1)
                if np.sign(mm) != np.sign(d0):
                    mm = 0.0
                elif np.sign(d0) != np.sign(d1) and abs(mm) > 3 * abs(d0):
                    mm = 3 * d0
                m[end] = mm
        self.m, self.h = m, h

    def __call__(self, u: float) -> tuple[float, float, float]:
        """Value, first and second derivative at u (clipped to the knot range)."""
        t = self.t
        u = min(max(u, t[0]), t[-1])
        i = int(np.searchsorted(t, u, side="right") - 1)
        i = min(max(i, 0), len(t) - 2)
        h = self.h[i]
        s = (u - t[i]) / h
        x0, x1, m0, m1 = self.x[i], self.x[i + 1], self.m[i] * h, self.m[i + 1] * h
        s2, s3 = s * s, s * s * s
        val = (2 * s3 - 3 * s2 + 1) * x0 + (s3 - 2 * s2 + s) * m0 + (-2 * s3 + 3 * s2) * x1 + (s3 - s2) * m1
        d1 = ((6 * s2 - 6 * s) * x0 + (3 * s2 - 4 * s + 1) * m0 + (-6 * s2 + 6 * s) * x1 + (3 * s2 - 2 * s) * m1) / h
        d2 = ((12 * s - 6) * x0 + (6 * s - 4) * m0 + (-12 * s + 6) * x1 + (6 * s - 2) * m1) / (h * h)
        return float(val), float(d1), float(d2)


class PhaseClock:
    """Maps control ticks to the phase x (temporal modulation, paper Sec. III-C).

    The clock integrates an internal *clock time* u at a speed k (the time scale, 1 = nominal)
    and maps it to the phase, x = τ(u):

    - linear: τ(u) = u / T on u ∈ [0, T]; the phase rate is dx/dt = k / T;
    - τ given as a callable on [0, T] or as knots (monotone cubic through them);
    - rhythmic: x = (u / T) mod 1 for ``cycles`` cycles (or forever), T the period;
    - ``reverse=True``: x → 1 - x (rhythmic: x → (1 - x) mod 1), the motion runs backwards.

    Changing the speed while moving (:meth:`set_rate`, :meth:`set_time_scale`) only changes how
    fast u advances from the current tick on, so x is continuous; with ``ramp_time > 0`` the
    speed changes linearly over that time, so dx/dt is continuous too.

    Use the constructors :meth:`linear`, :meth:`from_rate`, :meth:`from_tau`,
    :meth:`from_knots` and :meth:`rhythmic`.

    Parameters
    ----------
    dt : float
        Control period [s].
    duration : float
        T: duration of the motion at nominal speed (rhythmic: the period) [s].
    tau : callable u -> x, or None
        Time map on [0, T] with values in [0, 1]; None for the linear map u / T.
    rhythmic : bool
    cycles : int or None
        Number of cycles of a rhythmic clock, None for endless.
    reverse : bool
    time_scale : float
        Initial speed k.
    """

    _TAU_FD_STEP = 1e-4  # relative (to T) step of the central differences of a callable τ

    def __init__(self, dt: float, duration: float, tau: Callable[[float], float] | None = None, *,
                 rhythmic: bool = False, cycles: int | None = None, reverse: bool = False,
                 time_scale: float = 1.0, _pchip: _Pchip | None = None):
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"control period dt must be a finite number > 0 s; got {dt}")
        if not (math.isfinite(duration) and duration > 0):
            raise ValueError(f"duration/period T must be a finite number > 0 s; got {duration}")
        if rhythmic and (tau is not None or _pchip is not None):
            raise ValueError("a rhythmic clock uses the linear map x = (t/T) mod 1; tau/knots are "
                             "only for discrete (non-rhythmic) primitives")
        if cycles is not None:
            if not rhythmic:
                raise ValueError("cycles is only meaningful for a rhythmic clock")
            if int(cycles) != cycles or cycles < 1:
                raise ValueError(f"cycles must be an integer >= 1 or None (endless); got {cycles}")
            cycles = int(cycles)
        if not math.isfinite(time_scale):
            raise ValueError(f"time_scale must be finite; got {time_scale}")
        self.dt = float(dt)
        self.duration = float(duration)
        self.rhythmic = bool(rhythmic)
        self.cycles = cycles
        self.reverse = bool(reverse)
        self._tau = tau
        self._pchip = _pchip
        if rhythmic:
            self._u_end = math.inf if cycles is None else cycles * self.duration
        else:
            self._u_end = self.duration
        self._linear = not rhythmic and tau is None and _pchip is None
        self._u = 0.0
        self._k = float(time_scale)
        self._k_target = self._k
        self._k_slope = 0.0
        self._ticks = 0
        if tau is not None:
            for u in (0.0, self.duration):
                self._eval_tau(u)  # validates the range at the ends
        self._sample = self._make_sample()

    # ---- constructors ------------------------------------------------------------------
    @classmethod
    def linear(cls, dt: float, duration: float, *, reverse: bool = False) -> "PhaseClock":
        """x = t / T (reverse: 1 - t / T); done at t = T."""
        return cls(dt, duration, reverse=reverse)

    @classmethod
    def from_rate(cls, dt: float, rate: float, *, reverse: bool = False) -> "PhaseClock":
        """Linear clock with phase rate ``rate`` [phase/s] (T = 1 / rate)."""
        if not (math.isfinite(rate) and rate > 0):
            raise ValueError(f"phase rate must be a finite number > 0 phase/s; got {rate}")
        return cls(dt, 1.0 / rate, reverse=reverse)

    @classmethod
    def from_tau(cls, dt: float, tau: Callable[[float], float], duration: float, *,
                 reverse: bool = False) -> "PhaseClock":
        """x = τ(t) for a callable τ: [0, T] -> [0, 1] (monotone to move forward; a
        non-monotone τ goes back and forth). Derivatives by central differences of τ."""
        if not callable(tau):
            raise ValueError("tau must be a callable t -> x")
        return cls(dt, duration, tau, reverse=reverse)

    @classmethod
    def from_knots(cls, dt: float, times: Sequence[float], phases: Sequence[float], *,
                   reverse: bool = False) -> "PhaseClock":
        """τ through knots (t_i, x_i), t_0 = 0, strictly increasing times, phases in [0, 1];
        monotone piecewise-cubic (C¹) interpolation, so monotone knots give a monotone τ."""
        t = np.asarray(times, dtype=float)
        x = np.asarray(phases, dtype=float)
        if t.ndim != 1 or x.shape != t.shape or t.shape[0] < 2:
            raise ValueError(f"times and phases must be 1-D of equal length >= 2; got shapes "
                             f"{t.shape} and {x.shape}")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(x))):
            raise ValueError("knot times and phases must be finite")
        if t[0] != 0.0 or np.any(np.diff(t) <= 0):
            raise ValueError(f"knot times must start at 0 and be strictly increasing; got {t.tolist()}")
        if np.any(x < 0) or np.any(x > 1):
            raise ValueError(f"knot phases must lie in [0, 1]; got {x.tolist()}")
        return cls(dt, float(t[-1]), reverse=reverse, _pchip=_Pchip(t, x))

    @classmethod
    def rhythmic_clock(cls, dt: float, period: float, *, cycles: int | None = None,
                       reverse: bool = False) -> "PhaseClock":
        """x = (t / period) mod 1 for ``cycles`` cycles (None: endless)."""
        return cls(dt, period, rhythmic=True, cycles=cycles, reverse=reverse)

    # ---- state -------------------------------------------------------------------------
    @property
    def sample(self) -> PhaseSample:
        """Phase at the current tick."""
        return self._sample

    @property
    def x(self) -> float:
        return self._sample.x

    @property
    def done(self) -> bool:
        return self._sample.done

    @property
    def rate(self) -> float:
        """Current phase rate dx/dt [phase/s] (negative when reversed)."""
        return self._sample.x_dot

    @property
    def time_scale(self) -> float:
        """Current speed k of the clock time (1 = nominal)."""
        return self._k

    def set_time_scale(self, time_scale: float, ramp_time: float = 0.0) -> None:
        """Change the speed k from this tick on (linearly over ``ramp_time`` seconds).
        x is unchanged by the call; with ``ramp_time > 0`` dx/dt is continuous as well.
        A negative speed runs the clock time backwards (it stops at u = 0)."""
        if not math.isfinite(time_scale):
            raise ValueError(f"time_scale must be finite; got {time_scale}")
        if not (math.isfinite(ramp_time) and ramp_time >= 0):
            raise ValueError(f"ramp_time must be >= 0 s; got {ramp_time}")
        self._k_target = float(time_scale)
        if ramp_time < self.dt:
            self._k = self._k_target
            self._k_slope = 0.0
        else:
            self._k_slope = (self._k_target - self._k) / ramp_time
        self._sample = self._make_sample()

    def set_rate(self, rate: float, ramp_time: float = 0.0) -> None:
        """Change the phase rate |dx/dt| to ``rate`` [phase/s] (linear and rhythmic clocks).
        The phase itself does not jump (temporal modulation while moving)."""
        if self._tau is not None or self._pchip is not None:
            raise ValueError("set_rate needs a linear or rhythmic clock (its phase rate is k/T); "
                             "for a clock with a τ(t) map use set_time_scale")
        if not math.isfinite(rate):
            raise ValueError(f"phase rate must be finite; got {rate}")
        self.set_time_scale(rate * self.duration, ramp_time)

    def _integrate(self, ahead: float) -> tuple[float, float, float]:
        """Clock time u, speed k and its slope after ``ahead`` seconds (exact for the linear
        speed ramp of set_time_scale, then constant speed)."""
        k, slope = self._k, self._k_slope
        if slope != 0.0:
            t_ramp = (self._k_target - k) / slope
            if ahead < t_ramp:
                u = self._u + k * ahead + 0.5 * slope * ahead * ahead
                k = k + slope * ahead
            else:
                u = self._u + k * t_ramp + 0.5 * slope * t_ramp * t_ramp + self._k_target * (ahead - t_ramp)
                k, slope = self._k_target, 0.0
        else:
            u = self._u + k * ahead
        if u >= self._u_end - 1e-9 * self.dt:  # rounding of the summed ticks: end exactly
            u = self._u_end
        return min(max(u, 0.0), self._u_end), k, slope

    def tick(self) -> PhaseSample:
        """Advance by one control period and return the phase of the new tick."""
        self._u, self._k, self._k_slope = self._integrate(self.dt)
        self._ticks += 1
        self._sample = self._make_sample()
        return self._sample

    def peek(self, ahead: float) -> PhaseSample:
        """Predicted phase ``ahead`` seconds after the current tick at the current speed
        (and speed ramp), without advancing the clock. Used to look ahead in tracking."""
        if not (0.0 <= ahead < math.inf):  # (False for NaN too)
            raise ValueError(f"look-ahead must be >= 0 s; got {ahead}")
        u, k, slope = self._integrate(ahead)
        return self._make_sample(u, k, slope, self._ticks * self.dt + ahead)

    def reset(self) -> None:
        """Back to x at t = 0, keeping the current speed."""
        self._u = 0.0
        self._ticks = 0
        self._sample = self._make_sample()

    # ---- maps --------------------------------------------------------------------------
    def _eval_tau(self, u: float) -> tuple[float, float, float]:
        if self._pchip is not None:
            return self._pchip(u)
        if self._tau is None:
            return u / self.duration, 1.0 / self.duration, 0.0
        T = self.duration
        h = self._TAU_FD_STEP * T
        if u - h < 0.0:      # one-sided stencils at the ends of [0, T]
            lo, hi = 0.0, 2 * h
        elif u + h > T:
            lo, hi = T - 2 * h, T
        else:
            lo, hi = u - h, u + h
        mid = 0.5 * (lo + hi)
        f_lo, f_mid, f_hi = (float(self._tau(v)) for v in (lo, mid, hi))
        x = float(self._tau(u))
        for v, f in ((u, x), (lo, f_lo), (hi, f_hi)):
            if not (math.isfinite(f) and -1e-12 <= f <= 1 + 1e-12):
                raise ValueError(f"tau({v:.6g}) = {f}; a time map must return a phase in [0, 1]")
        d1 = (f_hi - f_lo) / (hi - lo)
        d2 = (f_hi - 2 * f_mid + f_lo) / (h * h)
        return min(max(x, 0.0), 1.0), d1, d2

    def _make_sample(self, u: float | None = None, k: float | None = None,
                     k_dot: float | None = None, t: float | None = None) -> PhaseSample:
        if u is None:
            u, k, k_dot, t = self._u, self._k, self._k_slope, self._ticks * self.dt
        if self._linear:  # x = u / T (the common case, inlined: called 2-3 times per tick)
            T = self.duration
            done = u >= self._u_end
            if done or (u <= 0.0 and k < 0):
                x_dot = x_ddot = 0.0
            else:
                x_dot = 1.0 / T * k
                x_ddot = 0.0 * k * k + 1.0 / T * k_dot
            if self.reverse:
                return _tuple_new(PhaseSample, (t, 1.0 - u / T, -x_dot, -x_ddot, 0, done))
            return _tuple_new(PhaseSample, (t, u / T, x_dot, x_ddot, 0, done))
        if self.rhythmic:
            done = u >= self._u_end
            s = u / self.duration
            cycle = int(math.floor(s))
            x = s - cycle
            x_dot = 0.0 if done else k / self.duration
            x_ddot = 0.0 if done else k_dot / self.duration
            if self.reverse:
                x = (1.0 - x) % 1.0
                x_dot, x_ddot = -x_dot, -x_ddot
            return PhaseSample(t, x, x_dot, x_ddot, cycle, done)
        done = u >= self._u_end
        x, d1, d2 = self._eval_tau(u)
        at_stop = done or (u <= 0.0 and k < 0)
        x_dot = 0.0 if at_stop else d1 * k
        x_ddot = 0.0 if at_stop else d2 * k * k + d1 * k_dot
        if self.reverse:
            x, x_dot, x_ddot = 1.0 - x, -x_dot, -x_ddot
        return PhaseSample(t, x, x_dot, x_ddot, 0, done)


# --------------------------------------------------------------------------------------------
# Reference (target) state from the primitive
# --------------------------------------------------------------------------------------------
class ReferenceState(NamedTuple):
    """Target joint state of the primitive at one tick, arrays of shape (d,)."""

    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray


def reference_state(target_fn: Callable[[np.ndarray], np.ndarray], phase: PhaseSample, *,
                    periodic: bool = False, h: float = 1e-3) -> ReferenceState:
    """Target position, velocity and acceleration of a primitive at the phase of one tick.

    With y(x) the primitive (e.g. its mean μ_y(z, x)) and x = τ(t) (paper Sec. III-C), by the
    chain rule::

        qd  = y'(x) · dx/dt
        qdd = y''(x) · (dx/dt)² + y'(x) · d²x/dt²

    y' and y'' are central finite differences in phase with step h (second order; near the
    ends of [0, 1] a one-sided stencil inside [0, 1], or wrapped when ``periodic``). The three
    phases are evaluated in ONE call of ``target_fn``. Truncation error is O(h²); rounding error
    of y'' is O(eps·|y|/h²): h = 1e-3 suits float64 primitives, use h ≈ 1e-2 for float32 ones.
    When the primitive has analytic derivatives, compute qd and qdd yourself and pass them to
    :meth:`RuckigStreamer.step` directly.

    Parameters
    ----------
    target_fn : callable
        Maps phases, array shape (3,), to joint positions, array shape (3, d).
    phase : PhaseSample
        From :meth:`PhaseClock.tick`.
    periodic : bool
        The primitive is rhythmic (y(x) = y(x + 1)).
    h : float
        Phase step of the finite differences, 0 < h <= 0.25.

    Returns
    -------
    ReferenceState
        q, qd, qdd, each shape (d,).
    """
    if not (0.0 < h <= 0.25):
        raise ValueError(f"finite-difference step h must be in (0, 0.25]; got {h}")
    x = phase.x
    if periodic:
        xs = np.array([(x - h) % 1.0, x, (x + h) % 1.0])
        offset = 0  # centred stencil
    elif x - h < 0.0:
        xs = np.array([x, x + h, x + 2 * h])
        offset = -1
    elif x + h > 1.0:
        xs = np.array([x - 2 * h, x - h, x])
        offset = 1
    else:
        xs = np.array([x - h, x, x + h])
        offset = 0
    ys = np.asarray(target_fn(xs), dtype=float)
    if ys.ndim != 2 or ys.shape[0] != 3:
        raise ValueError(f"target_fn must map phases of shape (3,) to positions of shape (3, d); "
                         f"got shape {ys.shape}")
    y0, y1, y2 = ys
    d2 = (y0 - 2 * y1 + y2) / (h * h)
    if offset == 0:
        q = y1
        d1 = (y2 - y0) / (2 * h)
    elif offset < 0:  # x is the first point: second-order forward difference
        q = y0
        d1 = (-3 * y0 + 4 * y1 - y2) / (2 * h)
    else:  # x is the last point: second-order backward difference
        q = y2
        d1 = (3 * y2 - 4 * y1 + y0) / (2 * h)
    qd = d1 * phase.x_dot
    qdd = d2 * phase.x_dot ** 2 + d1 * phase.x_ddot
    return ReferenceState(q.copy(), qd, qdd)


def clock_reference(target_fn: Callable[[np.ndarray], np.ndarray], clock: PhaseClock, *,
                    periodic: bool | None = None, h: float = 1e-3
                    ) -> Callable[[float], ReferenceState]:
    """The ``reference(ahead)`` callable of :meth:`RuckigStreamer.track` for a primitive
    ``target_fn`` (phases (k,) -> positions (k, d)) driven by ``clock``: the reference state
    at the phase the clock predicts ``ahead`` seconds after its current tick
    (:meth:`PhaseClock.peek`), by :func:`reference_state`. ``periodic`` defaults to the
    clock's ``rhythmic``."""
    wrap = clock.rhythmic if periodic is None else bool(periodic)

    def reference(ahead: float) -> ReferenceState:
        return reference_state(target_fn, clock.peek(ahead), periodic=wrap, h=h)
    return reference


# --------------------------------------------------------------------------------------------
# Ruckig streamer
# --------------------------------------------------------------------------------------------
def _brake_joint(q: float, v: float, a: float, a_max: float, j_max: float,
                 t: float) -> tuple[float, float, float, float, float]:
    """Time-optimal jerk-limited brake of one joint to v = 0, a = 0.

    Profile (for a joint whose velocity must decrease; the other case is mirrored): jerk
    -j_max until the acceleration reaches a_p, hold a_p (only when a_p hits -a_max), jerk
    +j_max until a = 0, reached exactly when v = 0. Without the hold, the velocity balance
    v0 + (a0² - a_p²)/(2j) - a_p²/(2j) = 0 gives a_p = -sqrt(j·v0 + a0²/2); with it, the hold
    lasts t2 = (v0 + (a0² - 2a²)/(2j)) / a. The speed stays within
    max(|v0|, |v0 + a0|a0|/(2j)|) and the acceleration within a_max, so the brake of a state
    inside the limits keeps them. Computed here rather than with ruckig's velocity interface
    (its ``position_extrema`` is wrong for velocity-interface trajectories in 0.19.4) so that
    the brake that is checked and the brake that is executed are the same function: stepping
    along it and recomputing gives the same profile, which the position guard relies on.
    Plain floats: for d <= 7 this is faster than numpy on (d,) arrays.

    Returns
    -------
    lo, hi : float
        Min / max position over the whole brake.
    q_t, v_t, a_t : float
        State after time t (at rest once the brake is over).
    """
    s = 1.0 if v + a * abs(a) / (2.0 * j_max) >= 0.0 else -1.0
    vf, af = s * v, s * a  # mirrored: the brake decelerates, vf + af|af|/(2j) >= 0
    ap = -math.sqrt(max(j_max * vf + 0.5 * af * af, 0.0))
    t2 = 0.0
    if ap < -a_max:
        ap = -a_max
        t2 = max((vf + (af * af - 2.0 * a_max * a_max) / (2.0 * j_max)) / a_max, 0.0)
    t1 = max((af - ap) / j_max, 0.0)
    t3 = -ap / j_max
    p1 = vf * t1 + af * t1 * t1 / 2.0 - j_max * t1 ** 3 / 6.0
    v1 = vf + af * t1 - j_max * t1 * t1 / 2.0
    p2 = p1 + v1 * t2 + ap * t2 * t2 / 2.0
    v2 = v1 + ap * t2
    p3 = p2 + v2 * t3 + ap * t3 * t3 / 2.0 + j_max * t3 ** 3 / 6.0
    lo_f, hi_f = min(0.0, p3), max(0.0, p3)
    if vf < 0.0:  # the velocity turns around during the first segment: a position extremum
        ts = (af - math.sqrt(max(af * af + 2.0 * j_max * vf, 0.0))) / j_max
        ps = vf * ts + af * ts * ts / 2.0 - j_max * ts ** 3 / 6.0
        lo_f, hi_f = min(lo_f, ps), max(hi_f, ps)
    if t <= t1:
        pt = vf * t + af * t * t / 2.0 - j_max * t ** 3 / 6.0
        vt = vf + af * t - j_max * t * t / 2.0
        at = af - j_max * t
    elif t <= t1 + t2:
        u = t - t1
        pt, vt, at = p1 + v1 * u + ap * u * u / 2.0, v1 + ap * u, ap
    elif t < t1 + t2 + t3:
        u = t - t1 - t2
        pt = p2 + v2 * u + ap * u * u / 2.0 + j_max * u ** 3 / 6.0
        vt = v2 + ap * u + j_max * u * u / 2.0
        at = ap + j_max * u
    else:
        pt, vt, at = p3, 0.0, 0.0
    if s > 0:
        return q + lo_f, q + hi_f, q + pt, vt, at
    return q - hi_f, q - lo_f, q - pt, -vt, -at


class StreamStatus(enum.IntEnum):
    """What produced a streamed sample."""

    ERROR = -1           #: ruckig rejected the tick's input; all joints braked this tick
    TRACKING = 0         #: following the reference with the look-ahead horizon (or moving to a step target)
    REACHED = 1          #: at the target state of :meth:`RuckigStreamer.step`
    POSITION_GUARD = 2   #: some joints braked to stay inside their position limits
    STOPPING = 3         #: braking after a stop request
    STOPPED = 4          #: at rest after a stop request
    APPROACHING = 5      #: far from the reference: intercepting it at a committed time


# enum members as module constants: looking one up on the class costs ~0.15 µs, several per tick
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


ReferenceFn = Callable[[float], "ReferenceState | tuple[np.ndarray, np.ndarray, np.ndarray]"]


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
        margin = _vector("position_margin", position_margin, d)
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
        q = _vector("start position q", q, d).copy()
        qd = np.zeros(d) if qd is None else _vector("start velocity qd", qd, d).copy()
        qdd = np.zeros(d) if qdd is None else _vector("start acceleration qdd", qdd, d).copy()
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
            b_lo, b_hi, _, _, _ = _brake_joint(q[i], qd[i], qdd[i], amax, jmax, 0.0)
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
            :class:`PhaseClock` that is ticked after this call:
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
            b_lo, b_hi, _, _, _ = _brake_joint(pi, v[i], a[i], amax, jmax, 0.0)
            if b_lo < lo - tol or b_hi > hi + tol:
                # brake from the current state instead (within limits by the invariant)
                _, _, p[i], v[i], a[i] = _brake_joint(self._q[i], self._qd[i], self._qdd[i],
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
            out = [_brake_joint(self._q[i], self._qd[i], self._qdd[i], amax, jmax, self.dt)[2:]
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


# --------------------------------------------------------------------------------------------
# Limit checks (tests, benchmarks)
# --------------------------------------------------------------------------------------------
class LimitReport(NamedTuple):
    """Worst use of each limit over a sampled joint trajectory (ratio 1 = at the limit).

    Attributes
    ----------
    position_excess : float
        max over samples and joints of max(lower - q, q - upper, 0) [rad].
    velocity_ratio, acceleration_ratio : float
        max |qd| / v_max and max |qdd| / a_max over the samples.
    jerk_ratio : float
        max |qdd[k+1] - qdd[k]| / dt / j_max (finite-difference jerk of the samples).
    fd_velocity_ratio, fd_acceleration_ratio : float
        max |Δq| / dt / v_max and max |Δqd| / dt / a_max (mean velocity / acceleration over
        each period: must not exceed the limits either).
    worst : tuple (str, int, int)
        (quantity, sample index, joint index) of the largest ratio; for finite-difference
        quantities the sample index k refers to the step from sample k to k + 1.
    """

    position_excess: float
    velocity_ratio: float
    acceleration_ratio: float
    jerk_ratio: float
    fd_velocity_ratio: float
    fd_acceleration_ratio: float
    worst: tuple[str, int, int]

    def ok(self, rtol: float = 1e-6, position_tol: float = 1e-9) -> bool:
        """All ratios <= 1 + rtol and positions within the limits up to position_tol."""
        ratios = (self.velocity_ratio, self.acceleration_ratio, self.jerk_ratio,
                  self.fd_velocity_ratio, self.fd_acceleration_ratio)
        return self.position_excess <= position_tol and max(ratios) <= 1 + rtol


def check_limits(q, qd, qdd, dt: float, limits: JointLimits) -> LimitReport:
    """Check a sampled joint trajectory against limits.

    Parameters
    ----------
    q, qd, qdd : array, shape (T, d)
        Sampled positions, velocities, accelerations at period dt (include the start state as
        the first row to check the first step too).
    dt : float
    limits : JointLimits

    Returns
    -------
    LimitReport
    """
    q = np.asarray(q, dtype=float)
    qd = np.asarray(qd, dtype=float)
    qdd = np.asarray(qdd, dtype=float)
    d = limits.n_joints
    for name, arr in (("q", q), ("qd", qd), ("qdd", qdd)):
        if arr.ndim != 2 or arr.shape[1] != d or arr.shape[0] == 0:
            raise ValueError(f"{name} must have shape (T >= 1, {d}); got {arr.shape}")
    if not (q.shape == qd.shape == qdd.shape):
        raise ValueError(f"q, qd, qdd shapes differ: {q.shape}, {qd.shape}, {qdd.shape}")
    excess = np.maximum(np.maximum(limits.lower - q, q - limits.upper), 0.0)
    quantities = {
        "velocity": np.abs(qd) / limits.max_velocity,
        "acceleration": np.abs(qdd) / limits.max_acceleration,
        "jerk": np.abs(np.diff(qdd, axis=0)) / dt / limits.max_jerk,
        "fd_velocity": np.abs(np.diff(q, axis=0)) / dt / limits.max_velocity,
        "fd_acceleration": np.abs(np.diff(qd, axis=0)) / dt / limits.max_acceleration,
    }
    maxima = {}
    worst = ("none", 0, 0)
    worst_val = -1.0
    for name, r in quantities.items():
        if r.size == 0:
            maxima[name] = 0.0
            continue
        idx = np.unravel_index(int(np.argmax(r)), r.shape)
        maxima[name] = float(r[idx])
        if r[idx] > worst_val:
            worst_val = float(r[idx])
            worst = (name, int(idx[0]), int(idx[1]))
    return LimitReport(float(excess.max()), maxima["velocity"], maxima["acceleration"],
                       maxima["jerk"], maxima["fd_velocity"], maxima["fd_acceleration"], worst)
