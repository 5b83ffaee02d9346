"""Phase clock: maps control ticks to the phase x of a primitive (temporal modulation
x = τ(t), paper Sec. III-C).

:class:`PhaseClock` supports the linear map τ(t) = t/T (or a phase rate 1/T), any τ given as a
callable or as knots, reversal (x runs 1 → 0), rhythmic cycles (x wraps over [0, 1); the
rhythmic decoder sees [sin 2πx, cos 2πx], so the wrap is seamless) and a live change of the
speed that keeps x continuous. Each tick gives a :class:`PhaseSample` (x, dx/dt, d²x/dt²), from
which :mod:`deepprompt_ros.execution.reference` builds the reference joint state.
"""
from __future__ import annotations

import math
from typing import Callable, NamedTuple, Sequence

import numpy as np

__all__ = ["PhaseSample", "PhaseClock"]

#: ``tuple.__new__(NamedTupleClass, values)`` builds a NamedTuple without its Python-level
#: ``__new__`` (the clock makes two or three samples per control tick).
_tuple_new = tuple.__new__


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
