"""Robot descriptions: joint limits, URDF files and Pinocchio kinematics / dynamics.

Two arms ship with the package as URDF files written from the manufacturers' published numbers
(``deepprompt_ros/resources/urdf``; every number is cited in the file):

* ``"gen3_lite"`` — Kinova Gen3 lite, 6 DoF, joints ``joint_1``..``joint_6`` (Kinova's names),
  end-effector frame ``tool_frame`` (between the gripper's fingertips).
* ``"wam"`` — Barrett WAM, 7 DoF, joints ``wam_j1``..``wam_j7`` (J1..J7 of Barrett's manual),
  end-effector frame ``wam_tool_plate`` (DH frame 7, no hand).

Any fixed-base arm of ``example-robot-data`` can be loaded by its loader name (``"panda"``,
``"ur5"``, ``"xarm7"``, ``"kinova"``...). Their position / velocity / effort limits come from the
URDF; the acceleration and jerk limits are the defaults documented at
:data:`DEFAULT_ACCELERATION_PER_VELOCITY` unless the manufacturer's figures are known here (panda).

All limits are per joint, in the robot's units (rad, rad/s, rad/s², rad/s³, N·m; m and N for
prismatic joints). Continuous joints (no position limit; Pinocchio represents their angle by
(cos θ, sin θ), so nq != nv) are supported: their position limits are ``-inf`` / ``+inf`` and every
function here takes and returns plain joint angles.
"""
from __future__ import annotations

import dataclasses
import functools
import importlib.resources
import math
import os
import pathlib
import shutil
import tempfile
import xml.etree.ElementTree as ET
from typing import NamedTuple, Sequence

import numpy as np
import pinocchio as pin

__all__ = [
    "GRAVITY",
    "DEFAULT_ACCELERATION_PER_VELOCITY",
    "DEFAULT_JERK_PER_ACCELERATION",
    "RobotSpec",
    "FramePose",
    "RobotKinematics",
    "available_robots",
    "load_robot",
    "urdf_path",
    "links_without_inertial",
]

#: Standard gravity used by both Pinocchio and the simulation (m/s², along -z of the world).
GRAVITY = 9.81

#: Default acceleration limit when the manufacturer gives none: a_max = 2 /s × v_max, i.e. a joint
#: reaches its full speed in 0.5 s.
DEFAULT_ACCELERATION_PER_VELOCITY = 2.0
#: Default jerk limit when the manufacturer gives none: j_max = 10 /s × a_max, i.e. the full
#: acceleration is reached in 0.1 s.
DEFAULT_JERK_PER_ACCELERATION = 10.0

_PACKAGE_ROBOTS = ("gen3_lite", "wam")


# ----------------------------------------------------------------------------------------------
# Robot specification
# ----------------------------------------------------------------------------------------------
def _joint_list_text(names: Sequence[str]) -> str:
    """``joint_1..joint_6`` for numbered names, else a comma-separated list."""
    names = list(names)
    if len(names) >= 3:
        stem = names[0].rstrip("0123456789")
        tails = [n[len(stem):] for n in names]
        if all(n.startswith(stem) for n in names) and all(t.isdigit() for t in tails):
            nums = [int(t) for t in tails]
            if nums == list(range(nums[0], nums[0] + len(nums))):
                return f"{names[0]}..{names[-1]}"
    return ", ".join(names)


@dataclasses.dataclass(frozen=True, eq=False)
class RobotSpec:
    """Everything a controller needs to know about an arm, without Pinocchio or PyBullet.

    Arrays are float64, read-only, one value per joint in ``joint_names`` order.

    Attributes
    ----------
    name : str
        Name given to :func:`load_robot`.
    urdf_path : pathlib.Path
    joint_names : tuple of str, length n
        The controlled joints, in the order of every array here.
    lower, upper : array, shape (n,)
        Position limits (rad or m); ``-inf`` / ``+inf`` for continuous joints.
    velocity, acceleration, jerk : array, shape (n,)
        Symmetric limits |q̇| <= velocity, |q̈| <= acceleration, |q⃛| <= jerk (all > 0).
    effort : array, shape (n,)
        Torque / force limits (N·m or N) from the URDF.
    control_rate_hz : float
        Rate of the robot's joint controller (the rate a trajectory stream should have).
    ee_frame : str
        Name of the end-effector frame (a URDF link).
    home : array, shape (n,)
        A ready configuration inside the limits.
    locked_joints : tuple of (str, float)
        Joints of the URDF that are not controlled (e.g. gripper fingers), held at these values.
    limits_source : str
        Where the limits come from (free text, for model files and logs).
    """

    name: str
    urdf_path: pathlib.Path
    joint_names: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    jerk: np.ndarray
    effort: np.ndarray
    control_rate_hz: float
    ee_frame: str
    home: np.ndarray
    locked_joints: tuple[tuple[str, float], ...] = ()
    limits_source: str = ""

    def __post_init__(self) -> None:
        n = len(self.joint_names)
        if n == 0:
            raise ValueError(f"robot '{self.name}' has no joints; expected at least one")
        if len(set(self.joint_names)) != n:
            raise ValueError(f"robot '{self.name}' has duplicate joint names: {self.joint_names}")
        object.__setattr__(self, "joint_names", tuple(self.joint_names))
        object.__setattr__(self, "urdf_path", pathlib.Path(self.urdf_path))
        for field in ("lower", "upper", "velocity", "acceleration", "jerk", "effort", "home"):
            arr = np.array(getattr(self, field), dtype=np.float64)
            if arr.shape != (n,):
                raise ValueError(
                    f"robot '{self.name}': {field} has shape {arr.shape}; expected ({n},), one value "
                    f"per joint ({_joint_list_text(self.joint_names)})")
            arr.setflags(write=False)
            object.__setattr__(self, field, arr)
        if np.any(np.isnan(self.lower)) or np.any(np.isnan(self.upper)) or np.any(self.lower > self.upper):
            raise ValueError(f"robot '{self.name}': position limits must satisfy lower <= upper; "
                             f"got lower={self.lower}, upper={self.upper}")
        for field in ("velocity", "acceleration", "jerk"):
            arr = getattr(self, field)
            if not np.all(np.isfinite(arr) & (arr > 0)):
                raise ValueError(f"robot '{self.name}': {field} limits must be finite and > 0; got {arr}")
        if not (self.control_rate_hz > 0):
            raise ValueError(f"robot '{self.name}': control_rate_hz must be > 0; got {self.control_rate_hz}")
        object.__setattr__(self, "control_rate_hz", float(self.control_rate_hz))
        object.__setattr__(self, "locked_joints",
                           tuple((str(j), float(v)) for j, v in self.locked_joints))
        self.validate_positions(self.home, label="home")

    # -- convenience ----------------------------------------------------------------------------
    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def continuous(self) -> np.ndarray:
        """Boolean mask, shape (n,): joints without position limits."""
        return ~(np.isfinite(self.lower) & np.isfinite(self.upper))

    def joints_text(self) -> str:
        """The joint names for messages, e.g. ``"joint_1..joint_6"``."""
        return _joint_list_text(self.joint_names)

    def to_dict(self) -> dict:
        """Plain-python description (lists and floats) for JSON model files; ``inf`` stays ``inf``."""
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, np.ndarray):
                v = [float(x) for x in v]
            elif isinstance(v, pathlib.Path):
                v = str(v)
            elif f.name == "joint_names":
                v = list(v)
            elif f.name == "locked_joints":
                v = [[j, x] for j, x in v]
            out[f.name] = v
        return out

    # -- validation -----------------------------------------------------------------------------
    def _check_shape(self, values, label: str) -> np.ndarray:
        arr = np.asarray(values, dtype=np.float64)
        if arr.ndim == 0 or arr.shape[-1] != self.n_joints:
            got = "a scalar" if arr.ndim == 0 else f"{arr.shape[-1]} joint values (shape {arr.shape})"
            raise ValueError(f"{label} has {got}; robot '{self.name}' has {self.n_joints} joints: "
                             f"{self.joints_text()}")
        if np.any(~np.isfinite(arr)):
            bad = sorted({self.joint_names[j] for j in np.argwhere(~np.isfinite(arr))[:, -1]})
            raise ValueError(f"{label} contains NaN or inf for joint(s) {', '.join(bad)} of robot "
                             f"'{self.name}'; expected finite values")
        return arr

    def validate_positions(self, q, *, tolerance: float = 1e-9, label: str = "q") -> np.ndarray:
        """Check joint positions against the limits.

        Parameters
        ----------
        q : array_like, shape (..., n)
        tolerance : float
            Values outside the limits by at most this much are accepted and clipped.
        label : str
            What ``q`` is, for the error message.

        Returns
        -------
        q : array, shape (..., n)
            A float64 copy, clipped to the limits.

        Raises
        ------
        ValueError
            Wrong number of joints, non-finite values, or a position outside its limits; the
            message names the joint, the value and the limits.
        """
        arr = self._check_shape(q, label)
        lo, hi = self.lower - tolerance, self.upper + tolerance
        bad = (arr < lo) | (arr > hi)
        if np.any(bad):
            msgs = []
            for idx in np.argwhere(bad)[:5]:
                j = idx[-1]
                where = f"[{', '.join(map(str, idx[:-1]))}] " if arr.ndim > 1 else ""
                msgs.append(f"{where}joint '{self.joint_names[j]}' = {arr[tuple(idx)]:.4f} is outside "
                            f"[{self.lower[j]:.4f}, {self.upper[j]:.4f}]")
            more = f" (and {int(bad.sum()) - 5} more)" if bad.sum() > 5 else ""
            raise ValueError(f"{label} violates the position limits of robot '{self.name}': "
                             + "; ".join(msgs) + more)
        return np.clip(arr, self.lower, self.upper)

    def validate_velocities(self, qd, *, tolerance: float = 1e-9, label: str = "qd") -> np.ndarray:
        """Check |q̇| <= velocity limit (same conventions as :meth:`validate_positions`).

        Parameters
        ----------
        qd : array_like, shape (..., n)

        Returns
        -------
        qd : array, shape (..., n)
            A float64 copy, clipped to ±velocity.
        """
        arr = self._check_shape(qd, label)
        bad = np.abs(arr) > self.velocity * (1.0 + tolerance) + tolerance
        if np.any(bad):
            msgs = []
            for idx in np.argwhere(bad)[:5]:
                j = idx[-1]
                msgs.append(f"joint '{self.joint_names[j]}' = {arr[tuple(idx)]:.4f} exceeds "
                            f"±{self.velocity[j]:.4f}")
            raise ValueError(f"{label} violates the velocity limits of robot '{self.name}': "
                             + "; ".join(msgs))
        return np.clip(arr, -self.velocity, self.velocity)

    def clip_positions(self, q) -> np.ndarray:
        """Clip positions, shape (..., n), into the limits (no error for values outside)."""
        return np.clip(self._check_shape(q, "q"), self.lower, self.upper)


# ----------------------------------------------------------------------------------------------
# URDF locations
# ----------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=None)
def _packaged_urdf(name: str) -> pathlib.Path:
    res = importlib.resources.files("deepprompt_ros") / "resources" / "urdf" / f"{name}.urdf"
    if isinstance(res, pathlib.Path):
        return res
    # Installed as a zip: Pinocchio and PyBullet need a real file; extract once per process.
    out = pathlib.Path(tempfile.mkdtemp(prefix="deepprompt_urdf_")) / f"{name}.urdf"
    with importlib.resources.as_file(res) as src:
        shutil.copyfile(src, out)
    return out


def _erd_loader(name: str):
    try:
        from example_robot_data.robots_loader import ROBOTS
    except ImportError:  # pragma: no cover - example-robot-data is a declared dependency
        return None
    return ROBOTS.get(name)


def _erd_urdf(loader) -> pathlib.Path:
    from example_robot_data.utils import getModelPath

    sub = os.path.join(loader.path, loader.urdf_subpath, loader.urdf_filename)
    return pathlib.Path(os.path.normpath(os.path.join(getModelPath(sub), sub)))


def _erd_srdf(loader) -> pathlib.Path | None:
    from example_robot_data.utils import getModelPath

    if not getattr(loader, "srdf_filename", ""):
        return None
    sub = os.path.join(loader.path, loader.srdf_subpath, loader.srdf_filename)
    try:
        return pathlib.Path(os.path.normpath(os.path.join(getModelPath(sub), sub)))
    except OSError:
        return None


@functools.lru_cache(maxsize=1)
def _erd_arm_names() -> tuple[str, ...]:
    try:
        from example_robot_data.robots_loader import ROBOTS
    except ImportError:  # pragma: no cover
        return ()
    return tuple(sorted(n for n, cls in ROBOTS.items()
                        if getattr(cls, "urdf_filename", "") and not getattr(cls, "free_flyer", False)))


def available_robots() -> tuple[str, ...]:
    """Names accepted by :func:`load_robot`: the packaged arms, then example-robot-data's
    fixed-base robots."""
    return _PACKAGE_ROBOTS + _erd_arm_names()


def _unknown(name: str) -> ValueError:
    erd = _erd_arm_names()
    return ValueError(
        f"unknown robot '{name}'; available: {', '.join(_PACKAGE_ROBOTS)} (packaged URDFs) and the "
        f"fixed-base robots of example-robot-data: {', '.join(erd) if erd else '(not installed)'}")


def urdf_path(name: str) -> pathlib.Path:
    """Path of the URDF file of robot ``name`` (a real file, also for installed packages).

    Raises
    ------
    ValueError
        Unknown name; the message lists the available ones.
    """
    if name in _PACKAGE_ROBOTS:
        return _packaged_urdf(name)
    loader = _erd_loader(name)
    if loader is None or not getattr(loader, "urdf_filename", ""):
        raise _unknown(name)
    return _erd_urdf(loader)


# ----------------------------------------------------------------------------------------------
# Per-robot data that a URDF cannot hold
# ----------------------------------------------------------------------------------------------
class _Extras(NamedTuple):
    ee_frame: str | None = None
    home: tuple[float, ...] | None = None
    acceleration: tuple[float, ...] | None = None
    jerk: tuple[float, ...] | None = None
    control_rate_hz: float = 1000.0
    lock: tuple[str, ...] | None = None  # None: lock joints whose name has "finger" or "gripper"
    source: str = ""


_UR_HOME = (0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0)
_UR = _Extras(ee_frame="tool0", home=_UR_HOME, control_rate_hz=500.0,
              source="URDF limits; UR control rate 500 Hz (e-Series); acceleration/jerk defaults")
_PANDA = _Extras(
    ee_frame="panda_hand_tcp",
    # Franka Emika, libfranka rate_limiting.h: kMaxJointAcceleration, kMaxJointJerk.
    acceleration=(15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0),
    jerk=(7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0),
    control_rate_hz=1000.0,
    source="URDF position/velocity/effort; acceleration/jerk: libfranka kMaxJointAcceleration/Jerk")

_EXTRAS: dict[str, _Extras] = {
    "gen3_lite": _Extras(
        ee_frame="tool_frame",
        # Chosen ready pose: tool_frame at (0.30, 0.00, 0.25) m pointing down, every joint >= 1 rad
        # from its limits. Not a manufacturer figure.
        home=(-0.16, -0.19, 1.51, 1.57, 1.44, -0.16),
        # Kinova ros2_kortex kortex_description/arms/gen3_lite/6dof/config/joint_limits.yaml.
        acceleration=(1.0, 0.5, 0.4, 1.0, 10.0, 10.0),
        # No published jerk limit: DEFAULT_JERK_PER_ACCELERATION x acceleration.
        jerk=tuple(DEFAULT_JERK_PER_ACCELERATION * a for a in (1.0, 0.5, 0.4, 1.0, 10.0, 10.0)),
        # Kinova's Gen3 lite ros2_control configuration runs the controllers at 1000 Hz.
        control_rate_hz=1000.0,
        lock=(),
        source="gen3_lite.urdf (Kinova kortex_description); acceleration: Kinova ros2 "
               "joint_limits.yaml; jerk: 10 x acceleration (default)"),
    "wam": _Extras(
        ee_frame="wam_tool_plate",
        # Chosen ready pose: tool plate at (0.52, 0.00, 0.53) m pointing down. (Barrett's own "home"
        # (0, -1.9, 0, 3.14, 0, 0, 0) is the folded rest pose against the J4 stop.)
        home=(0.0, 0.5, 0.0, 2.0, 0.0, 0.6, 0.0),
        # libbarrett runs the WAM's real-time control loop at 500 Hz.
        control_rate_hz=500.0,
        lock=(),
        source="wam.urdf (Barrett WAM manual DH and limits, OpenRAVE velocity/torque); "
               "acceleration/jerk defaults"),
    "panda": _PANDA,
    "panda_collision": _PANDA,
    "ur3": _UR, "ur3_limited": _UR, "ur3_gripper": _UR,
    "ur5": _UR, "ur5_limited": _UR, "ur5_gripper": _UR,
    "ur10": _UR, "ur10_limited": _UR,
    "kinova": _Extras(ee_frame="j2s6s200_end_effector", control_rate_hz=100.0,
                      source="URDF limits; Kinova JACO2 API runs at 100 Hz; acceleration/jerk defaults"),
    "z1": _Extras(ee_frame="gripperStator"),
}


# ----------------------------------------------------------------------------------------------
# Pinocchio model building (shared by load_robot and RobotKinematics)
# ----------------------------------------------------------------------------------------------
class _JointInfo(NamedTuple):
    name: str
    joint_id: int
    idx_q: int
    idx_v: int
    continuous: bool  # stored as (cos, sin) in Pinocchio


def _classify_joint(model: pin.Model, jid: int, robot: str) -> _JointInfo:
    j = model.joints[jid]
    name = model.names[jid]
    if j.nq == 1 and j.nv == 1:
        return _JointInfo(name, jid, j.idx_q, j.idx_v, False)
    if j.nq == 2 and j.nv == 1:  # revolute unbounded (continuous)
        return _JointInfo(name, jid, j.idx_q, j.idx_v, True)
    raise ValueError(
        f"robot '{robot}': joint '{name}' is a {j.shortname()} (nq={j.nq}, nv={j.nv}); only "
        f"revolute, prismatic and continuous joints are supported")


@functools.lru_cache(maxsize=32)
def _full_model(path: str) -> pin.Model:
    model = pin.buildModelFromUrdf(path)
    model.gravity.linear = np.array([0.0, 0.0, -GRAVITY])
    return model


def _reference_q(model: pin.Model, loader) -> np.ndarray:
    """Reference posture of an example-robot-data robot (SRDF), else the neutral one."""
    q = pin.neutral(model)
    srdf = _erd_srdf(loader) if loader is not None else None
    ref = getattr(loader, "ref_posture", None) if loader is not None else None
    if srdf is not None and ref:
        m = model.copy()
        try:
            pin.loadReferenceConfigurations(m, str(srdf), False)
            if ref in m.referenceConfigurations:
                q = np.array(m.referenceConfigurations[ref], dtype=np.float64)
        except (RuntimeError, ValueError):  # malformed SRDF: keep the neutral posture
            pass
    return q


def _angle(qpin: np.ndarray, info: _JointInfo) -> float:
    if info.continuous:
        return math.atan2(qpin[info.idx_q + 1], qpin[info.idx_q])
    return float(qpin[info.idx_q])


def _default_ee_frame(model: pin.Model, last_joint: int) -> str:
    """Last body frame rigidly attached to the last controlled joint (in URDF order)."""
    best = None
    for fr in model.frames:
        if fr.type == pin.FrameType.BODY and fr.parentJoint == last_joint:
            best = fr.name
    if best is None:
        best = model.frames[-1].name
    return best


def _build_spec(name: str, path: pathlib.Path, loader) -> RobotSpec:
    model = _full_model(str(path))
    extras = _EXTRAS.get(name, _Extras(source="URDF limits; acceleration/jerk defaults"))
    infos = [_classify_joint(model, jid, name) for jid in range(1, model.njoints)]
    if extras.lock is None:
        lock_names = {i.name for i in infos
                      if "finger" in i.name.lower() or "gripper" in i.name.lower()}
    else:
        lock_names = set(extras.lock)
    arm = [i for i in infos if i.name not in lock_names]
    if not arm:
        raise ValueError(f"robot '{name}': no controllable joint left after locking {sorted(lock_names)}")
    qref = _reference_q(model, loader)
    locked = tuple((i.name, _angle(qref, i)) for i in infos if i.name in lock_names)

    lower, upper = [], []
    for i in arm:
        if i.continuous:
            lower.append(-np.inf)
            upper.append(np.inf)
        else:
            lower.append(model.lowerPositionLimit[i.idx_q])
            upper.append(model.upperPositionLimit[i.idx_q])
    lower, upper = np.array(lower), np.array(upper)
    velocity = np.array([model.velocityLimit[i.idx_v] for i in arm])
    effort = np.array([model.effortLimit[i.idx_v] for i in arm])
    if not np.all(np.isfinite(velocity) & (velocity > 0)):
        bad = [i.name for i, v in zip(arm, velocity) if not (np.isfinite(v) and v > 0)]
        raise ValueError(f"robot '{name}': the URDF gives no positive velocity limit for "
                         f"{', '.join(bad)}; expected <limit velocity=...> on every controlled joint")
    acceleration = (np.array(extras.acceleration) if extras.acceleration is not None
                    else DEFAULT_ACCELERATION_PER_VELOCITY * velocity)
    jerk = (np.array(extras.jerk) if extras.jerk is not None
            else DEFAULT_JERK_PER_ACCELERATION * acceleration)
    if extras.home is not None:
        home = np.array(extras.home, dtype=np.float64)
    else:
        home = np.array([_angle(qref, i) for i in arm])
        # A neutral posture may sit outside the limits (e.g. a joint limited to [0.1, 2]).
        home = np.clip(home, lower, upper)
    ee = extras.ee_frame or _default_ee_frame(model, arm[-1].joint_id)
    if not model.existFrame(ee):
        raise ValueError(f"robot '{name}': end-effector frame '{ee}' is not in {path}")
    return RobotSpec(
        name=name, urdf_path=path, joint_names=tuple(i.name for i in arm),
        lower=lower, upper=upper, velocity=velocity, acceleration=acceleration, jerk=jerk,
        effort=effort, control_rate_hz=extras.control_rate_hz, ee_frame=ee, home=home,
        locked_joints=locked, limits_source=extras.source)


def load_robot(name: str) -> RobotSpec:
    """Specification of robot ``name``.

    Parameters
    ----------
    name : str
        ``"gen3_lite"``, ``"wam"``, or the loader name of a fixed-base example-robot-data robot
        (``"panda"``, ``"ur5"``, ...; see :func:`available_robots`).

    Returns
    -------
    RobotSpec
        For example-robot-data robots: position, velocity and effort limits from the URDF;
        acceleration = :data:`DEFAULT_ACCELERATION_PER_VELOCITY` × velocity and jerk =
        :data:`DEFAULT_JERK_PER_ACCELERATION` × acceleration unless listed in this module
        (panda: libfranka's limits); joints named ``*finger*`` / ``*gripper*`` are locked at the
        SRDF reference posture; home = that posture (UR arms: (0, -π/2, π/2, -π/2, -π/2, 0));
        end-effector frame from a table here, else the last body on the last controlled joint.

    Raises
    ------
    ValueError
        Unknown name (the message lists the available ones), a floating-base robot, or a robot
        with joints other than revolute / prismatic / continuous.
    """
    if not isinstance(name, str):
        raise ValueError(f"robot name must be a string; got {name!r}")
    if name in _PACKAGE_ROBOTS:
        return _build_spec(name, _packaged_urdf(name), None)
    loader = _erd_loader(name)
    if loader is None:
        raise _unknown(name)
    if getattr(loader, "free_flyer", False):
        raise ValueError(f"robot '{name}' of example-robot-data has a floating base; only fixed-base "
                         f"arms are supported: {', '.join(available_robots())}")
    if not getattr(loader, "urdf_filename", ""):
        raise ValueError(f"robot '{name}' of example-robot-data has no URDF; choose one of "
                         f"{', '.join(available_robots())}")
    return _build_spec(name, _erd_urdf(loader), loader)


def links_without_inertial(path: str | os.PathLike) -> frozenset[str]:
    """Links of a URDF that have no ``<inertial>`` element (massless for Pinocchio; PyBullet would
    give them 1 kg)."""
    root = ET.parse(str(path)).getroot()
    return frozenset(link.get("name") for link in root.iter("link") if link.find("inertial") is None)


# ----------------------------------------------------------------------------------------------
# Kinematics and dynamics
# ----------------------------------------------------------------------------------------------
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
        return np.array(pin.Quaternion(self.rotation).coeffs(), dtype=np.float64)


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
        full = _full_model(str(spec.urdf_path))
        locked = dict(spec.locked_joints)
        if locked:
            qlock = pin.neutral(full)
            lock_ids = []
            for jname, value in locked.items():
                if not full.existJointName(jname):
                    raise ValueError(f"robot '{spec.name}': locked joint '{jname}' is not in {spec.urdf_path}")
                info = _classify_joint(full, full.getJointId(jname), spec.name)
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
            infos.append(_classify_joint(model, model.getJointId(jname), spec.name))
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
