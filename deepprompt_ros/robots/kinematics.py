"""Kinematics and dynamics of a robot spec with Pinocchio: forward kinematics, Jacobians, gravity.

:class:`RobotKinematics` wraps the Pinocchio model of a
:class:`~deepprompt_ros.robots.spec.RobotSpec`'s URDF with its locked joints removed; every method
takes plain joint angles in ``spec.joint_names`` order (also for continuous joints, which Pinocchio
stores as (cos θ, sin θ)). Poses are :class:`FramePose` (position, rotation matrix) in the base frame.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import pinocchio as pin

from deepprompt_ros.robots.geometry import quat_xyzw
from deepprompt_ros.robots.spec import GRAVITY, RobotSpec, classify_joint, urdf_model

__all__ = ["FramePose", "RobotKinematics"]


class FramePose(NamedTuple):
    """Pose of a frame in the world (base) frame.

    Attributes
    ----------
    position : array, shape (3,)
    rotation : array, shape (3, 3)
        Columns are the frame's axes expressed in the world frame.
    """

    position: np.ndarray
    rotation: np.ndarray

    @property
    def quaternion_xyzw(self) -> np.ndarray:
        """Orientation as a unit quaternion (x, y, z, w), shape (4,)."""
        return quat_xyzw(self.rotation)


class RobotKinematics:
    """Pinocchio model of a :class:`RobotSpec` (locked joints removed).

    Every method takes joint values in ``spec.joint_names`` order (plain angles also for
    continuous joints) and validates their count.

    Parameters
    ----------
    spec : RobotSpec

    Attributes
    ----------
    spec : RobotSpec
    model : pinocchio.Model
        Reduced model: only the controlled joints.
    data : pinocchio.Data
    """

    def __init__(self, spec: RobotSpec):
        self.spec = spec
        full = urdf_model(str(spec.urdf_path))
        locked = dict(spec.locked_joints)
        if locked:
            qlock = pin.neutral(full)
            lock_ids = []
            for jname, value in locked.items():
                if not full.existJointName(jname):
                    raise ValueError(f"robot '{spec.name}': locked joint '{jname}' is not in {spec.urdf_path}")
                info = classify_joint(full, full.getJointId(jname), spec.name)
                if info.continuous:
                    qlock[info.idx_q:info.idx_q + 2] = (math.cos(value), math.sin(value))
                else:
                    qlock[info.idx_q] = value
                lock_ids.append(info.joint_id)
            model = pin.buildReducedModel(full, sorted(lock_ids), qlock)
            model.gravity.linear = np.array([0.0, 0.0, -GRAVITY])
        else:
            model = full.copy()
        self.model = model
        self.data = model.createData()
        infos = []
        for jname in spec.joint_names:
            if not model.existJointName(jname):
                raise ValueError(f"robot '{spec.name}': joint '{jname}' is not in {spec.urdf_path}; "
                                 f"the URDF has {[model.names[i] for i in range(1, model.njoints)]}")
            infos.append(classify_joint(model, model.getJointId(jname), spec.name))
        if model.nv != spec.n_joints:
            raise ValueError(f"robot '{spec.name}': the model has {model.nv} degrees of freedom after "
                             f"locking {list(locked)}, but the spec lists {spec.n_joints} joints")
        self._infos = tuple(infos)
        self._idx_v = np.array([i.idx_v for i in infos])
        self._plain_q = np.array([i.idx_q for i in infos if not i.continuous], dtype=int)
        self._plain_j = np.array([k for k, i in enumerate(infos) if not i.continuous], dtype=int)
        self._cont_q = np.array([i.idx_q for i in infos if i.continuous], dtype=int)
        self._cont_j = np.array([k for k, i in enumerate(infos) if i.continuous], dtype=int)
        self.ee_frame_id = self.frame_id(spec.ee_frame)
        self._zero_v = np.zeros(model.nv)
        self._qpin_buffer = pin.neutral(model)

    # -- conversions ----------------------------------------------------------------------------
    def frame_id(self, frame: str) -> int:
        """Pinocchio index of a frame (a URDF link or joint name)."""
        if not self.model.existFrame(frame):
            raise ValueError(f"robot '{self.spec.name}' has no frame '{frame}'; links are "
                             f"{[f.name for f in self.model.frames if f.type == pin.FrameType.BODY]}")
        if self.model.existFrame(frame, pin.FrameType.BODY):  # a link and a joint may share a name
            return self.model.getFrameId(frame, pin.FrameType.BODY)
        return self.model.getFrameId(frame)

    def configuration(self, q) -> np.ndarray:
        """Pinocchio configuration vector, shape (nq,), from joint values, shape (n,)."""
        q = self.spec._check_shape(q, "q")
        if q.ndim != 1:
            raise ValueError(f"q must have shape ({self.spec.n_joints},); got {q.shape}")
        qp = np.empty(self.model.nq)
        qp[self._plain_q] = q[self._plain_j]
        if self._cont_q.size:
            qp[self._cont_q] = np.cos(q[self._cont_j])
            qp[self._cont_q + 1] = np.sin(q[self._cont_j])
        return qp

    def joint_values(self, qpin) -> np.ndarray:
        """Inverse of :meth:`configuration`: joint values, shape (n,), from shape (nq,)."""
        qpin = np.asarray(qpin, dtype=np.float64)
        q = np.empty(self.spec.n_joints)
        q[self._plain_j] = qpin[self._plain_q]
        if self._cont_q.size:
            q[self._cont_j] = np.arctan2(qpin[self._cont_q + 1], qpin[self._cont_q])
        return q

    # -- kinematics -----------------------------------------------------------------------------
    def forward_kinematics(self, q, frame: str | None = None) -> FramePose:
        """Pose of ``frame`` (default: the end effector) at joint values q, shape (n,)."""
        fid = self.ee_frame_id if frame is None else self.frame_id(frame)
        pin.forwardKinematics(self.model, self.data, self.configuration(q))
        M = pin.updateFramePlacement(self.model, self.data, fid)
        return FramePose(M.translation.copy(), M.rotation.copy())

    def jacobian(self, q, frame: str | None = None) -> np.ndarray:
        """Geometric Jacobian of ``frame`` (default: end effector), shape (6, n).

        Rows: linear velocity of the frame origin, then angular velocity, both in world
        axes (Pinocchio's LOCAL_WORLD_ALIGNED), so that [v; ω] = J q̇.
        """
        fid = self.ee_frame_id if frame is None else self.frame_id(frame)
        J = pin.computeFrameJacobian(self.model, self.data, self.configuration(q), fid,
                                     pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        return J[:, self._idx_v]

    def pose_and_jacobian(self, q) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """End-effector position (3,), rotation (3, 3) and Jacobian (6, n) (as :meth:`jacobian`)
        at joint values q, shape (n,), from one kinematics pass."""
        fid = self.ee_frame_id
        J = pin.computeFrameJacobian(self.model, self.data, self.configuration(q), fid,
                                     pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        M = pin.updateFramePlacement(self.model, self.data, fid)
        return M.translation.copy(), M.rotation.copy(), J[:, self._idx_v]

    # -- dynamics -------------------------------------------------------------------------------
    def gravity_torques(self, q) -> np.ndarray:
        """Joint torques g(q), shape (n,), that hold the arm still: τ = RNEA(q, q̇=0, q̈=0)."""
        tau = pin.rnea(self.model, self.data, self.configuration(q), self._zero_v, self._zero_v)
        return tau[self._idx_v].copy()

    def _gravity_unchecked(self, q: np.ndarray) -> np.ndarray:
        """:meth:`gravity_torques` without input validation, for control loops (q float64 (n,))."""
        qp = self._qpin_buffer
        qp[self._plain_q] = q[self._plain_j]
        if self._cont_q.size:
            qp[self._cont_q] = np.cos(q[self._cont_j])
            qp[self._cont_q + 1] = np.sin(q[self._cont_j])
        return pin.rnea(self.model, self.data, qp, self._zero_v, self._zero_v)[self._idx_v]

    # -- limits ---------------------------------------------------------------------------------
    def check_joint_limits(self, q, qd=None, *, tolerance: float = 1e-9) -> None:
        """Raise ``ValueError`` naming the joint if q (or q̇) is outside the spec's limits.

        Parameters
        ----------
        q : array_like, shape (..., n)
        qd : array_like, shape (..., n), optional
        """
        self.spec.validate_positions(q, tolerance=tolerance, label="q")
        if qd is not None:
            self.spec.validate_velocities(qd, tolerance=tolerance, label="qd")

    def within_limits(self, q, *, tolerance: float = 1e-9) -> bool:
        """True when every joint of q, shape (n,), is inside its position limits."""
        q = self.spec._check_shape(q, "q")
        return bool(np.all((q >= self.spec.lower - tolerance) & (q <= self.spec.upper + tolerance)))
