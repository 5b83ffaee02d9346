"""The primitive server's plain request and result types.

The ROS node converts messages to these types (:mod:`deepprompt_ros.ros.conversions`), calls
:class:`~deepprompt_ros.server.service.PrimitiveServerCore` and converts the results back;
nothing here needs rclpy. Every request that cannot be carried out raises
:class:`~deepprompt_ros.common.results.RequestError` with a
:class:`~deepprompt_ros.common.results.Code` (the values of ``deepprompt_msgs/msg/ResultCode``)
and a message that says what was wrong and what is expected.
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple, Sequence

import numpy as np

from deepprompt_ros.common.results import Code

__all__ = [
    "ViaPointIn", "ImageIn", "ContextIn", "ConditionRequest", "BlendRequest", "SampleRequest",
    "ExecuteRequest", "Preview", "ConditionResult", "BlendResult", "SampleResult", "PrimitiveDescription",
]


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
