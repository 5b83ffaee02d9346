"""The end of every JointTrajectory message: the brake of every joint to rest from the last
sample of the look-ahead (:class:`BrakeTail`), appended to the look-ahead samples by
:func:`trajectory_points`. Every message is thereby a complete trajectory ending at rest.
"""
from __future__ import annotations

import numpy as np

from deepprompt_ros.execution.controller import Snapshot
from deepprompt_ros.execution.limits import JointLimits

__all__ = ["BrakeTail", "trajectory_points"]


class BrakeTail:
    """Time-optimal, jerk-limited brake of every joint to rest (Ruckig velocity interface, joints
    independent): the end of each JointTrajectory message, so that every message is a complete
    trajectory ending at rest (a controller that receives no further message stops smoothly, and
    a JointTrajectoryController accepts it without allow_nonzero_velocity_at_trajectory_end).
    From a state produced by RuckigStreamer this brake stays inside the position limits (the
    streamer's invariant)."""

    REST = 1e-9  #: |qd|, |qdd| at or below this count as at rest (no tail; zeroed in messages)

    def __init__(self, limits: JointLimits):
        from ruckig import ControlInterface, InputParameter, Ruckig, Synchronization, Trajectory

        d = limits.n_joints
        self._otg, self._traj, self._inp = Ruckig(d), Trajectory(d), InputParameter(d)
        self._inp.control_interface = ControlInterface.Velocity
        self._inp.synchronization = Synchronization.No
        self._inp.max_velocity = list(map(float, limits.max_velocity))
        self._inp.max_acceleration = list(map(float, limits.max_acceleration))
        self._inp.max_jerk = list(map(float, limits.max_jerk))
        self._inp.target_velocity = [0.0] * d
        self._inp.target_acceleration = [0.0] * d
        self._lower, self._upper = np.asarray(limits.lower), np.asarray(limits.upper)
        self._vmax, self._amax = np.asarray(limits.max_velocity), np.asarray(limits.max_acceleration)

    def __call__(self, q, qd, qdd, n_points: int = 3):
        """Brake from (q, qd, qdd) (d,) each.

        Returns
        -------
        times : array, shape (m,), seconds after the given state (m = 0 when already at rest)
        q, qd, qdd : array, shape (m, d); the last row has qd = qdd = 0 exactly.
        """
        qd = np.clip(np.asarray(qd, dtype=float), -self._vmax, self._vmax)
        qdd = np.clip(np.asarray(qdd, dtype=float), -self._amax, self._amax)
        d = qd.shape[0]
        if not (np.any(np.abs(qd) > self.REST) or np.any(np.abs(qdd) > self.REST)):
            return np.zeros(0), np.zeros((0, d)), np.zeros((0, d)), np.zeros((0, d))
        inp = self._inp
        inp.current_position = np.asarray(q, dtype=float).tolist()
        inp.current_velocity = qd.tolist()
        inp.current_acceleration = qdd.tolist()
        self._otg.calculate(inp, self._traj)
        dur = max(self._traj.duration, 1e-6)
        times = dur * np.arange(1, n_points + 1) / n_points
        rows = [self._traj.at_time(float(t))[:3] for t in times]
        pq = np.clip(np.array([r[0] for r in rows]), self._lower, self._upper)
        pv = np.array([r[1] for r in rows])
        pa = np.array([r[2] for r in rows])
        pv[-1] = 0.0
        pa[-1] = 0.0
        return times, pq, pv, pa


def trajectory_points(snap: Snapshot, tail: BrakeTail):
    """Points of one JointTrajectory message: the snapshot's future samples, then the brake to
    rest from the last of them. The last point has velocity and acceleration exactly 0.

    Returns
    -------
    times : array, shape (P,), seconds after ``snap.t0``, strictly increasing
    q, qd, qdd : array, shape (P, d)
    """
    tt, tq, tv, ta = tail(snap.q[-1], snap.qd[-1], snap.qdd[-1])
    times = np.concatenate([snap.times, snap.times[-1] + tt])
    q = np.concatenate([snap.q, tq])
    qd = np.concatenate([snap.qd, tv])
    qdd = np.concatenate([snap.qdd, ta])
    qd[-1] = 0.0
    qdd[-1] = 0.0
    return times, q, qd, qdd
