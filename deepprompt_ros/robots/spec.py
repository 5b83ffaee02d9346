"""Robot descriptions: joint limits and URDF files (:func:`load_robot` makes a :class:`RobotSpec`).

Two arms ship with the package as URDF files written from the manufacturers' published numbers
(``deepprompt_ros/resources/urdf``; every number is cited in the file; :func:`_packaged_urdf`
finds them):

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
function here takes and returns plain joint angles. Kinematics and dynamics of a spec:
:class:`~deepprompt_ros.robots.kinematics.RobotKinematics`.

Length: over 400 lines because the spec and the one function that makes it belong together: a
:class:`RobotSpec` (about 200 lines of validated limits) is only ever built by :func:`load_robot`
from a URDF read with Pinocchio plus the table of what a URDF cannot hold (home pose, end-effector
frame, acceleration / jerk limits, control rate) — the table and the reading are the other half.
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
from typing import NamedTuple

import numpy as np
import pinocchio as pin

from deepprompt_ros.common.joints import joint_list_text

__all__ = [
    "GRAVITY",
    "DEFAULT_ACCELERATION_PER_VELOCITY",
    "DEFAULT_JERK_PER_ACCELERATION",
    "RobotSpec",
    "JointInfo",
    "available_robots",
    "load_robot",
    "urdf_path",
    "links_without_inertial",
    "classify_joint",
    "urdf_model",
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
                    f"per joint ({joint_list_text(self.joint_names)})")
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
        return joint_list_text(self.joint_names)

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
# Pinocchio model building (shared by load_robot and robots.kinematics.RobotKinematics)
# ----------------------------------------------------------------------------------------------
class JointInfo(NamedTuple):
    """One joint of a Pinocchio model: its name, index and positions in q (``idx_q``) and v (``idx_v``)."""

    name: str
    joint_id: int
    idx_q: int
    idx_v: int
    continuous: bool  # stored as (cos, sin) in Pinocchio


def classify_joint(model: pin.Model, jid: int, robot: str) -> JointInfo:
    """:class:`JointInfo` of joint ``jid``; ValueError for joints other than revolute, prismatic and
    continuous (``robot`` names the robot in the message)."""
    j = model.joints[jid]
    name = model.names[jid]
    if j.nq == 1 and j.nv == 1:
        return JointInfo(name, jid, j.idx_q, j.idx_v, False)
    if j.nq == 2 and j.nv == 1:  # revolute unbounded (continuous)
        return JointInfo(name, jid, j.idx_q, j.idx_v, True)
    raise ValueError(
        f"robot '{robot}': joint '{name}' is a {j.shortname()} (nq={j.nq}, nv={j.nv}); only "
        f"revolute, prismatic and continuous joints are supported")


@functools.lru_cache(maxsize=32)
def urdf_model(path: str) -> pin.Model:
    """Pinocchio model of a URDF file with gravity :data:`GRAVITY` along -z (cached per path; do not
    modify it: copy it)."""
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


def _angle(qpin: np.ndarray, info: JointInfo) -> float:
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
    model = urdf_model(str(path))
    extras = _EXTRAS.get(name, _Extras(source="URDF limits; acceleration/jerk defaults"))
    infos = [classify_joint(model, jid, name) for jid in range(1, model.njoints)]
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
