"""Temporal modulation (paper Sec. III-C, "Time Modulation"): a time map τ(t): [0, T] → phase x.

Linear τ = t/T gives proportionally faster or slower motion; any monotone τ accelerates or
decelerates during the motion; a decreasing τ replays the motion backwards. Rhythmic primitives
use x = t/T modulo 1 (their network input [sin 2πx, cos 2πx] makes the wrap seamless).
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np


class TimeMap:
    """τ(t) → x and its derivative dτ/dt. Subclasses implement ``phase`` and ``rate``."""

    duration: float

    def phase(self, t) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    def rate(self, t) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    def __call__(self, t) -> np.ndarray:
        return self.phase(t)

    def _check_t(self, t) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        if not np.all(np.isfinite(t)):
            raise ValueError("time stamps must be finite")
        return np.clip(t, 0.0, self.duration)


def _check_duration(T: float) -> float:
    if not (np.isfinite(T) and T > 0):
        raise ValueError(f"duration T must be a finite number of seconds > 0, got {T}")
    return float(T)


@dataclasses.dataclass(frozen=True)
class LinearTimeMap(TimeMap):
    """τ(t) = t / T, or 1 − t / T when ``reverse`` (the motion played backwards)."""

    duration: float
    reverse: bool = False

    def __post_init__(self):
        _check_duration(self.duration)

    def phase(self, t):
        x = self._check_t(t) / self.duration
        return 1.0 - x if self.reverse else x

    def rate(self, t):
        r = np.full(np.shape(t), 1.0 / self.duration)
        return -r if self.reverse else r


@dataclasses.dataclass(frozen=True)
class MonotoneTimeMap(TimeMap):
    """Monotone τ through knots (t_i, x_i), shape-preserving cubic (Fritsch–Carlson, 1980).

    Knot times strictly increasing from 0 to T; knot phases either non-decreasing from 0 to 1
    (speed profile) or non-increasing from 1 to 0 (reversed). The interpolant is C¹ and never
    overshoots, so x stays monotone and inside [0, 1].
    """

    knot_t: tuple[float, ...]
    knot_x: tuple[float, ...]

    def __post_init__(self):
        t = np.asarray(self.knot_t, dtype=np.float64)
        x = np.asarray(self.knot_x, dtype=np.float64)
        if t.ndim != 1 or t.shape != x.shape or t.size < 2:
            raise ValueError("monotone time map needs >= 2 knots with matching knot_t and knot_x")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(x))):
            raise ValueError("time map knots must be finite")
        if t[0] != 0 or np.any(np.diff(t) <= 0):
            raise ValueError("knot times must start at 0 and be strictly increasing")
        d = np.diff(x)
        if not ((np.all(d >= 0) and x[0] == 0 and x[-1] == 1) or (np.all(d <= 0) and x[0] == 1 and x[-1] == 0)):
            raise ValueError("knot phases must run monotonically from 0 to 1 (or from 1 to 0 to reverse)")
        _check_duration(t[-1])

    @property
    def duration(self) -> float:  # type: ignore[override]
        return float(self.knot_t[-1])

    def _slopes(self):
        t = np.asarray(self.knot_t)
        x = np.asarray(self.knot_x)
        h = np.diff(t)
        delta = np.diff(x) / h
        m = np.empty_like(x)
        m[0], m[-1] = delta[0], delta[-1]
        m[1:-1] = (delta[:-1] + delta[1:]) / 2
        m[1:-1][delta[:-1] * delta[1:] <= 0] = 0.0
        for k in range(delta.size):  # Fritsch–Carlson limiter keeps each cubic monotone
            if delta[k] == 0:
                m[k] = m[k + 1] = 0.0
                continue
            a, b = m[k] / delta[k], m[k + 1] / delta[k]
            s = a * a + b * b
            if s > 9:
                tau = 3 / np.sqrt(s)
                m[k], m[k + 1] = tau * a * delta[k], tau * b * delta[k]
        return t, x, h, m

    def _eval(self, tt):
        t, x, h, m = self._slopes()
        tt = self._check_t(tt)
        k = np.clip(np.searchsorted(t, tt, side="right") - 1, 0, h.size - 1)
        s = (tt - t[k]) / h[k]
        h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
        val = h00 * x[k] + h10 * h[k] * m[k] + h01 * x[k + 1] + h11 * h[k] * m[k + 1]
        d00, d10, d01, d11 = 6 * s**2 - 6 * s, 3 * s**2 - 4 * s + 1, -6 * s**2 + 6 * s, 3 * s**2 - 2 * s
        der = (d00 * x[k] + d01 * x[k + 1]) / h[k] + d10 * m[k] + d11 * m[k + 1]
        return np.clip(val, 0.0, 1.0), der

    def phase(self, t):
        return self._eval(t)[0]

    def rate(self, t):
        return self._eval(t)[1]


@dataclasses.dataclass(frozen=True)
class RhythmicTimeMap(TimeMap):
    """x = (t / T) mod 1 over ``cycles`` periods of length T (the phase of a rhythmic primitive)."""

    period: float
    cycles: int = 1
    reverse: bool = False

    def __post_init__(self):
        _check_duration(self.period)
        if self.cycles < 1:
            raise ValueError(f"cycles must be >= 1, got {self.cycles}")

    @property
    def duration(self) -> float:  # type: ignore[override]
        return self.period * self.cycles

    def phase(self, t):
        x = np.mod(self._check_t(t) / self.period, 1.0)
        return np.mod(-x, 1.0) if self.reverse else x

    def rate(self, t):
        r = np.full(np.shape(t), 1.0 / self.period)
        return -r if self.reverse else r


def evaluate(trajectory: Callable[[np.ndarray], np.ndarray], time_map: TimeMap, t, dx: float = 1e-4):
    """Positions and velocities of a phase trajectory under a time map.

    q(t) = y(τ(t)),  q̇(t) = dy/dx(τ(t)) · τ̇(t)  (chain rule; dy/dx by central differences).

    Parameters
    ----------
    trajectory : callable x (T,) -> y (T, d)
    t : array, shape (T,) seconds

    Returns
    -------
    q, qd : array, shape (T, d)
    """
    x = time_map.phase(t)
    q = trajectory(x)
    lo, hi = np.clip(x - dx, 0, 1), np.clip(x + dx, 0, 1)
    if isinstance(time_map, RhythmicTimeMap):
        lo, hi = np.mod(x - dx, 1.0), np.mod(x + dx, 1.0)
        width = np.full_like(x, 2 * dx)
    else:
        width = hi - lo
    dydx = (trajectory(hi) - trajectory(lo)) / width[:, None]
    return q, dydx * np.asarray(time_map.rate(t))[:, None]
