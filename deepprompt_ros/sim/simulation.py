"""PyBullet simulation of one fixed-base arm with objects and a camera (DIRECT mode, no ROS).

One :class:`Simulation` owns its own PyBullet physics client, so several instances in one process
do not interfere. Two control modes:

* **position control** (default): :meth:`Simulation.set_position_targets` sets joint targets
  (and optional feed-forward velocities). Each physics step turns them into a joint velocity
  command that respects the robot's velocity and acceleration limits (PyBullet ignores the URDF
  velocity limits, so they are enforced here) and hands it to PyBullet's velocity motors, whose
  torque is bounded by the URDF effort limits.
* **kinesthetic** mode: the motors are switched off and the joints are torque controlled with
  gravity compensation computed by Pinocchio, τ = g(q) − D q̇ (g from RNEA(q, 0, 0), D a small
  viscous damping), so the arm floats and can be guided by external forces
  (:meth:`Simulation.apply_guiding_force`, :meth:`Simulation.guide_towards`) like a human
  demonstrator guides a real arm in gravity-compensation mode.

Units: m, rad, s, N, N·m; quaternions are (x, y, z, w) as in PyBullet and ROS (conversions:
:mod:`deepprompt_ros.robots.geometry`). Camera poses and their matrices:
:mod:`deepprompt_ros.sim.camera`.

Length: over 400 lines because it is one class, the simulated arm: its position loop, kinesthetic
torque control, guiding forces, objects and rendering all act on the same PyBullet client, body
and joint tables inside one :meth:`Simulation.step`, and splitting the class would only spread
that shared state over several files.
"""
from __future__ import annotations

import contextlib
import ctypes
import math
import os
import time
from typing import NamedTuple, Sequence

import numpy as np
import pybullet as pb

from deepprompt_ros.robots.geometry import rotation_from_quat_xyzw
from deepprompt_ros.robots.kinematics import FramePose, RobotKinematics
from deepprompt_ros.robots.spec import GRAVITY, RobotSpec, links_without_inertial, load_robot
from deepprompt_ros.sim.camera import CameraPose, projection_matrix, view_matrix

__all__ = ["JointState", "ObjectPose", "Simulation", "SHAPES"]

#: Relative margin kept between velocity commands and the velocity limits.
_VELOCITY_MARGIN = 2e-3

#: Object shapes accepted by :meth:`Simulation.spawn_object` and the meaning of ``size``.
SHAPES = {
    "box": "size = (lx, ly, lz), full edge lengths",
    "sphere": "size = (radius,)",
    "cylinder": "size = (radius, length), axis along the object's z",
    "capsule": "size = (radius, length of the cylindrical part), axis along z",
}


class JointState(NamedTuple):
    """Measured joint state, each array of shape (n,) in ``spec.joint_names`` order.

    Attributes
    ----------
    position : array (rad or m)
    velocity : array (rad/s or m/s)
    effort : array (N·m or N): torque applied by the joint's actuator during the last step
    """

    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray


class ObjectPose(NamedTuple):
    """Pose of an object's centre of mass in the world frame.

    Attributes
    ----------
    position : array, shape (3,)
    orientation_xyzw : array, shape (4,)
    """

    position: np.ndarray
    orientation_xyzw: np.ndarray


@contextlib.contextmanager
def _quiet_stdout():
    """Silence the C-level stdout of PyBullet's URDF importer (mesh / inertia warnings)."""
    try:
        fd = os.dup(1)
    except OSError:  # no usable stdout
        yield
        return
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), 1)
            try:
                yield
            finally:
                try:
                    ctypes.CDLL(None).fflush(None)
                except (OSError, AttributeError):
                    pass
                os.dup2(fd, 1)
    finally:
        os.close(fd)


def _vec(values, n: int, label: str) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64).reshape(-1)
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{label} must be {n} finite numbers; got {values!r}")
    return arr


class Simulation:
    """One arm in its own PyBullet world (DIRECT mode), with a ground plane, objects and a camera.

    Parameters
    ----------
    robot : str or RobotSpec
        A name accepted by :func:`~deepprompt_ros.robots.spec.load_robot` (``"gen3_lite"``,
        ``"wam"``, ``"panda"``, ...) or a spec. The base is fixed at the world origin.
    timestep : float
        Physics step (s); default 1e-3 (1 kHz).
    real_time_factor : float
        0 runs as fast as possible; r > 0 paces :meth:`step` so that simulated time advances r
        times as fast as wall-clock time (1 = real time). When the simulation falls more than
        0.1 s of wall time behind, it resynchronises instead of racing to catch up.
    kinesthetic : bool
        Start in kinesthetic (gravity-compensated, torque-controlled) mode.
    camera : CameraPose, optional
        Default camera for :meth:`camera_image` (attribute ``camera``, may be reassigned); by
        default one that frames the arm at home and the ground in front of it.
    position_gain : float
        Gain k (1/s) of the position loop: far from the target the joint moves at its velocity
        limit, braking at its acceleration limit; close to it the error decays as exp(−k t).
    kinesthetic_damping : float or array of shape (n,), optional
        Viscous joint damping D (N·m·s/rad) in kinesthetic mode; default 0.01 s × effort limit.
    ground : bool
        Add a static ground plane at z = 0.
    initial_q : array of shape (n,), optional
        Start configuration; default ``spec.home``.
    """

    def __init__(
        self,
        robot: str | RobotSpec = "gen3_lite",
        *,
        timestep: float = 1e-3,
        real_time_factor: float = 0.0,
        kinesthetic: bool = False,
        camera: CameraPose | None = None,
        position_gain: float = 20.0,
        kinesthetic_damping: float | Sequence[float] | None = None,
        ground: bool = True,
        initial_q: Sequence[float] | None = None,
    ):
        if not (timestep > 0 and math.isfinite(timestep)):
            raise ValueError(f"timestep must be a positive number of seconds; got {timestep}")
        if not (position_gain > 0 and math.isfinite(position_gain)):
            raise ValueError(f"position_gain must be > 0 (1/s); got {position_gain}")
        self.spec: RobotSpec = load_robot(robot) if isinstance(robot, str) else robot
        self.kinematics = RobotKinematics(self.spec)
        n = self.spec.n_joints
        self.timestep = float(timestep)
        self.position_gain = float(position_gain)
        if kinesthetic_damping is None:
            damping = 0.01 * self.spec.effort
        else:
            damping = np.asarray(kinesthetic_damping, dtype=np.float64)
            if damping.shape not in ((), (n,)):
                raise ValueError(f"kinesthetic_damping must be a number or {n} numbers (one per joint: "
                                 f"{self.spec.joints_text()}); got shape {damping.shape}")
            damping = np.broadcast_to(damping, (n,)).copy()
        if np.any(~np.isfinite(damping)) or np.any(damping < 0):
            raise ValueError(f"kinesthetic_damping must be >= 0 (N·m·s/rad); got {kinesthetic_damping}")
        self.kinesthetic_damping = damping
        self._rtf = 0.0
        self._wall_ref: tuple[float, float] | None = None
        self.real_time_factor = real_time_factor

        self._client = pb.connect(pb.DIRECT)
        if self._client < 0:
            raise RuntimeError("could not start a PyBullet DIRECT client")
        self._closed = False
        c = self._client
        pb.setGravity(0.0, 0.0, -GRAVITY, physicsClientId=c)
        pb.setTimeStep(self.timestep, physicsClientId=c)
        if ground:
            col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[3.0, 3.0, 0.01], physicsClientId=c)
            vis = pb.createVisualShape(pb.GEOM_BOX, halfExtents=[3.0, 3.0, 0.01],
                                       rgbaColor=[0.55, 0.55, 0.52, 1.0], physicsClientId=c)
            self._ground = pb.createMultiBody(0.0, col, vis, basePosition=[0.0, 0.0, -0.01],
                                              physicsClientId=c)
        else:
            self._ground = None

        urdf = str(self.spec.urdf_path)
        with _quiet_stdout():
            self._robot = pb.loadURDF(urdf, [0.0, 0.0, 0.0], useFixedBase=True,
                                      flags=pb.URDF_USE_INERTIA_FROM_FILE, physicsClientId=c)
        self._joint_index: dict[str, int] = {}
        self._link_index: dict[str, int] = {}
        base_name = pb.getBodyInfo(self._robot, physicsClientId=c)[0].decode()
        self._link_index[base_name] = -1
        for j in range(pb.getNumJoints(self._robot, physicsClientId=c)):
            info = pb.getJointInfo(self._robot, j, physicsClientId=c)
            self._joint_index[info[1].decode()] = j
            self._link_index[info[12].decode()] = j
        missing = [jn for jn in self.spec.joint_names if jn not in self._joint_index]
        if missing:
            raise ValueError(f"robot '{self.spec.name}': PyBullet found no joint {missing} in {urdf}")
        self._arm = [self._joint_index[jn] for jn in self.spec.joint_names]
        self._locked = [(self._joint_index[jn], v) for jn, v in self.spec.locked_joints
                        if jn in self._joint_index]
        if self.spec.ee_frame not in self._link_index:
            raise ValueError(f"robot '{self.spec.name}': end-effector frame '{self.spec.ee_frame}' "
                             f"is not a link of {urdf}")
        self._ee_link = self._link_index[self.spec.ee_frame]

        # Same dynamics as Pinocchio: links without <inertial> are massless there, 1 kg in PyBullet;
        # no extra velocity damping on the links (PyBullet's default is 0.04).
        massless = links_without_inertial(urdf)
        for lname, li in self._link_index.items():
            if li >= 0 and lname in massless:
                pb.changeDynamics(self._robot, li, mass=1e-6, localInertiaDiagonal=[1e-9] * 3,
                                  physicsClientId=c)
            pb.changeDynamics(self._robot, li, linearDamping=0.0, angularDamping=0.0,
                              jointDamping=0.0, physicsClientId=c)

        # Velocity commands stay _VELOCITY_MARGIN (relative) under the limit: PyBullet's motors (a soft
        # constraint) overshoot their target by up to ~0.03 %, and the measured velocity must not
        # exceed the limit.
        self._v_cmd_max = self.spec.velocity * (1.0 - _VELOCITY_MARGIN)
        # bounds of set_position_targets' checks (those of RobotSpec.validate_positions /
        # validate_velocities with tolerance 1e-6), for plain comparisons in the common case
        self._shape = (n,)
        self._q_lo_tol = self.spec.lower - 1e-6
        self._q_hi_tol = self.spec.upper + 1e-6
        self._qd_bound = self.spec.velocity * (1.0 + 1e-6) + 1e-6
        self._neg_velocity = -self.spec.velocity
        # joint positions read by joint_state() since the last change of the state (step, reset,
        # mode switch): the next step() starts from them instead of reading them again
        self._q_read: list | None = None
        self._two_acc = 2.0 * self.spec.acceleration
        self._dv_max = self.spec.acceleration * self.timestep
        self._cmd_limits = (self._v_cmd_max.tolist(), self._two_acc.tolist(), self._dv_max.tolist())
        self._effort_list = self.spec.effort.tolist()
        self._objects: dict[str, int] = {}
        self._forces: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # link -> (force, local offset)
        self._spring: tuple[np.ndarray, float, float, float] | None = None
        self._kinesthetic = False
        self._time = 0.0
        self._tau_cmd = np.zeros(n)
        self._q_target = np.zeros(n)
        self._qd_ff = np.zeros(n)
        self._v_cmd = np.zeros(n)
        self.camera = self._default_camera() if camera is None else camera
        self.reset(self.spec.home if initial_q is None else initial_q)
        self.set_kinesthetic(kinesthetic)

    def _default_camera(self) -> CameraPose:
        """Camera that frames the arm at home and the ground in front of it.

        Looks at the centre of the box around the base and the link frames (at y = 0), from the
        front-left-above direction (0.8, 0.45, 0.4), from 2.4 × the box's half diagonal.
        """
        for j, qj in zip(self._arm, self.spec.home):
            pb.resetJointState(self._robot, j, float(qj), 0.0, physicsClientId=self._client)
        pts = np.array([np.zeros(3)] + [self._link_state(li)[0] for li in self._link_index.values()])
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        target = (lo + hi) / 2.0
        target[1] = 0.0
        half_diag = max(float(np.linalg.norm(hi - lo)) / 2.0, 0.1)
        direction = np.array([0.8, 0.45, 0.4]) / np.linalg.norm([0.8, 0.45, 0.4])
        eye = target + 2.4 * half_diag * direction
        return CameraPose(eye=tuple(eye), target=tuple(target), fov_deg=50.0)

    # ------------------------------------------------------------------------------------------
    # life cycle
    # ------------------------------------------------------------------------------------------
    @property
    def client_id(self) -> int:
        """PyBullet physics client id of this simulation."""
        return self._client

    @property
    def robot_id(self) -> int:
        """PyBullet body id of the robot."""
        return self._robot

    @property
    def time(self) -> float:
        """Simulated time since construction (s); :meth:`reset` does not rewind it."""
        return self._time

    @property
    def real_time_factor(self) -> float:
        return self._rtf

    @real_time_factor.setter
    def real_time_factor(self, value: float) -> None:
        value = float(value)
        if not (value >= 0.0 and math.isfinite(value)):
            raise ValueError(f"real_time_factor must be >= 0 (0 = as fast as possible); got {value}")
        self._rtf = value
        self._wall_ref = None

    def close(self) -> None:
        """Disconnect the PyBullet client (idempotent)."""
        if not getattr(self, "_closed", True):
            self._closed = True
            try:
                pb.disconnect(physicsClientId=self._client)
            except pb.error:
                pass

    def __enter__(self) -> "Simulation":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown: pybullet may already be gone
            pass

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("this Simulation has been closed")

    # ------------------------------------------------------------------------------------------
    # robot state and control
    # ------------------------------------------------------------------------------------------
    def reset(self, q: Sequence[float] | None = None) -> None:
        """Teleport the arm to q (default: home) at rest, hold it there and drop guiding forces.

        Parameters
        ----------
        q : array_like, shape (n,), optional
        """
        self._check_open()
        q = self.spec.home if q is None else q
        q = self.spec.validate_positions(q, tolerance=1e-6, label="reset configuration")
        for j, qj in zip(self._arm, q):
            pb.resetJointState(self._robot, j, float(qj), 0.0, physicsClientId=self._client)
        for j, v in self._locked:
            pb.resetJointState(self._robot, j, v, 0.0, physicsClientId=self._client)
        self._q_read = None
        self._q_target = q.copy()
        self._qd_ff = np.zeros(self.spec.n_joints)
        self._v_cmd = np.zeros(self.spec.n_joints)
        self._tau_cmd = np.zeros(self.spec.n_joints)
        self.release()
        self._configure_motors()

    def _configure_motors(self) -> None:
        c = self._client
        # Locked joints (e.g. gripper fingers) are always position controlled.
        if self._locked:
            idx = [j for j, _ in self._locked]
            forces = []
            for j in idx:
                f = pb.getJointInfo(self._robot, j, physicsClientId=c)[10]
                forces.append(f if f > 0 else 100.0)
            pb.setJointMotorControlArray(self._robot, idx, pb.POSITION_CONTROL,
                                         targetPositions=[v for _, v in self._locked],
                                         forces=forces, physicsClientId=c)
        if self._kinesthetic:
            # Switch the velocity motors off: the joints are then driven by the torques of step().
            pb.setJointMotorControlArray(self._robot, self._arm, pb.VELOCITY_CONTROL,
                                         targetVelocities=[0.0] * len(self._arm),
                                         forces=[0.0] * len(self._arm), physicsClientId=c)

    @property
    def kinesthetic(self) -> bool:
        return self._kinesthetic

    def set_kinesthetic(self, enabled: bool) -> None:
        """Switch kinesthetic (gravity-compensated) mode on or off.

        Switching off holds the arm where it is: the position target becomes the current
        configuration and the velocity command starts from the measured velocity.
        """
        self._check_open()
        enabled = bool(enabled)
        if enabled == self._kinesthetic:
            return
        self._kinesthetic = enabled
        self._q_read = None
        if not enabled:
            q, qd, _ = self.joint_state()
            self._q_target = self.spec.clip_positions(q)
            self._qd_ff = np.zeros(self.spec.n_joints)
            self._v_cmd = np.clip(qd, -self._v_cmd_max, self._v_cmd_max)
            self._tau_cmd = np.zeros(self.spec.n_joints)
        self._configure_motors()

    def set_position_targets(self, q: Sequence[float], qd: Sequence[float] | None = None) -> None:
        """Set the joint position targets (position-control mode).

        Parameters
        ----------
        q : array_like, shape (n,)
            Target positions, inside the position limits (to 1e-6): where the joints should be
            now. A streamer sends one target per step; the position loop then follows with an
            error decaying as exp(−k t) (k = ``position_gain``).
        qd : array_like, shape (n,), optional
            Feed-forward velocities (e.g. of a streamed trajectory), |qd| <= velocity limit.
            Default: zero (move to q and stop there).

        Raises
        ------
        ValueError
            Wrong length, non-finite values or limits violated (the message names the joint).
        RuntimeError
            Kinesthetic mode is on.
        """
        self._check_open()
        if self._kinesthetic:
            raise RuntimeError("kinesthetic mode is on: position targets are not accepted; call "
                               "set_kinesthetic(False) first")
        spec = self.spec
        # common case first: n finite values inside the limits, tested with plain comparisons
        # (NaN fails them); anything else takes the full check, which raises with the details
        arr = np.asarray(q, dtype=np.float64)
        if arr.shape == self._shape and (self._q_lo_tol <= arr).all() and (arr <= self._q_hi_tol).all():
            q = np.minimum(np.maximum(arr, spec.lower), spec.upper)  # = np.clip, faster for (n,)
        else:
            q = spec.validate_positions(q, tolerance=1e-6, label="position target")
            if q.ndim != 1:
                raise ValueError(f"position target must have shape ({spec.n_joints},); got {q.shape}")
        if qd is None:
            qd_arr = np.zeros(spec.n_joints)
        else:
            arr = np.asarray(qd, dtype=np.float64)
            if arr.shape == self._shape and (np.abs(arr) <= self._qd_bound).all():
                qd_arr = np.minimum(np.maximum(arr, self._neg_velocity), spec.velocity)
            else:
                qd_arr = spec.validate_velocities(qd, tolerance=1e-6, label="velocity target")
                if qd_arr.ndim != 1:
                    raise ValueError(f"velocity target must have shape ({spec.n_joints},); got {qd_arr.shape}")
        self._q_target = q
        self._qd_ff = qd_arr

    @property
    def position_targets(self) -> np.ndarray:
        """Current position targets, shape (n,)."""
        return self._q_target.copy()

    def joint_state(self) -> JointState:
        """Measured (position, velocity, effort) of the controlled joints, each shape (n,)."""
        self._check_open()
        states = pb.getJointStates(self._robot, self._arm, physicsClientId=self._client)
        q = np.array([s[0] for s in states])
        qd = np.array([s[1] for s in states])
        motor = np.array([s[3] for s in states])
        effort = motor + self._tau_cmd if self._kinesthetic else motor
        self._q_read = q.tolist()
        return JointState(q, qd, effort)

    def _velocity_command(self, q: list) -> list:
        """Joint velocity command of the position loop, within the velocity/acceleration limits.

        v_fb = sign(e) min(k|e|, sqrt(2 a |e|)) brakes at the acceleration limit a before the
        target; v = clip(q̇_ff + v_fb, ±v_cmd_max), then its change per step is limited to a·dt.
        (Plain floats, joint by joint: on arrays this small numpy's per-call overhead dominates.)

        Parameters
        ----------
        q : list of n floats
            Measured positions.

        Returns
        -------
        list of n floats
        """
        k = self.position_gain
        out = []
        for qt, qi, ff, vc, vmax, two_a, dv_max in zip(self._q_target.tolist(), q, self._qd_ff.tolist(),
                                                      self._v_cmd.tolist(), *self._cmd_limits):
            e = qt - qi
            ae = abs(e)
            fb = k * ae
            r = math.sqrt(two_a * ae)
            fb = math.copysign(r if r < fb else fb, e)
            v = ff + fb
            v = -vmax if v < -vmax else (vmax if v > vmax else v)
            dv = v - vc
            dv = -dv_max if dv < -dv_max else (dv_max if dv > dv_max else dv)
            out.append(vc + dv)
        return out

    def step(self, n: int = 1) -> None:
        """Advance the simulation by ``n`` physics steps of ``timestep`` seconds."""
        self._check_open()
        n = int(n)
        if n < 0:
            raise ValueError(f"number of steps must be >= 0; got {n}")
        c, robot, arm = self._client, self._robot, self._arm
        for _ in range(n):
            q = self._q_read
            if q is None or self._kinesthetic:
                states = pb.getJointStates(robot, arm, physicsClientId=c)
                q = [s[0] for s in states]
            self._q_read = None
            if self._kinesthetic:
                q = np.array(q)
                qd = np.array([s[1] for s in states])
                tau = self.kinematics._gravity_unchecked(q) - self.kinesthetic_damping * qd
                self._tau_cmd = np.clip(tau, -self.spec.effort, self.spec.effort)
                pb.setJointMotorControlArray(robot, arm, pb.TORQUE_CONTROL, forces=self._tau_cmd,
                                             physicsClientId=c)
            else:
                v_cmd = self._velocity_command(q)
                self._v_cmd = np.array(v_cmd)
                # (lists: pybullet reads numpy arrays element by element, which is slower)
                pb.setJointMotorControlArray(robot, arm, pb.VELOCITY_CONTROL,
                                             targetVelocities=v_cmd, forces=self._effort_list,
                                             physicsClientId=c)
            if self._forces or self._spring is not None:
                self._apply_external_forces()
            pb.stepSimulation(physicsClientId=c)
            self._time += self.timestep
            if self._rtf > 0.0:
                self._pace()

    def _pace(self) -> None:
        now = time.perf_counter()
        if self._wall_ref is None:
            self._wall_ref = (now, self._time)
            return
        wall0, sim0 = self._wall_ref
        delay = wall0 + (self._time - sim0) / self._rtf - now
        if delay > 0.0:
            time.sleep(delay)
        elif delay < -0.1:
            self._wall_ref = (now, self._time)

    # ------------------------------------------------------------------------------------------
    # end effector and guiding forces
    # ------------------------------------------------------------------------------------------
    def _link(self, link: str) -> int:
        if link == "ee":
            return self._ee_link
        if link not in self._link_index:
            raise ValueError(f"robot '{self.spec.name}' has no link '{link}'; use 'ee' or one of "
                             f"{sorted(self._link_index)}")
        return self._link_index[link]

    def _link_state(self, li: int, velocity: bool = False):
        if li < 0:
            pos, orn = pb.getBasePositionAndOrientation(self._robot, physicsClientId=self._client)
            return np.array(pos), np.array(orn), np.zeros(3)
        s = pb.getLinkState(self._robot, li, computeLinkVelocity=int(velocity),
                            computeForwardKinematics=1, physicsClientId=self._client)
        v = np.array(s[6]) if velocity else np.zeros(3)
        return np.array(s[4]), np.array(s[5]), v

    def link_pose(self, link: str = "ee") -> FramePose:
        """World pose of a link frame as PyBullet simulates it ('ee' = the end-effector frame)."""
        self._check_open()
        pos, orn, _ = self._link_state(self._link(link))
        R = rotation_from_quat_xyzw(orn)
        return FramePose(pos, R)

    def ee_position(self) -> np.ndarray:
        """World position of the end-effector frame, shape (3,)."""
        return self.link_pose("ee").position

    def apply_guiding_force(self, link_or_ee: str, force_world: Sequence[float],
                            position: Sequence[float] | None = None) -> None:
        """Push a link with a constant world-frame force, at every step until :meth:`release`.

        Parameters
        ----------
        link_or_ee : str
            ``"ee"`` or a link name of the URDF.
        force_world : array_like, shape (3,)
            Force (N) in world axes; replaces an earlier force on the same link.
        position : array_like, shape (3,), optional
            World point where the force acts at the time of the call; it then moves with the
            link. Default: the link frame's origin.
        """
        self._check_open()
        li = self._link(link_or_ee)
        f = _vec(force_world, 3, "force_world")
        if position is None:
            offset = np.zeros(3)
        else:
            p = _vec(position, 3, "position")
            pos, orn, _ = self._link_state(li)
            R = rotation_from_quat_xyzw(orn)
            offset = R.T @ (p - pos)
        self._forces[li] = (f, offset)

    def guide_towards(self, target_xyz: Sequence[float], stiffness: float = 100.0,
                      damping: float | None = None, max_force: float = 50.0) -> None:
        """Pull the end effector towards a point with a spring, at every step until :meth:`release`.

        F = clip(K (target − p_ee) − C v_ee, max_force) acts at the end-effector origin, like a
        hand guiding the arm. Most useful in kinesthetic mode.

        Parameters
        ----------
        target_xyz : array_like, shape (3,)
            World point (m).
        stiffness : float
            K (N/m), > 0.
        damping : float, optional
            C (N·s/m); default 2 sqrt(K × 1 kg), critical damping of a 1 kg point.
        max_force : float
            Bound on |F| (N).
        """
        self._check_open()
        target = _vec(target_xyz, 3, "target_xyz")
        if not (stiffness > 0 and math.isfinite(stiffness)):
            raise ValueError(f"stiffness must be > 0 (N/m); got {stiffness}")
        damping = 2.0 * math.sqrt(stiffness) if damping is None else float(damping)
        if not (damping >= 0 and math.isfinite(damping)):
            raise ValueError(f"damping must be >= 0 (N·s/m); got {damping}")
        if not (max_force > 0):
            raise ValueError(f"max_force must be > 0 (N); got {max_force}")
        self._spring = (target, float(stiffness), damping, float(max_force))

    def release(self) -> None:
        """Remove every guiding force and the guiding spring."""
        self._forces = {}
        self._spring = None

    def _apply_external_forces(self) -> None:
        c = self._client
        for li, (f, offset) in self._forces.items():
            pos, orn, _ = self._link_state(li)
            R = rotation_from_quat_xyzw(orn)
            pb.applyExternalForce(self._robot, li, f.tolist(), (pos + R @ offset).tolist(),
                                  pb.WORLD_FRAME, physicsClientId=c)
        if self._spring is not None:
            target, k, d, fmax = self._spring
            pos, _, vel = self._link_state(self._ee_link, velocity=True)
            f = k * (target - pos) - d * vel
            norm = float(np.linalg.norm(f))
            if norm > fmax:
                f *= fmax / norm
            pb.applyExternalForce(self._robot, self._ee_link, f.tolist(), pos.tolist(),
                                  pb.WORLD_FRAME, physicsClientId=c)

    # ------------------------------------------------------------------------------------------
    # objects
    # ------------------------------------------------------------------------------------------
    @property
    def objects(self) -> tuple[str, ...]:
        """Names of the spawned objects."""
        return tuple(self._objects)

    def spawn_object(self, name: str, shape: str = "box", size: Sequence[float] = (0.05, 0.05, 0.05),
                     position: Sequence[float] = (0.4, 0.0, 0.025),
                     orientation_xyzw: Sequence[float] = (0.0, 0.0, 0.0, 1.0),
                     rgba: Sequence[float] = (0.85, 0.15, 0.1, 1.0), mass: float = 0.1) -> int:
        """Add a rigid object and return its PyBullet body id.

        Parameters
        ----------
        name : str
            Unique name, used by :meth:`object_pose` and :meth:`remove_object`.
        shape : {"box", "sphere", "cylinder", "capsule"}
            See :data:`SHAPES` for the meaning of ``size``.
        size : sequence of float
            Dimensions (m), all > 0.
        position : array_like, shape (3,)
            World position of the object's centre (m).
        orientation_xyzw : array_like, shape (4,)
            World orientation (normalised here).
        rgba : array_like, shape (4,)
            Colour, components in [0, 1].
        mass : float
            kg; 0 makes a static object.
        """
        self._check_open()
        if not isinstance(name, str) or not name:
            raise ValueError(f"object name must be a non-empty string; got {name!r}")
        if name in self._objects:
            raise ValueError(f"an object named '{name}' exists already; objects: {list(self._objects)}")
        if shape not in SHAPES:
            raise ValueError(f"unknown shape '{shape}'; expected one of: "
                             + "; ".join(f"{k} ({v})" for k, v in SHAPES.items()))
        size_arr = np.asarray(size, dtype=np.float64).reshape(-1)
        expected = {"box": 3, "sphere": 1, "cylinder": 2, "capsule": 2}[shape]
        if size_arr.shape != (expected,) or not np.all(np.isfinite(size_arr) & (size_arr > 0)):
            raise ValueError(f"size of a {shape} must be {expected} positive numbers ({SHAPES[shape]}); "
                             f"got {size!r}")
        pos = _vec(position, 3, "position")
        orn = _vec(orientation_xyzw, 4, "orientation_xyzw")
        if np.linalg.norm(orn) < 1e-9:
            raise ValueError("orientation_xyzw must be a non-zero quaternion (x, y, z, w)")
        orn = orn / np.linalg.norm(orn)
        color = _vec(rgba, 4, "rgba")
        if np.any((color < 0) | (color > 1)):
            raise ValueError(f"rgba components must be in [0, 1]; got {rgba!r}")
        if not (mass >= 0 and math.isfinite(mass)):
            raise ValueError(f"mass must be >= 0 kg (0 = static); got {mass}")
        c = self._client
        if shape == "box":
            kw = dict(halfExtents=(size_arr / 2).tolist())
            col = pb.createCollisionShape(pb.GEOM_BOX, physicsClientId=c, **kw)
            vis = pb.createVisualShape(pb.GEOM_BOX, rgbaColor=color.tolist(), physicsClientId=c, **kw)
        elif shape == "sphere":
            col = pb.createCollisionShape(pb.GEOM_SPHERE, radius=size_arr[0], physicsClientId=c)
            vis = pb.createVisualShape(pb.GEOM_SPHERE, radius=size_arr[0], rgbaColor=color.tolist(),
                                       physicsClientId=c)
        else:
            g = pb.GEOM_CYLINDER if shape == "cylinder" else pb.GEOM_CAPSULE
            col = pb.createCollisionShape(g, radius=size_arr[0], height=size_arr[1], physicsClientId=c)
            vis = pb.createVisualShape(g, radius=size_arr[0], length=size_arr[1],
                                       rgbaColor=color.tolist(), physicsClientId=c)
        body = pb.createMultiBody(float(mass), col, vis, basePosition=pos.tolist(),
                                  baseOrientation=orn.tolist(), physicsClientId=c)
        self._objects[name] = body
        return body

    def _object(self, name: str) -> int:
        if name not in self._objects:
            raise ValueError(f"no object named '{name}'; objects: {list(self._objects)}")
        return self._objects[name]

    def object_pose(self, name: str) -> ObjectPose:
        """World pose of object ``name``."""
        self._check_open()
        pos, orn = pb.getBasePositionAndOrientation(self._object(name), physicsClientId=self._client)
        return ObjectPose(np.array(pos), np.array(orn))

    def set_object_pose(self, name: str, position: Sequence[float],
                        orientation_xyzw: Sequence[float] = (0.0, 0.0, 0.0, 1.0)) -> None:
        """Teleport object ``name`` (at rest) to a pose."""
        self._check_open()
        body = self._object(name)
        orn = _vec(orientation_xyzw, 4, "orientation_xyzw")
        orn = orn / np.linalg.norm(orn)
        pb.resetBasePositionAndOrientation(body, _vec(position, 3, "position").tolist(), orn.tolist(),
                                           physicsClientId=self._client)
        pb.resetBaseVelocity(body, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], physicsClientId=self._client)

    def remove_object(self, name: str) -> None:
        """Remove object ``name`` from the world."""
        self._check_open()
        body = self._object(name)
        pb.removeBody(body, physicsClientId=self._client)
        del self._objects[name]

    # ------------------------------------------------------------------------------------------
    # camera
    # ------------------------------------------------------------------------------------------
    def camera_image(self, width: int = 128, height: int = 128,
                     camera: CameraPose | None = None) -> np.ndarray:
        """RGB image rendered by PyBullet's software renderer (ER_TINY_RENDERER).

        Parameters
        ----------
        width, height : int
            Image size in pixels (1..4096).
        camera : CameraPose, optional
            Default: the simulation's ``camera``.

        Returns
        -------
        image : array of uint8, shape (height, width, 3)
        """
        self._check_open()
        width, height = int(width), int(height)
        if not (1 <= width <= 4096 and 1 <= height <= 4096):
            raise ValueError(f"image size must be 1..4096 pixels per side; got {width}x{height}")
        cam = self.camera if camera is None else camera
        view, proj = view_matrix(cam), projection_matrix(cam, width, height)
        _, _, rgba, _, _ = pb.getCameraImage(width, height, view, proj,
                                             renderer=pb.ER_TINY_RENDERER,
                                             physicsClientId=self._client)
        img = np.asarray(rgba, dtype=np.uint8).reshape(height, width, 4)
        return np.ascontiguousarray(img[:, :, :3])
