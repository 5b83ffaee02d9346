"""The primitive server's plain request and result types and its result codes.

The ROS node converts messages to these types (:mod:`deepprompt_ros.ros.conversions`), calls
:class:`~deepprompt_ros.server.service.PrimitiveServerCore` and converts the results back;
nothing here needs rclpy. Every request that cannot be carried out raises :class:`RequestError`
with a :class:`Code` (the values of ``deepprompt_msgs/msg/ResultCode``, shared by the services,
the Execute action and the control loop) and a message that says what was wrong and what is
expected.
"""
from __future__ import annotations

import dataclasses
import enum
from typing import NamedTuple, Sequence

import numpy as np

__all__ = [
    "Code", "RequestError", "ViaPointIn", "ImageIn", "ContextIn", "ConditionRequest", "BlendRequest",
    "SampleRequest", "ExecuteRequest", "Preview", "ConditionResult", "BlendResult", "SampleResult",
    "PrimitiveDescription",
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
