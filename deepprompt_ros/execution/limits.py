"""Per-joint kinematic limits of a robot and the check of a sampled joint trajectory against
them.

:class:`JointLimits` holds position, velocity, acceleration and jerk limits (arrays of shape
(d,)); :class:`~deepprompt_ros.execution.ruckig_streamer.RuckigStreamer` keeps every sample it
produces within them. :func:`check_limits` measures a sampled trajectory against the limits
(tests and benchmarks): every sample's |qd| <= v_max and |qdd| <= a_max, successive samples'
|Δq|/dt <= v_max, |Δqd|/dt <= a_max and |Δqdd|/dt <= j_max (finite-difference jerk of the
reported accelerations), and lower <= q <= upper.
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

__all__ = ["JointLimits", "LimitReport", "check_limits", "joint_vector"]


def joint_vector(name: str, value, n: int | None = None) -> np.ndarray:
    """``value`` as a float array of shape (n,) (a scalar is repeated n times); ValueError naming
    ``name`` when the shape is not (n,) (any length when ``n`` is None)."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0 and n is not None:
        arr = np.full(n, float(arr))
    if arr.ndim != 1:
        raise ValueError(f"{name} must be a 1-D array of length {n if n is not None else 'd'}; "
                         f"got shape {arr.shape}")
    if n is not None and arr.shape[0] != n:
        raise ValueError(f"{name} has {arr.shape[0]} values; expected {n} (one per joint)")
    return arr


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
        lower = joint_vector("lower", self.lower)
        d = lower.shape[0]
        if d == 0:
            raise ValueError("JointLimits needs at least one joint; got 0")
        upper = joint_vector("upper", self.upper, d)
        fields = {"lower": lower, "upper": upper}
        for name in ("max_velocity", "max_acceleration", "max_jerk"):
            arr = joint_vector(name, getattr(self, name), d)
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
