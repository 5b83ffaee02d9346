"""Inverse kinematics of the end-effector frame: damped least squares on the Pinocchio model.

The one IK solver of the package. The scripted demonstrators of :mod:`deepprompt_ros.sim.tasks` use
it with its defaults (position and tool axis or full orientation, null-space pull to a rest
posture, capped steps); the kinematic reach generator
(:mod:`deepprompt_ros.sim.tasks.kinematic_reach`) uses its position-only form (no null-space term,
no step cap, its own limit margin, damping and tolerances, the seed as given).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from deepprompt_ros.robots.geometry import log3, skew
from deepprompt_ros.robots.kinematics import RobotKinematics

__all__ = ["IKResult", "solve_ik"]


class IKResult(NamedTuple):
    """Result of :func:`solve_ik`.

    Attributes
    ----------
    q : array, shape (n,)
        Joint values, inside the limits shrunk by ``margin``.
    position_error : float
        |p_target − p(q)| (m).
    angle_error : float
        Angle (rad) between the desired and reached tool axis (or rotation); 0 without one.
    """

    q: np.ndarray
    position_error: float
    angle_error: float


def solve_ik(kin: RobotKinematics, position, q_seed, *, axis=None, rotation=None, rest=None,
             margin: float = 0.05, iterations: int = 300, damping: float = 0.03, angle_weight: float = 0.3,
             rest_gain: float = 0.05, max_step: float | None = 0.2, tol_position: float = 1e-4,
             tol_angle: float = 1e-3, clip_seed: bool = True, measure_after_last_step: bool = True) -> IKResult:
    """Damped-least-squares inverse kinematics of the end-effector frame (Wampler 1986; Buss 2004).

    Each iteration solves Δq = Aᵀ(AAᵀ + λ²I)⁻¹ e for the stacked task error e (position, and
    optionally the tool-axis or full-rotation error weighted by ``angle_weight``) and adds a
    null-space step (I − A⁺A) k (q_rest − q) towards ``rest``; steps are capped at ``max_step``
    (rad, largest joint) and q is clipped to the limits shrunk by ``margin``. The iteration stops
    when the position error is below ``tol_position`` and the angle error below ``tol_angle``, or
    after ``iterations`` steps.

    Parameters
    ----------
    kin : RobotKinematics
    position : array_like, shape (3,)
        Target position of the end-effector frame (m, base frame).
    q_seed : array_like, shape (n,)
        Start of the iteration (e.g. the previous via-configuration, for continuity).
    axis : array_like, shape (3,), optional
        Desired direction of the end-effector frame's z axis (tool axis); e = a* − a, with
        ȧ = ω × a, i.e. rows −[a]ₓ J_ω.
    rotation : array, shape (3, 3), optional
        Desired full orientation (instead of ``axis``); e = log(R* Rᵀ), rows J_ω.
    rest : array_like, shape (n,), optional
        Posture preferred in the null space (default: ``q_seed``).
    margin : float
        Distance (rad or m) kept from the position limits.
    iterations : int
        Most steps taken.
    damping : float
        λ of the damped least squares.
    angle_weight : float
        Weight of the orientation rows against the position rows (m/rad).
    rest_gain : float
        k of the null-space step; 0 takes none.
    max_step : float or None
        Cap on the largest joint change of one step (the step is scaled down); None: no cap.
    tol_position, tol_angle : float
        Convergence tolerances (m, rad).
    clip_seed : bool
        Clip ``q_seed`` into the shrunk limits before the first iteration (False: start from it as
        given; the first step's result is clipped).
    measure_after_last_step : bool
        Measure the errors again after the last step. False: after the ``iterations``-th step the
        iteration ends without measuring, and the returned errors are those measured before that
        step.

    Returns
    -------
    IKResult
    """
    spec = kin.spec
    target = np.asarray(position, dtype=np.float64)
    lo = np.where(np.isfinite(spec.lower), spec.lower + margin, -np.inf)
    hi = np.where(np.isfinite(spec.upper), spec.upper - margin, np.inf)
    q = np.asarray(q_seed, dtype=np.float64)
    q = np.clip(q, lo, hi) if clip_seed else q.copy()
    q_rest = q.copy() if rest is None else np.asarray(rest, dtype=np.float64)
    a_des = None if axis is None else np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    R_des = None if rotation is None else np.asarray(rotation, dtype=np.float64)
    eye_n = np.eye(spec.n_joints)
    e_p = ang = math.inf
    for it in range(iterations + 1):
        if it == iterations and not measure_after_last_step:
            break
        p, R, J = kin.pose_and_jacobian(q)
        e_p_vec = target - p
        rows, errs = [J[:3]], [e_p_vec]
        ang = 0.0
        if a_des is not None:
            a = R[:, 2]
            ang = math.acos(float(np.clip(a @ a_des, -1.0, 1.0)))
            rows.append(angle_weight * (-skew(a) @ J[3:]))
            errs.append(angle_weight * (a_des - a))
        elif R_des is not None:
            e_r = log3(R_des @ R.T)
            ang = float(np.linalg.norm(e_r))
            rows.append(angle_weight * J[3:])
            errs.append(angle_weight * e_r)
        e_p = float(np.linalg.norm(e_p_vec))
        if (e_p < tol_position and ang < tol_angle) or it == iterations:
            break
        A, e = np.vstack(rows), np.concatenate(errs)
        dq = A.T @ np.linalg.solve(A @ A.T + damping**2 * np.eye(A.shape[0]), e)
        if rest_gain:
            # exact null-space projector (I − A⁺A): the posture term does not disturb the task
            dq = dq + (eye_n - np.linalg.pinv(A, rcond=1e-6) @ A) @ (rest_gain * (q_rest - q))
        if max_step is not None:
            step = float(np.max(np.abs(dq)))
            if step > max_step:
                dq *= max_step / step
        q = np.clip(q + dq, lo, hi)
    return IKResult(q, e_p, ang)

