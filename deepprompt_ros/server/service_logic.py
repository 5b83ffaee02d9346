"""ROS-free logic of the primitive server: parameters, primitive loading, request validation,
conditioning / blending / sampling, and execution planning.

The ROS node (:mod:`deepprompt_ros.ros.primitive_server`) converts messages to the plain
request types below (:mod:`deepprompt_ros.ros.conversions`), calls :class:`PrimitiveServerCore`,
and converts the results back. Every invalid request raises :class:`RequestError` carrying a
:class:`Code` (the values of ``deepprompt_msgs/msg/ResultCode``) and a message that says what was
wrong and what is expected; nothing here needs rclpy.

Parameters are declared once, as the fields of :class:`ServerConfig` (type, default,
description, range or choices); the node declares its ROS parameters from
:data:`PARAMETERS` and :func:`parameters_markdown` renders the documentation table.
"""
from __future__ import annotations

import dataclasses
import enum
import math
import pathlib
import re
from typing import TYPE_CHECKING, Any, Callable, Mapping, NamedTuple, Sequence

import numpy as np

from deepprompt_ros.server.handles import (BlendedLatent, ConditionedLatent, HandleLimitError, HandleStore, Schedule,
                      StoredDistribution, UnknownHandleError)
from deepprompt_ros.execution.limits import JointLimits
from deepprompt_ros.execution.phase_clock import PhaseClock

if TYPE_CHECKING:  # imported where models are loaded: parameters are checked without torch
    from deepprompt_ros.primitive.deep_promp import DeepProMP

__all__ = [
    "Code", "RequestError", "ConfigError", "ParamSpec", "ServerConfig", "PARAMETERS",
    "parameters_markdown", "PrimitiveEntry", "LoadedPrimitive", "read_primitives_file",
    "load_primitive", "load_primitives", "robot_limits", "ViaPointIn", "ImageIn", "ContextIn",
    "ConditionRequest", "BlendRequest", "SampleRequest", "ExecuteRequest", "Preview",
    "ConditionResult", "BlendResult", "SampleResult", "PrimitiveDescription", "decode_image",
    "ExecutionReference", "ExecutionPlan", "PrimitiveServerCore",
]


class Code(enum.IntEnum):
    """Result codes; the same values as the constants of ``deepprompt_msgs/msg/ResultCode``."""

    SUCCESS = 0
    INVALID_REQUEST = 1
    UNKNOWN_PRIMITIVE = 2
    UNKNOWN_HANDLE = 3
    INVALID_VIA_POINT = 4
    INVALID_CONTEXT = 5
    INVALID_IMAGE = 6
    REFINEMENT_UNREACHABLE = 7
    HANDLE_LIMIT = 8
    ROBOT_STATE_STALE = 9
    LIMIT_VIOLATION = 10
    CANCELED = 11
    PREEMPTED = 12
    NO_ACTIVE_EXECUTION = 13
    RECORDING_ACTIVE = 14
    NOT_RECORDING = 15
    INTERNAL_ERROR = 99


class RequestError(Exception):
    """A request that cannot be carried out: ``code`` and an actionable ``message``."""

    def __init__(self, code: Code, message: str):
        super().__init__(message)
        self.code = Code(code)
        self.message = message


class ConfigError(ValueError):
    """Invalid server parameters or primitives file; the message lists every problem."""


# =================================================================================================
# Parameters: declared once (generate_parameter_library style)
# =================================================================================================
def _param(default, description: str, *, min=None, max=None, choices=None, unit: str = ""):
    return dataclasses.field(default=default, metadata={
        "description": description, "min": min, "max": max, "choices": choices, "unit": unit})


@dataclasses.dataclass(frozen=True)
class ServerConfig:
    """Parameters of the primitive server (ROS parameters of the same names).

    Every field is one parameter: its annotation is the type, its default the default, and its
    metadata the description and the valid range (inclusive) or the allowed choices.
    """

    # -- robot and primitives
    robot: str = _param("gen3_lite", "Robot whose joint names and limits are used (core.robots.load_robot: "
                        "'gen3_lite', 'wam' or an example-robot-data arm). Position limits come from its URDF.")
    primitives_file: str = _param("", "YAML file listing the primitives to serve; '' = config/primitives.yaml "
                                  "of the package (installed share folder first, then the source tree).")
    models_dir: str = _param("", "Folder of relative model paths in the primitives file; '' = the package's "
                             "models/ folders (installed share first, then the source tree).")
    # -- control loop
    control_rate_hz: float = _param(0.0, "Rate of the phase clock and of the command stream; 0 = the robot's "
                                    "control rate (1000 Hz for the Gen3 lite).", min=0.0, max=10000.0, unit="Hz")
    loop_mode: str = _param("thread", "Pacing of the control loop: 'thread' (dedicated thread, absolute "
                            "perf_counter deadlines) or 'timer' (ROS timer in its own callback group).",
                            choices=("thread", "timer"))
    spin_wait: float = _param(0.0, "'thread' mode: busy-wait this long before each deadline instead of "
                              "sleeping (sleep overshoot is ~60 us on Linux); 0 = sleep only. The busy wait "
                              "burns CPU and holds the interpreter lock; on a loaded 2-core machine 0.2 ms "
                              "gave the same p99 period error as 0.",
                              min=0.0, max=0.01, unit="s")
    gil_switch_interval: float = _param(0.0002, "sys.setswitchinterval of the node process: the longest "
                                        "another Python thread keeps the interpreter lock while the control "
                                        "loop waits for it (Python's default is 0.005 s).",
                                        min=1e-5, max=0.1, unit="s")
    realtime_priority: int = _param(50, "SCHED_FIFO priority of the control thread ('thread' mode; with "
                                    "loop_process, of every thread of the control process, so that none "
                                    "holding the interpreter lock is preempted by another process); 0 = normal "
                                    "scheduling. Needs CAP_SYS_NICE (root, or rtprio in limits.conf); refused "
                                    "-> a warning, normal scheduling (as ros2_control's controller_manager).",
                                    min=0, max=99)
    control_cpu: int = _param(-1, "loop_process: pin the control process (all its threads) to this CPU "
                              "(os.sched_setaffinity, like ros2_control's cpu_affinity); -1 = any CPU. A CPU "
                              "the machine does not have -> a warning, not pinned.", min=-1, max=1023)
    loop_process: bool = _param(True, "'thread' mode: run the control loop (command stream, JointTrajectory "
                                "output, joint_states reader) in a child process with its own interpreter, "
                                "so that service handlers and the 1 kHz loop do not share one interpreter "
                                "lock; false = a thread of the server's process. 'timer' mode is always "
                                "in-process.")
    velocity_scale: float = _param(1.0, "Fraction of the robot's velocity limits used.", min=1e-3, max=1.0)
    acceleration_scale: float = _param(1.0, "Fraction of the robot's acceleration limits used.", min=1e-3, max=1.0)
    jerk_scale: float = _param(1.0, "Fraction of the robot's jerk limits used.", min=1e-3, max=1.0)
    position_margin: float = _param(0.01, "Targets are kept this far inside the URDF position limits.",
                                    min=0.0, max=0.5, unit="rad")
    tracking_horizon: float = _param(0.01, "Look-ahead of the Ruckig tracking of the primitive.",
                                     min=0.001, max=0.5, unit="s")
    lookahead_ticks: int = _param(30, "The command stream is computed this many control periods ahead; the "
                                  "JointTrajectory messages carry these future samples (and the reaction time "
                                  "to cancel / SetPhaseRate / a new goal is this long).", min=1, max=2000)
    approach_tolerance: float = _param(0.01, "Farther than this (max over joints) from the primitive's start, "
                                       "the robot first moves to the start (time-optimal, within limits) and "
                                       "then starts the phase clock.", min=0.0, max=10.0, unit="rad")
    execution_grid_points: int = _param(4001, "The executed mean trajectory is decoded once per Execute on this "
                                        "many phases and interpolated at every control tick.", min=101, max=200001)
    derivative_step: float = _param(0.005, "Phase step of the central differences that give the reference "
                                    "velocity and acceleration from the decoded grid.", min=1e-4, max=0.1)
    phase_rate_ramp_time: float = _param(0.2, "SetPhaseRate changes the phase rate linearly over this time "
                                         "(continuous phase velocity).", min=0.0, max=60.0, unit="s")
    stale_timeout: float = _param(0.2, "No joint_states for this long: execution stops (brakes) with "
                                  "ROBOT_STATE_STALE; Execute is refused if the last message is older.",
                                  min=0.001, max=60.0, unit="s")
    max_tracking_error: float = _param(0.0, "Abort with LIMIT_VIOLATION (braking) when |commanded - measured| "
                                       "exceeds this on any joint; 0 = no bound.", min=0.0, max=10.0, unit="rad")
    check_feasibility: bool = _param(True, "Refuse Execute / SetPhaseRate (LIMIT_VIOLATION) when the mean "
                                     "trajectory leaves the position limits or needs more than the velocity "
                                     "limits at the requested phase rate.")
    default_duration: float = _param(5.0, "Execute duration when the goal sets neither duration nor phase_rate "
                                      "(a primitive's own default in the primitives file wins).",
                                      min=0.01, max=86400.0, unit="s")
    feedback_rate_hz: float = _param(20.0, "Rate of Execute feedback messages.", min=0.1, max=1000.0, unit="Hz")
    # -- outputs
    joint_states_topic: str = _param("joint_states", "sensor_msgs/JointState input (measured robot state).")
    controller: str = _param("joint_trajectory_controller", "JointTrajectory output goes to "
                             "'<controller>/joint_trajectory'; '' = no JointTrajectory output.")
    command_topic: str = _param("joint_command", "sensor_msgs/JointState per control tick (names, positions, "
                                "velocities in the robot's joint order; what sim_bridge follows); '' = off.")
    trajectory_rate_hz: float = _param(50.0, "Rate of JointTrajectory messages.", min=1.0, max=1000.0, unit="Hz")
    trajectory_points: int = _param(3, "Points of the look-ahead in each JointTrajectory message (evenly spaced "
                                     "over lookahead_ticks); a braking tail to rest follows them.", min=1, max=100)
    trajectory_stamp: str = _param("now", "header.stamp of JointTrajectory messages: 'now' (the time of the "
                                   "first sample, exact timing) or 'zero' (start on receipt).",
                                   choices=("now", "zero"))
    # -- handles and request bounds
    max_handles: int = _param(64, "Number of stored conditioned distributions.", min=1, max=100000)
    handle_ttl: float = _param(600.0, "A handle unused for this long is dropped; 0 = never.",
                               min=0.0, max=1e7, unit="s")
    evict_when_full: bool = _param(True, "Full store: drop the least recently used handle (true) or refuse "
                                   "with HANDLE_LIMIT (false).")
    preview_points: int = _param(100, "Default number of preview / sample phases.", min=2, max=100000)
    max_preview_points: int = _param(10000, "Largest preview_points / n_points accepted.", min=2, max=1000000)
    preview_std_method: str = _param("linearized", "Standard deviation of the preview: 'linearized' (first "
                                     "order in z: |∂μ_y/∂z| σ_z at the mean latent, exact where the decoder is "
                                     "linear in z, ~1 ms) or 'sampled' (Monte Carlo over preview_std_samples "
                                     "trajectories, ~4 ms for a 128-unit decoder). Blended handles are always "
                                     "sampled.", choices=("linearized", "sampled"))
    preview_std_samples: int = _param(32, "Monte-Carlo trajectories behind a sampled standard deviation.",
                                      min=2, max=10000)
    preview_std_points: int = _param(26, "The preview's standard deviation is estimated at this many evenly "
                                     "spaced phases (at most preview_points) and interpolated linearly in "
                                     "between (it varies slowly with the phase).", min=2, max=100000)
    max_via_points: int = _param(1000, "Largest number of via-points (and blending-schedule knots) accepted.",
                                 min=1, max=1000000)
    max_images: int = _param(16, "Largest number of images in one image context.", min=1, max=1000)
    max_samples: int = _param(1000, "Largest Sample.n_samples accepted.", min=1, max=1000000)
    max_sample_values: int = _param(5000000, "Largest n_samples x n_points x joints of one Sample response.",
                                    min=1000, max=100000000)
    refine_max_iterations: int = _param(200, "Default refinement iteration budget (Condition."
                                        "refine_max_iterations = 0).", min=1, max=10000)
    refine_tolerance: float = _param(1e-6, "Default refinement tolerance on the via-point error.",
                                     min=1e-12, max=1.0, unit="rad")
    max_cycles: int = _param(100000, "Largest Execute.cycles accepted (rhythmic primitives).", min=1, max=10**9)

    def __post_init__(self):
        errors = [err for f in dataclasses.fields(self)
                  if (err := _check_param(PARAM_SPECS[f.name], getattr(self, f.name)))]
        if errors:
            raise ConfigError("invalid parameters:\n  " + "\n  ".join(errors))

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> "ServerConfig":
        """Build from {name: value}; unknown names and invalid values are all reported at once."""
        unknown = sorted(set(values) - set(PARAM_SPECS))
        errors = [f"unknown parameter '{n}'; known: {', '.join(sorted(PARAM_SPECS))}" for n in unknown]
        ok = {}
        for name, value in values.items():
            if name in PARAM_SPECS:
                err = _check_param(PARAM_SPECS[name], value)
                if err:
                    errors.append(err)
                else:
                    ok[name] = _coerce(PARAM_SPECS[name], value)
        if errors:
            raise ConfigError("invalid parameters:\n  " + "\n  ".join(errors))
        return cls(**ok)


class ParamSpec(NamedTuple):
    """One parameter: name, type ('bool', 'int', 'double', 'string'), default, description,
    inclusive range (min, max; None = unbounded), choices (strings) and unit."""

    name: str
    type: str
    default: Any
    description: str
    min: float | None
    max: float | None
    choices: tuple[str, ...] | None
    unit: str


_TYPE_NAMES = {"bool": "bool", "int": "int", "float": "double", "str": "string"}

PARAMETERS: tuple[ParamSpec, ...] = tuple(
    ParamSpec(f.name, _TYPE_NAMES[f.type if isinstance(f.type, str) else f.type.__name__], f.default,
              f.metadata["description"], f.metadata["min"], f.metadata["max"], f.metadata["choices"],
              f.metadata["unit"])
    for f in dataclasses.fields(ServerConfig))
PARAM_SPECS = {p.name: p for p in PARAMETERS}


def _coerce(spec: ParamSpec, value):
    if spec.type == "double":
        return float(value)
    if spec.type == "int":
        return int(value)
    return value


def _check_param(spec: ParamSpec, value) -> str:
    """'' if ``value`` is valid for ``spec``, else a message saying what is expected."""
    want = {"bool": "a bool", "int": "an integer", "double": "a number", "string": "a string"}[spec.type]
    if spec.type == "bool":
        ok = isinstance(value, (bool, np.bool_))
    elif spec.type == "int":
        ok = isinstance(value, (int, np.integer)) and not isinstance(value, bool)
    elif spec.type == "double":
        ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
    else:
        ok = isinstance(value, str)
    if not ok:
        return f"{spec.name} = {value!r}: expected {want}"
    if spec.type in ("int", "double"):
        v = float(value)
        if not math.isfinite(v):
            return f"{spec.name} = {value!r}: expected a finite number"
        lo = -math.inf if spec.min is None else spec.min
        hi = math.inf if spec.max is None else spec.max
        if not lo <= v <= hi:
            return f"{spec.name} = {value!r}{' ' + spec.unit if spec.unit else ''}: expected a value in [{lo:g}, {hi:g}]"
    if spec.choices is not None and value not in spec.choices:
        return f"{spec.name} = {value!r}: expected one of {', '.join(repr(c) for c in spec.choices)}"
    return ""


def parameters_markdown() -> str:
    """Markdown table of every parameter (name, type, default, range, description)."""
    rows = ["| parameter | type | default | range | description |", "|---|---|---|---|---|"]
    for p in PARAMETERS:
        if p.choices:
            rng = " / ".join(f"`{c}`" for c in p.choices)
        elif p.min is not None or p.max is not None:
            rng = f"[{p.min:g}, {p.max:g}]" + (f" {p.unit}" if p.unit else "")
        else:
            rng = ""
        default = f"`{p.default!r}`" if p.type == "string" else f"`{p.default}`"
        rows.append(f"| `{p.name}` | {p.type} | {default} | {rng} | {p.description} |")
    return "\n".join(rows)


# =================================================================================================
# Primitives file and model loading
# =================================================================================================
_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,63}$")


@dataclasses.dataclass(frozen=True)
class PrimitiveEntry:
    """One entry of the primitives file.

    Attributes
    ----------
    name : str
        Name clients use (letters, digits, '_'; starts with a letter).
    model : str
        Model file, absolute or relative to the models folder.
    description : str
    default_duration : float
        Execute duration when the goal sets none; 0 = the server's default_duration.
    """

    name: str
    model: str
    description: str = ""
    default_duration: float = 0.0


_ENTRY_KEYS = {f.name for f in dataclasses.fields(PrimitiveEntry)}


def read_primitives_file(path) -> tuple[list[PrimitiveEntry], list[str]]:
    """Parse the primitives YAML::

        primitives:
          - name: reach
            model: gen3_lite_reach.safetensors
            description: Reach an object (context 'object' = its position)
            default_duration: 5.0

    Returns
    -------
    entries : list of PrimitiveEntry
        The valid entries.
    errors : list of str
        One message per invalid entry (the entry is skipped).

    Raises
    ------
    ConfigError
        The file is missing, not YAML, or has no ``primitives`` list.
    """
    import yaml

    path = pathlib.Path(path)
    try:
        raw = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"primitives file '{path}' does not exist; set the parameter primitives_file") from None
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"primitives file '{path}' is not readable YAML: {exc}") from None
    if not isinstance(raw, dict) or not isinstance(raw.get("primitives"), list):
        raise ConfigError(f"primitives file '{path}' must be a mapping with a list 'primitives: [{{name, model, "
                          f"description, default_duration}}, ...]'; got {type(raw).__name__}")
    entries, errors, seen = [], [], set()
    for i, item in enumerate(raw["primitives"]):
        where = f"{path.name}: primitives[{i}]"
        if not isinstance(item, dict):
            errors.append(f"{where} must be a mapping with keys name, model; got {item!r}")
            continue
        unknown = sorted(set(item) - _ENTRY_KEYS)
        name = item.get("name")
        if unknown:
            errors.append(f"{where} ({name!r}) has unknown keys {unknown}; allowed: {sorted(_ENTRY_KEYS)}")
            continue
        if not isinstance(name, str) or not _NAME_RE.match(name):
            errors.append(f"{where}: name {name!r} is invalid; expected letters, digits and '_', starting "
                          "with a letter (at most 64 characters)")
            continue
        if name in seen:
            errors.append(f"{where}: primitive name '{name}' appears twice; names must be unique")
            continue
        model = item.get("model")
        if not isinstance(model, str) or not model:
            errors.append(f"{where} ('{name}'): model must be a file name or path; got {model!r}")
            continue
        desc = item.get("description", "")
        dur = item.get("default_duration", 0.0)
        if not isinstance(desc, str):
            errors.append(f"{where} ('{name}'): description must be a string")
            continue
        if isinstance(dur, bool) or not isinstance(dur, (int, float)) or not (math.isfinite(dur) and 0 <= dur <= 86400):
            errors.append(f"{where} ('{name}'): default_duration {dur!r} must be a number of seconds in "
                          "(0, 86400], or 0 for the server default")
            continue
        seen.add(name)
        entries.append(PrimitiveEntry(name, model, desc, float(dur)))
    return entries, errors


@dataclasses.dataclass(frozen=True)
class LoadedPrimitive:
    """A servable primitive.

    Attributes
    ----------
    entry : PrimitiveEntry
    model : DeepProMP
    path : pathlib.Path
    robot_index : array of int, shape (d,)
        Model joint j is robot joint ``robot_index[j]``.
    """

    entry: PrimitiveEntry
    model: DeepProMP
    path: pathlib.Path
    robot_index: np.ndarray

    @property
    def name(self) -> str:
        return self.entry.name

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.model.joint_names

    def to_robot_order(self, y: np.ndarray) -> np.ndarray:
        """Positions (..., d) in model joint order -> robot joint order."""
        out = np.empty_like(y)
        out[..., self.robot_index] = y
        return out


def load_primitive(entry: PrimitiveEntry, robot_joint_names: Sequence[str],
                   resolve: Callable[[str], pathlib.Path]) -> LoadedPrimitive:
    """Load one model and check it against the robot; ValueError/FileNotFoundError say why not."""
    from deepprompt_ros.primitive.deep_promp import DeepProMP

    path = resolve(entry.model)
    model = DeepProMP.from_checkpoint(str(path), name=entry.name)
    robot = tuple(robot_joint_names)
    if set(model.joint_names) != set(robot) or len(model.joint_names) != len(robot):
        missing = [j for j in robot if j not in model.joint_names]
        extra = [j for j in model.joint_names if j not in robot]
        raise ValueError(
            f"primitive '{entry.name}' ({path.name}) has {len(model.joint_names)} joints "
            f"[{', '.join(model.joint_names)}] but the robot has {len(robot)} joints [{', '.join(robot)}]"
            + (f"; missing: {', '.join(missing)}" if missing else "")
            + (f"; not on the robot: {', '.join(extra)}" if extra else "")
            + "; a primitive must drive exactly the robot's joints")
    index = np.array([robot.index(j) for j in model.joint_names], dtype=int)
    return LoadedPrimitive(entry, model, path, index)


def load_primitives(entries: Sequence[PrimitiveEntry], robot_joint_names: Sequence[str],
                    resolve: Callable[[str], pathlib.Path]) -> tuple[dict[str, LoadedPrimitive], list[str]]:
    """Load every entry that is valid; (primitives by name, one error message per refused entry)."""
    out, errors = {}, []
    for e in entries:
        try:
            out[e.name] = load_primitive(e, robot_joint_names, resolve)
        except (ValueError, FileNotFoundError, OSError) as exc:
            errors.append(f"primitive '{e.name}' refused: {exc}")
    return out, errors


def robot_limits(spec, config: ServerConfig) -> JointLimits:
    """JointLimits in the robot's joint order from a RobotSpec (URDF position limits) and the
    velocity / acceleration / jerk scales of ``config``."""
    return JointLimits(lower=spec.lower, upper=spec.upper,
                       max_velocity=np.asarray(spec.velocity) * config.velocity_scale,
                       max_acceleration=np.asarray(spec.acceleration) * config.acceleration_scale,
                       max_jerk=np.asarray(spec.jerk) * config.jerk_scale, names=spec.joint_names)


# =================================================================================================
# Plain request / result types
# =================================================================================================
class ViaPointIn(NamedTuple):
    """Via-point as received: positions (d,), joint_mask (0 or d,) bool, weight used iff use_weight."""

    phase: float
    positions: np.ndarray
    joint_mask: np.ndarray
    use_weight: bool = False
    weight: float = 1.0


class ImageIn(NamedTuple):
    """sensor_msgs/Image fields; data is the raw byte buffer as uint8, shape (len,)."""

    height: int
    width: int
    encoding: str
    step: int
    data: np.ndarray


class ContextIn(NamedTuple):
    modality: str
    values: np.ndarray
    images: tuple = ()
    use_weight: bool = False
    weight: float = 1.0


@dataclasses.dataclass(frozen=True)
class ConditionRequest:
    primitive: str
    via_points: Sequence[ViaPointIn] = ()
    contexts: Sequence[ContextIn] = ()
    refine: bool = False
    refine_max_iterations: int = 0
    refine_tolerance: float = 0.0
    preview_points: int = 0


@dataclasses.dataclass(frozen=True)
class BlendRequest:
    handle_a: str
    handle_b: str
    schedule_phases: Sequence[float] = ()
    schedule_weights: Sequence[float] = ()
    preview_points: int = 0
    sample: bool = False
    seed: int = 0


@dataclasses.dataclass(frozen=True)
class SampleRequest:
    handle: str = ""
    primitive: str = ""
    n_samples: int = 0
    n_points: int = 0
    seed: int = 0


@dataclasses.dataclass(frozen=True)
class ExecuteRequest:
    handle: str
    duration: float = 0.0
    phase_rate: float = 0.0
    cycles: int = 0
    reverse: bool = False


class Preview(NamedTuple):
    """Trajectory distribution on a phase grid: phases (T,), mean and std (T, d), model joint order."""

    joint_names: tuple[str, ...]
    phases: np.ndarray
    mean: np.ndarray
    std: np.ndarray


@dataclasses.dataclass(frozen=True)
class ConditionResult:
    code: Code
    message: str
    handle: str
    expires_in: float
    preview: Preview
    refine_max_error: float
    refine_iterations: int
    reachable: bool


@dataclasses.dataclass(frozen=True)
class BlendResult:
    handle: str
    expires_in: float
    preview: Preview


@dataclasses.dataclass(frozen=True)
class SampleResult:
    """samples : array, shape (S, T, d), model joint order."""

    joint_names: tuple[str, ...]
    phases: np.ndarray
    samples: np.ndarray


@dataclasses.dataclass(frozen=True)
class PrimitiveDescription:
    """Everything a client needs to build valid requests (PrimitiveInfo)."""

    name: str
    joint_names: tuple[str, ...]
    position_lower: np.ndarray
    position_upper: np.ndarray
    phase_type: str
    context_modalities: tuple[str, ...]
    context_dims: tuple[int, ...]
    accepts_images: bool
    image_height: int
    image_width: int
    image_encoding: str
    latent_dim: int
    description: str


# =================================================================================================
# Images
# =================================================================================================
IMAGE_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8")
_CHANNELS = {"rgb8": (3, (0, 1, 2)), "bgr8": (3, (2, 1, 0)), "rgba8": (4, (0, 1, 2)), "bgra8": (4, (2, 1, 0))}


def decode_image(img: ImageIn, shape: tuple[int, int], where: str = "image") -> np.ndarray:
    """Check one image against the primitive's (H, W) and return it as RGB uint8 (H, W, 3).

    Accepted encodings: rgb8, bgr8, rgba8, bgra8 (alpha dropped). Raises RequestError(INVALID_IMAGE).
    """
    h, w = shape
    enc = img.encoding.lower()
    if enc not in _CHANNELS:
        raise RequestError(Code.INVALID_IMAGE, f"{where} has encoding '{img.encoding}'; expected one of "
                           f"{', '.join(IMAGE_ENCODINGS)} (rgb8 preferred)")
    if (img.height, img.width) != (h, w):
        raise RequestError(Code.INVALID_IMAGE, f"{where} is {img.height}x{img.width} (height x width); the "
                           f"primitive expects {h}x{w} images")
    ch, order = _CHANNELS[enc]
    if img.step < w * ch:
        raise RequestError(Code.INVALID_IMAGE, f"{where} has step {img.step} bytes per row; {enc} at width {w} "
                           f"needs at least {w * ch}")
    if img.data.size != img.step * h:
        raise RequestError(Code.INVALID_IMAGE, f"{where} has {img.data.size} bytes of data; expected "
                           f"step x height = {img.step} x {h} = {img.step * h}")
    rows = np.asarray(img.data, dtype=np.uint8).reshape(h, img.step)[:, :w * ch].reshape(h, w, ch)
    return np.ascontiguousarray(rows[:, :, list(order)])


# =================================================================================================
# Execution planning
# =================================================================================================
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


# =================================================================================================
# The server
# =================================================================================================
def _finite(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and math.isfinite(v)


class PrimitiveServerCore:
    """Conditioning, blending, sampling and execution planning on loaded primitives.

    Parameters
    ----------
    primitives : mapping name -> LoadedPrimitive
    config : ServerConfig
    limits : JointLimits
        The robot's limits, robot joint order (used by :meth:`plan_execution`).
    clock : callable () -> float
        Monotonic seconds, for handle expiry.
    """

    MAX_DURATION = 86400.0
    MIN_DURATION = 0.01

    def __init__(self, primitives: Mapping[str, LoadedPrimitive], config: ServerConfig, limits: JointLimits,
                 clock: Callable[[], float] | None = None):
        self.primitives = dict(primitives)
        self.config = config
        self.limits = limits
        kw = {} if clock is None else {"clock": clock}
        self.handles = HandleStore(config.max_handles, config.handle_ttl, config.evict_when_full, **kw)

    # ------------------------------------------------------------------ helpers
    def _primitive(self, name: str) -> LoadedPrimitive:
        prim = self.primitives.get(name)
        if prim is None:
            shown = name if len(name) <= 64 else name[:64] + "..."
            raise RequestError(Code.UNKNOWN_PRIMITIVE, f"unknown primitive '{shown}'; loaded primitives: "
                               f"{', '.join(sorted(self.primitives)) or '(none)'}")
        return prim

    def _handle(self, handle: str, field: str = "handle") -> StoredDistribution:
        try:
            return self.handles.get(handle)
        except UnknownHandleError as exc:
            raise RequestError(Code.UNKNOWN_HANDLE, f"{field}: {exc}") from None

    def _store(self, value: StoredDistribution) -> tuple[str, float]:
        try:
            return self.handles.put(value, prefix=value.primitive)
        except HandleLimitError as exc:
            raise RequestError(Code.HANDLE_LIMIT, str(exc)) from None

    def _n_points(self, n: int, field: str) -> int:
        if n == 0:
            return self.config.preview_points
        if n < 2 or n > self.config.max_preview_points:
            raise RequestError(Code.INVALID_REQUEST, f"{field} = {n}; expected 0 (server default "
                               f"{self.config.preview_points}) or 2..{self.config.max_preview_points} "
                               "(parameter max_preview_points)")
        return int(n)

    @staticmethod
    def _weight(use: bool, w: float, where: str, code: Code) -> float:
        if not use:
            return 1.0
        if not _finite(w) or w < 0:
            raise RequestError(code, f"{where}: weight {w!r} is invalid; expected a finite number >= 0 "
                               "(0 removes it, 1 is the default)")
        return float(w)

    def _decode(self, prim: LoadedPrimitive, dist: StoredDistribution, x: np.ndarray,
                eps: np.ndarray | None) -> np.ndarray:
        """Trajectory of ``dist`` at phases x (T,): z(x) = μ(x) + ε σ(x) (ε None -> 0), (T, d)."""
        if isinstance(dist, ConditionedLatent):
            z = dist.latent.mean if eps is None else dist.latent.mean + eps * dist.latent.std
            return prim.model.decode(z, x)
        mean, var = dist.latent_at(x)
        z = mean if eps is None else mean + eps[None, :] * np.sqrt(var)
        return prim.model.decode_per_phase(z, x)

    def _samples(self, prim: LoadedPrimitive, dist: StoredDistribution, x: np.ndarray, n: int,
                 seed: int) -> np.ndarray:
        """n trajectories, ONE ε per trajectory: shape (n, T, d)."""
        k, t = prim.model.latent_dim, x.shape[0]
        eps = np.random.default_rng(seed).standard_normal((n, k))
        mean, var = dist.latent_at(x)  # (T, k) each
        z = mean[None] + eps[:, None, :] * np.sqrt(var)[None]  # (n, T, k)
        # one (n T) x k matrix through the decoder: a single matrix product per layer (numpy's
        # stacked 3-D matmul is ~10x slower for these sizes)
        y = prim.model.decode_per_phase(z.reshape(n * t, k), np.tile(x, n))
        return y.reshape(n, t, -1)

    def _preview(self, prim: LoadedPrimitive, dist: StoredDistribution, n_points: int) -> Preview:
        """Mean at n_points phases; std at preview_std_points phases (linearized, or from
        preview_std_samples trajectories with ONE z each), interpolated linearly onto the n_points."""
        x = np.linspace(0.0, 1.0, n_points)
        mean = self._decode(prim, dist, x, dist.eps)
        xs = np.linspace(0.0, 1.0, min(n_points, self.config.preview_std_points))
        if isinstance(dist, ConditionedLatent) and self.config.preview_std_method == "linearized":
            _, jac = prim.model.decoder_jacobian(dist.latent.mean, xs)  # (T, d, k)
            std_s = np.sqrt(((jac * dist.latent.std) ** 2).sum(axis=-1))
        else:
            std_s = self._samples(prim, dist, xs, self.config.preview_std_samples, seed=0).std(axis=0)
        std = std_s if xs.size == n_points else np.stack(
            [np.interp(x, xs, std_s[:, j]) for j in range(std_s.shape[1])], axis=1)
        return Preview(prim.joint_names, x, mean, std)

    # ------------------------------------------------------------------ ListPrimitives
    def describe(self) -> list[PrimitiveDescription]:
        out = []
        for name in sorted(self.primitives):
            p = self.primitives[name]
            m = p.model
            img = m.image_shape
            out.append(PrimitiveDescription(
                name=name, joint_names=m.joint_names,
                position_lower=np.asarray(self.limits.lower)[p.robot_index],
                position_upper=np.asarray(self.limits.upper)[p.robot_index],
                phase_type=m.phase_type, context_modalities=tuple(m.context_dims),
                context_dims=tuple(int(v) for v in m.context_dims.values()),
                accepts_images=img is not None, image_height=int(img[0]) if img else 0,
                image_width=int(img[1]) if img else 0, image_encoding="rgb8" if img else "",
                latent_dim=m.latent_dim,
                description=p.entry.description or f"model {p.path.name}"))
        return out

    # ------------------------------------------------------------------ Condition
    def check_condition_sizes(self, n_via_points: int, n_contexts: int, n_images: Sequence[int],
                              preview_points: int) -> None:
        """Cheap bounds check BEFORE the message is converted (absurd sizes are refused here)."""
        cfg = self.config
        if n_via_points > cfg.max_via_points:
            raise RequestError(Code.INVALID_REQUEST, f"{n_via_points} via-points; the server accepts at most "
                               f"{cfg.max_via_points} (parameter max_via_points)")
        if n_contexts > 64:
            raise RequestError(Code.INVALID_CONTEXT, f"{n_contexts} contexts; expected at most one per "
                               "modality of the primitive (see ListPrimitives)")
        for i, n in enumerate(n_images):
            if n > cfg.max_images:
                raise RequestError(Code.INVALID_IMAGE, f"context {i} has {n} images; the server accepts at "
                                   f"most {cfg.max_images} per context (parameter max_images)")
        self._n_points(preview_points, "preview_points")

    def condition(self, req: ConditionRequest) -> ConditionResult:
        """Bayesian aggregation (paper Eq. 1/3) of via-points and contexts, optional refinement
        (paper Eq. 5), stored under a new handle, with a preview of mean and std."""
        cfg = self.config
        prim = self._primitive(req.primitive)
        model = prim.model
        d = model.n_joints
        self.check_condition_sizes(len(req.via_points), len(req.contexts),
                                   [len(c.images) for c in req.contexts], req.preview_points)
        n_points = self._n_points(req.preview_points, "preview_points")
        if not _finite(req.refine_tolerance) or req.refine_tolerance < 0:
            raise RequestError(Code.INVALID_REQUEST, f"refine_tolerance {req.refine_tolerance!r} is invalid; "
                               f"expected a finite number >= 0 (0 = server default {cfg.refine_tolerance:g} rad)")
        tol = float(req.refine_tolerance) or cfg.refine_tolerance
        iters = int(req.refine_max_iterations) or cfg.refine_max_iterations
        if iters > 10000:
            raise RequestError(Code.INVALID_REQUEST, f"refine_max_iterations {iters} is too large; expected "
                               "0 (server default) or 1..10000")

        # ---- via-points
        n = len(req.via_points)
        vx, vy = np.zeros(n), np.zeros((n, d))
        vmask, vw = np.ones((n, d), dtype=bool), np.ones(n)
        for i, vp in enumerate(req.via_points):
            where = f"via-point {i}"
            if not _finite(vp.phase) or not 0.0 <= vp.phase <= 1.0:
                raise RequestError(Code.INVALID_VIA_POINT, f"{where}: phase {vp.phase!r} is outside [0, 1]; "
                                   "phases are normalized time (0 = start, 1 = end"
                                   f"{', fraction of a cycle' if model.phase_type == 'rhythmic' else ''})")
            pos = np.asarray(vp.positions, dtype=np.float64).reshape(-1)
            if pos.size != d:
                raise RequestError(Code.INVALID_VIA_POINT, f"{where} has {pos.size} joint values; primitive "
                                   f"'{prim.name}' has {d} joints: {', '.join(model.joint_names)}")
            if not np.all(np.isfinite(pos)):
                j = int(np.argmax(~np.isfinite(pos)))
                raise RequestError(Code.INVALID_VIA_POINT, f"{where}: joint '{model.joint_names[j]}' is "
                                   f"{pos[j]}; expected finite positions (rad) for every joint, masked or not")
            mask = np.asarray(vp.joint_mask, dtype=bool).reshape(-1)
            if mask.size not in (0, d):
                raise RequestError(Code.INVALID_VIA_POINT, f"{where}: joint_mask has {mask.size} entries; "
                                   f"expected 0 (all joints) or {d} (one per joint)")
            if mask.size and not mask.any():
                raise RequestError(Code.INVALID_VIA_POINT, f"{where}: joint_mask selects no joint; set at least "
                                   "one entry true or leave the mask empty (all joints)")
            vx[i], vy[i] = float(vp.phase), pos
            if mask.size:
                vmask[i] = mask
            vw[i] = self._weight(vp.use_weight, vp.weight, where, Code.INVALID_VIA_POINT)

        # ---- contexts
        contexts, cweights, images, image_weight = {}, {}, None, 1.0
        seen = set()
        dims = model.context_dims
        for i, c in enumerate(req.contexts):
            where = f"context {i} ('{c.modality}')"
            if c.modality in seen:
                raise RequestError(Code.INVALID_CONTEXT, f"{where}: modality given twice; expected at most one "
                                   "Context per modality (put several images of one scene into one Context)")
            seen.add(c.modality)
            w = self._weight(c.use_weight, c.weight, where,
                             Code.INVALID_IMAGE if c.modality == "image" else Code.INVALID_CONTEXT)
            if c.modality == "image":
                if model.image_shape is None:
                    raise RequestError(Code.INVALID_IMAGE, f"{where}: primitive '{prim.name}' accepts no images; "
                                       f"its contexts: {', '.join(dims) or 'none'}")
                if len(c.values):
                    raise RequestError(Code.INVALID_IMAGE, f"{where}: values must be empty for modality 'image'")
                if not c.images:
                    raise RequestError(Code.INVALID_IMAGE, f"{where}: no images; expected at least one "
                                       f"{model.image_shape[0]}x{model.image_shape[1]} rgb8 image")
                images = np.stack([decode_image(im, model.image_shape, f"{where} image {k}")
                                   for k, im in enumerate(c.images)])
                image_weight = w
                continue
            if c.modality not in dims:
                raise RequestError(Code.INVALID_CONTEXT, f"{where}: unknown modality; primitive '{prim.name}' "
                                   f"accepts {', '.join(repr(m) for m in dims) or 'no low-dimensional contexts'}"
                                   f"{' and images' if model.image_shape else ''}")
            if c.images:
                raise RequestError(Code.INVALID_CONTEXT, f"{where}: images are only allowed with modality 'image'")
            vals = np.asarray(c.values, dtype=np.float64).reshape(-1)
            if vals.size != dims[c.modality]:
                raise RequestError(Code.INVALID_CONTEXT, f"{where} has {vals.size} values; expected exactly "
                                   f"{dims[c.modality]}")
            if not np.all(np.isfinite(vals)):
                raise RequestError(Code.INVALID_CONTEXT, f"{where} contains NaN or inf; expected finite values")
            contexts[c.modality] = vals[None, :]
            cweights[c.modality] = [w]

        # ---- aggregate (paper Eq. 1 / Eq. 3 with importance weights)
        try:
            latent = model.condition(vx if n else None, vy if n else None, vw if n else None,
                                     vmask if n else None, contexts or None, cweights or None,
                                     images, image_weight)
        except ValueError as exc:
            raise RequestError(Code.INVALID_REQUEST, str(exc)) from None

        # ---- error of the executed mean at the via-points, optional refinement (paper Eq. 5)
        active = vw > 0
        iterations, reason = 0, ""
        if active.any():
            xa, ya, ma = vx[active], vy[active], vmask[active]
            if req.refine:
                res = model.refine(latent, xa, ya, ma, max_iterations=iters, tol=tol)
                latent, iterations, reason = res.latent, res.iterations, res.reason
                max_err = res.max_error
            else:
                max_err = float(np.abs((model.decode(latent.mean, xa) - ya)[ma]).max())
        else:
            max_err = 0.0
        reachable = max_err <= tol
        dist = ConditionedLatent(prim.name, latent)
        handle, expires = self._store(dist)
        preview = self._preview(prim, dist, n_points)
        if req.refine and not reachable:
            code = Code.REFINEMENT_UNREACHABLE
            msg = (f"refinement stopped ({reason}) after {iterations} iterations with max via-point error "
                   f"{max_err:.3g} rad > tolerance {tol:g} rad: the via-points cannot all be met by this "
                   f"primitive; handle '{handle}' holds the best fit")
        else:
            code = Code.SUCCESS
            msg = (f"conditioned '{prim.name}' on {int(active.sum())} via-points and {len(req.contexts)} contexts"
                   + (f"; refined in {iterations} iterations" if req.refine and active.any() else "")
                   + f"; max via-point error {max_err:.3g} rad")
        return ConditionResult(code, msg, handle, expires, preview, max_err, iterations, reachable)

    # ------------------------------------------------------------------ Blend
    def blend(self, req: BlendRequest) -> BlendResult:
        """q_b(z | x) ∝ q_a^ω(x) q_b^(1-ω(x)) (paper Eq. 4) of two stored distributions."""
        a = self._handle(req.handle_a, "handle_a")
        b = self._handle(req.handle_b, "handle_b")
        if a.primitive != b.primitive:
            raise RequestError(Code.INVALID_REQUEST, f"handle_a is of primitive '{a.primitive}' and handle_b of "
                               f"'{b.primitive}'; blending combines latent distributions of ONE primitive "
                               "(one decoder), so both handles must come from the same primitive")
        prim = self._primitive(a.primitive)
        nx, nw = len(req.schedule_phases), len(req.schedule_weights)
        if max(nx, nw) > self.config.max_via_points:
            raise RequestError(Code.INVALID_REQUEST, f"schedule has {max(nx, nw)} knots; the server accepts at most "
                               f"{self.config.max_via_points} (parameter max_via_points)")
        n_points = self._n_points(req.preview_points, "preview_points")
        if nx == 0 and nw == 0:
            schedule = Schedule.linear_handover()
        else:
            try:
                schedule = Schedule(np.asarray(req.schedule_phases, dtype=np.float64),
                                    np.asarray(req.schedule_weights, dtype=np.float64))
            except ValueError as exc:
                raise RequestError(Code.INVALID_REQUEST, f"{exc} (schedule_phases strictly increasing in "
                                   "[0, 1], schedule_weights in [0, 1], same length; both empty = linear "
                                   "hand-over from a to b)") from None
        eps = None
        if req.sample:
            eps = np.random.default_rng(int(req.seed) & 0xFFFFFFFFFFFFFFFF).standard_normal(prim.model.latent_dim)
        dist = BlendedLatent(prim.name, a, b, schedule, eps)
        handle, expires = self._store(dist)
        return BlendResult(handle, expires, self._preview(prim, dist, n_points))

    # ------------------------------------------------------------------ Sample
    def sample(self, req: SampleRequest) -> SampleResult:
        """S whole trajectories, z ~ q(z) once per trajectory (prior of ``primitive`` if no handle)."""
        if req.handle:
            dist = self._handle(req.handle)
            prim = self._primitive(dist.primitive)
        else:
            if not req.primitive:
                raise RequestError(Code.INVALID_REQUEST, "set handle (from Condition or Blend) or, to sample "
                                   "the prior, primitive")
            prim = self._primitive(req.primitive)
            dist = ConditionedLatent(prim.name, prim.model.prior())
        s = int(req.n_samples) or 1
        if s > self.config.max_samples:
            raise RequestError(Code.INVALID_REQUEST, f"n_samples = {s}; expected 0 (= 1) or 1..{self.config.max_samples}"
                               " (parameter max_samples)")
        t = self._n_points(req.n_points, "n_points")
        total = s * t * prim.model.n_joints
        if total > self.config.max_sample_values:
            raise RequestError(Code.INVALID_REQUEST, f"n_samples x n_points x joints = {total} values; the server "
                               f"returns at most {self.config.max_sample_values} (parameter max_sample_values)")
        x = np.linspace(0.0, 1.0, t)
        return SampleResult(prim.joint_names, x, self._samples(prim, dist, x, s, int(req.seed) & 0xFFFFFFFFFFFFFFFF))

    # ------------------------------------------------------------------ Execute
    def plan_execution(self, req: ExecuteRequest) -> ExecutionPlan:
        """Validate an Execute goal and decode the executed mean on the dense grid (robot order)."""
        cfg = self.config
        dist = self._handle(req.handle)
        prim = self._primitive(dist.primitive)
        for field in ("duration", "phase_rate"):
            v = getattr(req, field)
            if not _finite(v) or v < 0:
                raise RequestError(Code.INVALID_REQUEST, f"{field} {v!r} is invalid; expected a finite number "
                                   ">= 0 (0 = not set)")
        if req.duration > 0 and req.phase_rate > 0:
            raise RequestError(Code.INVALID_REQUEST, f"both duration ({req.duration:g} s) and phase_rate "
                               f"({req.phase_rate:g} /s) are set; set at most one (phase_rate = 1 / duration)")
        if req.duration > 0:
            duration = float(req.duration)
        elif req.phase_rate > 0:
            duration = 1.0 / float(req.phase_rate)
        else:
            duration = prim.entry.default_duration or cfg.default_duration
        if not self.MIN_DURATION <= duration <= self.MAX_DURATION:
            raise RequestError(Code.INVALID_REQUEST, f"duration {duration:.6g} s (phase rate {1 / duration:.6g} /s)"
                               f" is out of range; expected {self.MIN_DURATION:g}..{self.MAX_DURATION:g} s")
        rhythmic = prim.model.phase_type == "rhythmic"
        cycles = 1
        if rhythmic:
            cycles = int(req.cycles) or 1
            if cycles > cfg.max_cycles:
                raise RequestError(Code.INVALID_REQUEST, f"cycles = {cycles}; expected 0 (= 1) or 1..{cfg.max_cycles}"
                                   " (parameter max_cycles)")
        x = np.linspace(0.0, 1.0, cfg.execution_grid_points)
        y = prim.to_robot_order(self._decode(prim, dist, x, dist.eps))
        ref = ExecutionReference(y, rhythmic, cfg.derivative_step)
        if cfg.check_feasibility:
            self._check_positions(ref, x)
            self.check_rate(ref, 1.0 / duration)
        return ExecutionPlan(req.handle, prim.name, ref, duration, rhythmic, cycles, bool(req.reverse))

    def _check_positions(self, ref: ExecutionReference, x: np.ndarray) -> None:
        lim = self.limits
        tol = 1e-6
        below = ref.y < lim.lower - tol
        above = ref.y > lim.upper + tol
        if below.any() or above.any():
            i, j = np.argwhere(below | above)[0]
            side, bound = ("lower", lim.lower[j]) if below[i, j] else ("upper", lim.upper[j])
            raise RequestError(Code.LIMIT_VIOLATION, f"the trajectory of this handle leaves the position limits: "
                               f"{lim.names[j]} reaches {ref.y[i, j]:.4g} rad at phase {x[i]:.3f}, beyond its "
                               f"{side} limit {bound:.4g} rad; condition on via-points inside the limits")

    def check_rate(self, ref: ExecutionReference, rate: float) -> None:
        """Refuse (LIMIT_VIOLATION) a phase rate at which the reference needs more than v_max."""
        speed = ref.max_speed_per_phase()
        need = speed * abs(rate)
        vmax = self.limits.max_velocity
        over = need > vmax * (1 + 1e-9)
        if over.any():
            j = int(np.argmax(need / vmax))
            t_min = float(np.max(speed / vmax))
            raise RequestError(Code.LIMIT_VIOLATION, f"at phase rate {abs(rate):.4g} /s (duration "
                               f"{1 / abs(rate):.4g} s) {self.limits.names[j]} would need {need[j]:.3g} rad/s; its "
                               f"velocity limit is {vmax[j]:.3g} rad/s: use a duration >= {t_min:.3g} s "
                               f"(phase rate <= {1 / t_min:.4g} /s)")


if __name__ == "__main__":  # python -m deepprompt_ros.server.service_logic: the parameter table (Markdown)
    print(parameters_markdown())
