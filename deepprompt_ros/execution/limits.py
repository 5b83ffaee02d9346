"""Per-joint kinematic limits of a robot and the check of a sampled joint trajectory against
them.

:class:`JointLimits` holds position, velocity, acceleration and jerk limits (arrays of shape
(d,)); :class:`~deepprompt_ros.execution.ruckig_streamer.RuckigStreamer` keeps every sample it
produces within them. :func:`check_limits` measures a sampled trajectory against the limits
(tests and benchmarks): every sample's |qd| <= v_max and |qdd| <= a_max, successive samples'
|Δq|/h <= v_max, |Δqd|/h <= a_max and |Δqdd|/h <= j_max (finite-difference jerk of the
reported accelerations), and lower <= q <= upper, where h is the time between the two samples
(dt, or k dt across a gap of k periods when sample times are given: a position jump is found
between neighbours and across skipped or lost samples alike).
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

__all__ = ["JointLimits", "LimitReport", "check_limits", "joint_vector"]

#: An interval between two samples counts as one period when it is within this fraction of dt.
_PERIOD_RTOL = 1e-3


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
        max |qd| / v_max and max |qdd| / a_max over the samples (without reported accelerations:
        the mean acceleration of each interval, as ``fd_acceleration_ratio``).
    jerk_ratio : float
        max |Δqdd| / h / j_max (finite-difference jerk of the samples' accelerations; without
        reported accelerations: the change of the mean acceleration between consecutive
        one-period intervals over the distance of their midpoints).
    fd_velocity_ratio, fd_acceleration_ratio : float
        max |Δq| / h / v_max and max |Δqd| / h / a_max over the intervals h between consecutive
        samples (mean velocity / acceleration over each interval: must not exceed the limits
        either). ``fd_velocity_ratio`` is the largest position jump between consecutive samples
        as a fraction of what the velocity limit allows in their interval.
    worst : tuple (str, int, int)
        (quantity, sample index, joint index) of the largest ratio; for finite-difference
        quantities the sample index k refers to the step from sample k to k + 1 (for the jerk
        without reported accelerations, to the one-period interval that starts at sample k and
        the next one).
    violations : int
        Samples at which some limit is exceeded (beyond the tolerances given to
        :func:`check_limits`): the sample's own position, velocity or acceleration, or a finite
        difference that ends at it.
    """

    position_excess: float
    velocity_ratio: float
    acceleration_ratio: float
    jerk_ratio: float
    fd_velocity_ratio: float
    fd_acceleration_ratio: float
    worst: tuple[str, int, int]
    violations: int = 0

    def ok(self, rtol: float = 1e-6, position_tol: float = 1e-9) -> bool:
        """All ratios <= 1 + rtol and positions within the limits up to position_tol."""
        ratios = (self.velocity_ratio, self.acceleration_ratio, self.jerk_ratio,
                  self.fd_velocity_ratio, self.fd_acceleration_ratio)
        return self.position_excess <= position_tol and max(ratios) <= 1 + rtol


def check_limits(q, qd, qdd, dt: float, limits: JointLimits, t=None, *, rtol: float = 1e-6,
                 position_tol: float = 1e-9) -> LimitReport:
    """Check a sampled joint trajectory against limits.

    Every interval between consecutive samples is checked, however long: with sample times ``t``
    a gap of k periods (lost or skipped samples) allows at most k dt v_max of motion and
    k dt a_max of velocity change, so a position jump across a gap is found as well as one
    between neighbours.

    Parameters
    ----------
    q, qd : array, shape (T, d)
        Sampled positions and velocities (include the start state as the first row to check
        the first step too).
    qdd : array, shape (T, d), or None
        Accelerations at the samples. None when the samples carry none (a sensor_msgs/JointState
        command stream): the mean acceleration of each interval, Δqd / h, is checked against
        a_max, and the jerk is its change between consecutive intervals of one period (h = dt)
        over the distance of their midpoints; across a gap, between the periods on either side
        of it (a bound that holds whether the gap lost samples or the stream skipped ticks,
        where one period of motion is stretched over a longer interval and that interval's
        mean acceleration drops without any jerk in the commands).
    dt : float
        Sample period [s]; the sample times are k dt when ``t`` is None.
    limits : JointLimits
    t : array, shape (T,), optional
        Sample times [s], strictly increasing (e.g. the commands' header stamps). The intervals
        h_k = t_(k+1) - t_k replace dt in every finite difference.
    rtol, position_tol : float
        Tolerances of :attr:`LimitReport.violations` (as in :meth:`LimitReport.ok`).

    Returns
    -------
    LimitReport
    """
    q = np.asarray(q, dtype=float)
    qd = np.asarray(qd, dtype=float)
    d = limits.n_joints
    arrays = (("q", q), ("qd", qd)) + ((("qdd", np.asarray(qdd, dtype=float)),) if qdd is not None else ())
    for name, arr in arrays:
        if arr.ndim != 2 or arr.shape[1] != d or arr.shape[0] == 0:
            raise ValueError(f"{name} must have shape (T >= 1, {d}); got {arr.shape}")
    if any(arr.shape != q.shape for _, arr in arrays):
        raise ValueError(f"q, qd, qdd shapes differ: {', '.join(str(a.shape) for _, a in arrays)}")
    n = q.shape[0]
    if t is None:
        h = np.full((n - 1, 1), float(dt))
    else:
        t = np.asarray(t, dtype=float)
        if t.shape != (n,):
            raise ValueError(f"t must have shape ({n},), one time per sample; got {t.shape}")
        h = np.diff(t)[:, None]
        if np.any(~(h > 0)):
            k = int(np.argmax(~(h > 0)))
            raise ValueError(f"sample times must increase strictly; t[{k + 1}] = {t[k + 1]!r} after "
                             f"t[{k}] = {t[k]!r}")
    excess = np.maximum(np.maximum(limits.lower - q, q - limits.upper), 0.0)
    fd_acc = np.diff(qd, axis=0) / h                        # mean acceleration of each interval
    steps = np.arange(1, n)                                 # the sample each interval ends at
    if qdd is None:
        # the mean accelerations of consecutive one-period intervals, over the distance of their
        # midpoints (across a gap: of the periods on either side of it)
        period = np.flatnonzero(np.abs(h[:, 0] - dt) <= _PERIOD_RTOL * dt)
        mid = (np.arange(n - 1) + 0.5) * dt if t is None else 0.5 * (t[:-1] + t[1:])
        acceleration = np.abs(fd_acc) / limits.max_acceleration
        jerk = np.abs(np.diff(fd_acc[period], axis=0)) / np.diff(mid[period])[:, None] / limits.max_jerk
        jerk_at, jerk_ends = period[:-1], period[1:] + 1
        acc_at = steps
    else:
        qdd = np.asarray(qdd, dtype=float)
        acceleration = np.abs(qdd) / limits.max_acceleration
        jerk = np.abs(np.diff(qdd, axis=0)) / h / limits.max_jerk
        jerk_at, jerk_ends = steps - 1, steps
        acc_at = np.arange(n)
    # name -> (ratios (rows, d), the sample index each row is reported at, the sample it ends at)
    quantities = {
        "velocity": (np.abs(qd) / limits.max_velocity, np.arange(n), np.arange(n)),
        "acceleration": (acceleration, acc_at - (qdd is None), acc_at),
        "jerk": (jerk, jerk_at, jerk_ends),
        "fd_velocity": (np.abs(np.diff(q, axis=0)) / h / limits.max_velocity, steps - 1, steps),
        "fd_acceleration": (np.abs(fd_acc) / limits.max_acceleration, steps - 1, steps),
    }
    maxima = {}
    worst = ("none", 0, 0)
    worst_val = -1.0
    bad = (excess > position_tol).any(axis=1)
    for name, (r, at, ends) in quantities.items():
        if r.size == 0:
            maxima[name] = 0.0
            continue
        row, joint = np.unravel_index(int(np.argmax(r)), r.shape)
        maxima[name] = float(r[row, joint])
        if r[row, joint] > worst_val:
            worst_val = float(r[row, joint])
            worst = (name, int(at[row]), int(joint))
        bad[ends] |= (r > 1 + rtol).any(axis=1)
    return LimitReport(float(excess.max()), maxima["velocity"], maxima["acceleration"],
                       maxima["jerk"], maxima["fd_velocity"], maxima["fd_acceleration"], worst,
                       int(bad.sum()))
