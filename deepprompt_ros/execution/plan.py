"""What one Execute goal runs: the executed mean trajectory on a dense phase grid
(:class:`ExecutionReference`) and its duration, direction and cycles (:class:`ExecutionPlan`).

The server builds a plan from a handle (it decodes the handle's distribution once per goal,
:meth:`~deepprompt_ros.server.service.PrimitiveServerCore.plan_execution`); from then on the
plan belongs to execution: the control loop asks it for a phase clock and, at every tick, for
the reference (q, q̇, q̈) at the clock's phase. It lives here, below the server, because it
needs only the phase clock and numpy, and the control loop
(:mod:`deepprompt_ros.execution.controller`) takes it without depending on the server's
models or handles.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from deepprompt_ros.execution.phase_clock import PhaseClock

__all__ = ["ExecutionReference", "ExecutionPlan"]


class ExecutionReference:
    """The executed mean trajectory on a dense phase grid, robot joint order, evaluated per tick.

    Positions are linearly interpolated on the grid (the decoder runs once per Execute, never
    per tick); the phase derivatives y'(x), y''(x) are central differences with step ``h`` on
    the grid (they also smooth the kinks of a ReLU decoder), interpolated the same way. Per
    tick, by the chain rule with x = τ(t):  q̇ = y'(x) ẋ,  q̈ = y''(x) ẋ² + y'(x) ẍ.

    Parameters
    ----------
    y : array, shape (N, d)
        Positions at N evenly spaced phases on [0, 1] (rhythmic: y[N-1] is the point of x = 1,
        equal to x = 0).
    periodic : bool
    h : float
        Phase step of the differences.
    """

    def __init__(self, y: np.ndarray, periodic: bool, h: float = 0.005):
        y = np.asarray(y, dtype=np.float64)
        if y.ndim != 2 or y.shape[0] < 3:
            raise ValueError(f"grid must have shape (N >= 3, d); got {y.shape}")
        n = y.shape[0]
        self.n = n
        self.periodic = bool(periodic)
        self.y = y
        k = max(1, int(round(h * (n - 1))))
        idx = np.arange(n)
        if periodic:
            m = n - 1  # last row repeats the first
            lo, hi = (idx - k) % m, (idx + k) % m
            dy = (y[hi] - y[lo]) / (2 * k / m)
            ddy = (y[hi] - 2 * y[idx % m] + y[lo]) / (k / m) ** 2
        else:
            lo, hi = np.clip(idx - k, 0, n - 1), np.clip(idx + k, 0, n - 1)
            span = (hi - lo) / (n - 1)
            dy = (y[hi] - y[lo]) / span[:, None]
            # second difference with the stencil shifted inside [0, 1] at the ends
            c = np.clip(idx, k, n - 1 - k)
            ddy = (y[c + k] - 2 * y[c] + y[c - k]) / (k / (n - 1)) ** 2
        self.dy, self.ddy = dy, ddy
        table = np.stack([y, dy, ddy], axis=1)  # (N, 3, d): one row read per tick
        self._table = table
        self._slope = np.concatenate([np.diff(table, axis=0), np.zeros((1,) + table.shape[1:])])

    @property
    def n_joints(self) -> int:
        return self.y.shape[1]

    def _interp(self, x: float):
        u = x * (self.n - 1)
        if self.periodic:
            u %= (self.n - 1)
        i = int(u)
        if i >= self.n - 1:
            i = self.n - 2
        elif i < 0:
            i = 0
        return self._table[i] + (u - i) * self._slope[i]  # rows y, y', y'' at x, shape (3, d)

    def positions(self, x) -> np.ndarray:
        """y at phases x, array (T,) -> (T, d) (vectorised; for previews and tests)."""
        x = np.asarray(x, dtype=np.float64)
        u = x * (self.n - 1)
        if self.periodic:
            u = np.mod(u, self.n - 1)
        i = np.clip(u.astype(int), 0, self.n - 2)
        f = (u - i)[:, None]
        return self.y[i] + f * (self.y[i + 1] - self.y[i])

    def state(self, x: float, x_dot: float, x_ddot: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Reference (q, q̇, q̈), each shape (d,), at phase x moving with ẋ, ẍ."""
        y, dy, ddy = self._interp(x)
        return y, dy * x_dot, ddy * (x_dot * x_dot) + dy * x_ddot

    def max_speed_per_phase(self) -> np.ndarray:
        """max_x |y'(x)| per joint, shape (d,) [rad per unit phase]."""
        return np.abs(self.dy).max(axis=0)

    def velocity_limit_ratios(self, max_velocity) -> np.ndarray:
        """max_j |y_j'(x)| / v_max,j at each grid phase, shape (N,) [s]: at a duration T a joint moves at
        |y_j'(x)| / T, so this is the duration below which the executed trajectory would need more than
        a velocity limit at that phase. ``max_velocity`` (d,), rad/s, in the grid's joint order."""
        return np.max(np.abs(self.dy) / np.asarray(max_velocity, dtype=np.float64), axis=1)

    def shortest_duration(self, max_velocity) -> float:
        """The shortest duration (s) at which no joint needs more than its velocity limit
        ``max_velocity`` (d,), rad/s: the maximum of :meth:`velocity_limit_ratios`."""
        return float(np.max(self.max_speed_per_phase() / np.asarray(max_velocity, dtype=np.float64)))


@dataclasses.dataclass(frozen=True)
class ExecutionPlan:
    """What the control loop needs to run one Execute goal.

    Attributes
    ----------
    handle, primitive : str
    reference : ExecutionReference (robot joint order)
    duration : float
        Seconds for phase 0 -> 1 at the initial rate (rhythmic: per cycle).
    rhythmic : bool
    cycles : int (1 for linear)
    reverse : bool
    """

    handle: str
    primitive: str
    reference: ExecutionReference
    duration: float
    rhythmic: bool
    cycles: int
    reverse: bool

    @property
    def phase_rate(self) -> float:
        return 1.0 / self.duration

    @property
    def start_phase(self) -> float:
        return 0.0 if self.rhythmic else (1.0 if self.reverse else 0.0)

    @property
    def end_phase(self) -> float:
        return 0.0 if self.rhythmic else (0.0 if self.reverse else 1.0)

    def make_clock(self, dt: float) -> PhaseClock:
        if self.rhythmic:
            return PhaseClock.rhythmic_clock(dt, self.duration, cycles=self.cycles, reverse=self.reverse)
        return PhaseClock.linear(dt, self.duration, reverse=self.reverse)
