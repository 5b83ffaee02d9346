"""Joint trajectories through via-configurations, made of minimum-jerk segments, and their timing."""
from __future__ import annotations

import numpy as np

from deepprompt_ros.sim.tasks.min_jerk import quintic_hermite

__all__ = ["LIMIT_FRACTION", "ViaTrajectory", "segment_durations"]

#: Planned peak velocity / acceleration as a fraction of the robot's limits.
LIMIT_FRACTION = 0.85


class ViaTrajectory:
    """Joint trajectory through via-configurations made of minimum-jerk (quintic) segments.

    Segment k joins (q_k, v_k, 0) at t_k to (q_{k+1}, v_{k+1}, 0) at t_{k+1}: the minimum-jerk
    curve between these boundary states is the quintic Hermite interpolant
    q(u) = H₀(u) q_k + h H₁(u) v_k + h H₂(u) v_{k+1} + H₃(u) q_{k+1}, u = (t − t_k)/h (Flash & Hogan
    1985; the basis: :func:`~deepprompt_ros.sim.tasks.min_jerk.quintic_hermite`). Velocities: 0 at
    both ends and wherever a joint's motion reverses or stops (a repeated via-configuration is a
    hold); elsewhere the Fritsch–Butland weighted harmonic mean of the neighbouring slopes, times
    ``flow`` in [0, 1] (0 = stop at every via).

    Parameters
    ----------
    knots : array, shape (K, n)
        Via-configurations, K >= 2.
    durations : array, shape (K-1,)
        Segment durations (s), > 0.
    flow : float
    """

    def __init__(self, knots, durations, flow: float = 1.0):
        self.knots = np.asarray(knots, dtype=np.float64)
        self.durations = np.asarray(durations, dtype=np.float64)
        if self.knots.ndim != 2 or self.knots.shape[0] < 2:
            raise ValueError(f"knots must have shape (K, n) with K >= 2; got {self.knots.shape}")
        if self.durations.shape != (self.knots.shape[0] - 1,) or np.any(~(self.durations > 0)):
            raise ValueError(f"durations must be K-1 = {self.knots.shape[0] - 1} positive numbers; "
                             f"got {self.durations}")
        self.flow = float(flow)
        self.times = np.concatenate([[0.0], np.cumsum(self.durations)])
        self.velocities = self._knot_velocities()

    @property
    def duration(self) -> float:
        return float(self.times[-1])

    def _knot_velocities(self) -> np.ndarray:
        q, h = self.knots, self.durations
        d = np.diff(q, axis=0) / h[:, None]  # secant slopes, (K-1, n)
        v = np.zeros_like(q)
        for k in range(1, q.shape[0] - 1):
            d0, d1 = d[k - 1], d[k]
            w1, w2 = 2 * h[k] + h[k - 1], h[k] + 2 * h[k - 1]
            same = (d0 * d1) > 0
            with np.errstate(divide="ignore", invalid="ignore"):
                hm = (w1 + w2) / (w1 / d0 + w2 / d1)
            v[k] = np.where(same, hm, 0.0) * self.flow
        return v

    def scaled(self, factor: float) -> "ViaTrajectory":
        """The same path, ``factor`` times slower (velocities / factor, accelerations / factor²)."""
        return ViaTrajectory(self.knots, self.durations * factor, self.flow)

    def evaluate(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions, velocities and accelerations at times t, each shape (len(t), n).

        Times outside [0, duration] are clamped (the arm rests at the first / last knot).
        """
        t = np.clip(np.asarray(t, dtype=np.float64), 0.0, self.duration)
        k = np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.durations) - 1)
        h = self.durations[k][:, None]
        u = ((t - self.times[k]) / self.durations[k])[:, None]
        q0, q1 = self.knots[k], self.knots[k + 1]
        v0, v1 = self.velocities[k], self.velocities[k + 1]
        (H0, H1, H2, H3), (dH0, dH1, dH2), (ddH0, ddH1, ddH2) = quintic_hermite(u)
        q = H0 * q0 + h * H1 * v0 + h * H2 * v1 + H3 * q1
        qd = (dH0 * (q0 - q1)) / h + dH1 * v0 + dH2 * v1
        qdd = (ddH0 * (q0 - q1)) / h**2 + (ddH1 * v0 + ddH2 * v1) / h
        return q, qd, qdd

    def within_limits(self, spec, fraction: float = LIMIT_FRACTION, rounds: int = 20) -> "ViaTrajectory":
        """The same path with every segment slowed down (only as much as needed) until
        |q̇| <= fraction·v_max and |q̈| <= fraction·a_max everywhere.

        A segment whose peak ratio r = max(|q̇|/v_lim, sqrt(|q̈|/a_lim)) exceeds 1 is stretched by
        r (velocities scale with 1/r, accelerations with 1/r²); knot velocities depend on the
        neighbouring durations, hence a few rounds.
        """
        traj = self
        m = 30
        u = (np.arange(m) + 0.5) / m
        for _ in range(rounds):
            t = (traj.times[:-1, None] + u[None, :] * traj.durations[:, None]).ravel()
            _, qd, qdd = traj.evaluate(t)
            rv = np.max(np.abs(qd) / (fraction * spec.velocity), axis=1).reshape(-1, m).max(axis=1)
            ra = np.max(np.abs(qdd) / (fraction * spec.acceleration), axis=1).reshape(-1, m).max(axis=1)
            r = np.maximum(rv, np.sqrt(ra))
            if np.all(r <= 1.0):
                return traj
            traj = ViaTrajectory(traj.knots, traj.durations * np.where(r > 1.0, r * 1.02, 1.0), traj.flow)
        return traj.scaled(float(max(1.0, r.max())) * 1.02)


def segment_durations(knots: np.ndarray, spec, rng, minimum: float = 0.3,
                      spread: tuple[float, float] = (0.85, 1.3)) -> np.ndarray:
    """Per-segment durations: the slowest joint at an average 45 % of its velocity limit, randomized."""
    dist = np.max(np.abs(np.diff(knots, axis=0)) / (0.45 * spec.velocity), axis=1)
    return np.maximum(dist, minimum) * rng.uniform(*spread, size=len(dist))
