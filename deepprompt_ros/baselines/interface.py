"""The one interface of every movement-primitive model of the package (DeepProMP, ProMP, CNMP,
VAE-CNMP and the Indep variants): :class:`MovementPrimitiveModel` with fit / condition /
mean_trajectory / sample / save / load, the validation of conditioning inputs
(:class:`InputSpec`, :class:`Inputs`), and what the baselines' files share (format tag, metadata,
provenance, the validation split).

Units: phases x in [0, 1], joint positions in the demonstrations' units (rad), contexts raw.
"""
from __future__ import annotations

import abc
import dataclasses
import datetime
import json
import pathlib
from typing import Any, ClassVar, Mapping, NamedTuple

import numpy as np
import torch

from deepprompt_ros import __version__
from deepprompt_ros.common.joints import joint_list_text
from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.model.checkpoint import Normalization
from deepprompt_ros.model.safetensors_file import metadata_json
from deepprompt_ros.primitive.inputs import check_images, check_phases
from deepprompt_ros.training.config import TrainConfig

__all__ = ["Inputs", "InputSpec", "MovementPrimitiveModel", "BASELINE_FORMAT", "split_for_validation",
           "provenance", "context_mean", "read_baseline_metadata"]

BASELINE_FORMAT = "deepprompt_ros.baseline/1"


class Inputs(NamedTuple):
    """Validated conditioning inputs (raw units).

    via_x : (n,); via_y : (n, d); contexts : modality -> (m, c); images : (n_img, H, W, 3) uint8 or None.
    """

    via_x: np.ndarray
    via_y: np.ndarray
    contexts: dict
    images: np.ndarray | None


@dataclasses.dataclass(frozen=True)
class InputSpec:
    """What a trained model accepts: joints, phase type, context modalities and image size."""

    name: str
    joint_names: tuple[str, ...]
    phase_type: str = "linear"
    context_dims: tuple[tuple[str, int], ...] = ()
    image_shape: tuple[int, int] | None = None

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    def _joints(self) -> str:
        return joint_list_text(self.joint_names)

    def check_phases(self, x, what: str = "phase") -> np.ndarray:
        """x : (T,) phases in [0, 1]."""
        return check_phases(x, what)

    def check(self, via_x=None, via_y=None, contexts: Mapping | None = None, images=None) -> Inputs:
        """Validate conditioning inputs; raise ``ValueError`` saying what is expected."""
        d = self.n_joints
        if (via_x is None) != (via_y is None):
            raise ValueError("via-points need both phases via_x (n,) and positions via_y (n, d); got only "
                             f"{'via_x' if via_y is None else 'via_y'}")
        if via_x is None:
            x, y = np.zeros(0), np.zeros((0, d))
        else:
            x = self.check_phases(via_x, "via-point phase")
            y = np.asarray(via_y, dtype=np.float64)
            if y.ndim == 1 and x.shape[0] == 1:
                y = y[None, :]
            if y.ndim != 2:
                raise ValueError(f"via-point positions must have shape (n, {d}), got {y.shape}")
            if y.shape[1] != d:
                raise ValueError(f"via-points have {y.shape[1]} joint values; model '{self.name}' has {d} "
                                 f"joints: {self._joints()}")
            if y.shape[0] != x.shape[0]:
                raise ValueError(f"{y.shape[0]} via-point position rows for {x.shape[0]} phases; expected one "
                                 "row per phase")
            bad = ~np.isfinite(y)
            if bad.any():
                i, j = np.argwhere(bad)[0]
                raise ValueError(f"via-point {i} joint '{self.joint_names[j]}' is NaN or inf; expected finite "
                                 "positions")
        dims = dict(self.context_dims)
        ctx = {}
        if contexts is not None and not isinstance(contexts, Mapping):
            raise ValueError(f"contexts must be a mapping modality -> array (m, c), got {type(contexts).__name__}")
        for name, c in (contexts or {}).items():
            if name not in dims:
                raise ValueError(f"model '{self.name}' takes no context '{name}'; it accepts "
                                 f"{sorted(dims) or 'no low-dimensional contexts'}"
                                 f"{' and images' if self.image_shape else ''}")
            c = np.asarray(c, dtype=np.float64)
            if c.ndim == 1:
                c = c[None, :]
            if c.ndim != 2 or c.shape[1] != dims[name] or c.shape[0] < 1:
                raise ValueError(f"context '{name}' must have {dims[name]} values per vector (shape (m, "
                                 f"{dims[name]}) or ({dims[name]},)), got shape {c.shape}")
            if not np.all(np.isfinite(c)):
                raise ValueError(f"context '{name}' contains NaN or inf; expected finite values")
            ctx[name] = c
        im = None
        if images is not None:
            if self.image_shape is None:
                raise ValueError(f"model '{self.name}' takes no images (it was trained without them)")
            im = check_images(images, self.image_shape)
        return Inputs(x, y, ctx, im)

    @classmethod
    def from_dataset(cls, name: str, ds: DemoDataset) -> "InputSpec":
        return cls(name, tuple(ds.joint_names), ds.phase_type, tuple(ds.context_dims.items()), ds.image_shape)

    def to_json(self) -> dict:
        return {"name": self.name, "joint_names": list(self.joint_names), "phase_type": self.phase_type,
                "context_dims": [list(c) for c in self.context_dims],
                "image_shape": list(self.image_shape) if self.image_shape else None}

    @classmethod
    def from_json(cls, d: Mapping) -> "InputSpec":
        """Inverse of :meth:`to_json`; ``ValueError`` saying which entry is missing or malformed."""
        missing = [k for k in ("name", "joint_names", "phase_type", "context_dims") if k not in d]
        if missing:
            raise ValueError(f"spec lacks {missing}")
        names = d["joint_names"]
        if not isinstance(names, list) or not names or not all(isinstance(n, str) and n for n in names) \
                or len(set(names)) != len(names):
            raise ValueError(f"spec joint_names must be a list of distinct non-empty strings; got {str(names)[:80]}")
        dims = d["context_dims"]
        if not isinstance(dims, list) or not all(
                isinstance(c, list) and len(c) == 2 and isinstance(c[0], str) and type(c[1]) is int and c[1] >= 1
                for c in dims):
            raise ValueError(f"spec context_dims must be a list of [name, dimension >= 1]; got {str(dims)[:80]}")
        shape = d.get("image_shape")
        if shape is not None and not (isinstance(shape, list) and len(shape) == 2
                                      and all(type(v) is int and v >= 1 for v in shape)):
            raise ValueError(f"spec image_shape must be null or [height, width]; got {str(shape)[:80]}")
        return cls(str(d["name"]), tuple(names), str(d["phase_type"]), tuple((n, c) for n, c in dims),
                   tuple(shape) if shape else None)


class MovementPrimitiveModel(abc.ABC):
    """fit / condition / mean_trajectory / sample / save / load, the same for all six models.

    ``condition`` returns an opaque conditioned object that only the model that made it reads.
    Inputs follow :meth:`deepprompt_ros.primitive.deep_promp.DeepProMP.condition`: via_x (n,) phases in
    [0, 1], via_y (n, d), contexts {modality: (m, c) or (c,)}, images (n_img, H, W, 3) uint8.
    """

    kind: ClassVar[str] = ""
    supports_images: ClassVar[bool] = True
    #: True when any single input (via-points only, one context modality only) is part of what the
    #: model was built or trained for; False for CNMP / VAE-CNMP, trained on all inputs at once.
    independent_inputs: ClassVar[bool] = True

    def __init__(self):
        self.spec: InputSpec | None = None
        self.history: list[dict] = []

    # -- common helpers ---------------------------------------------------------------------------
    def _require_fitted(self) -> InputSpec:
        if self.spec is None:
            raise ValueError(f"this {type(self).__name__} is not trained: call fit(train_dataset, config) or "
                             "load(path)")
        return self.spec

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self._require_fitted().joint_names

    @property
    def context_dims(self) -> dict[str, int]:
        return dict(self._require_fitted().context_dims)

    @property
    def image_shape(self):
        return self._require_fitted().image_shape

    def check_inputs(self, via_x=None, via_y=None, contexts=None, images=None) -> Inputs:
        return self._require_fitted().check(via_x, via_y, contexts, images)

    @staticmethod
    def _check_n(n) -> int:
        if int(n) != n or n < 1:
            raise ValueError(f"number of samples n must be an integer >= 1, got {n}")
        return int(n)

    # -- interface ----------------------------------------------------------------------------
    @abc.abstractmethod
    def fit(self, train_ds: DemoDataset, config: TrainConfig, val_ds: DemoDataset | None = None):
        """Train on ``train_ds``; keep the weights with the best validation MSE (``val_ds``, or a split
        of ``config.n_val`` demos when None). Returns self."""

    @abc.abstractmethod
    def condition(self, via_x=None, via_y=None, contexts=None, images=None) -> Any:
        """Condition on via-points and/or contexts; returns an opaque conditioned object."""

    @abc.abstractmethod
    def mean_trajectory(self, cond, x) -> np.ndarray:
        """Predicted trajectory for ``cond`` at phases x (T,): shape (T, d)."""

    @abc.abstractmethod
    def sample(self, cond, x, n: int, rng=None) -> np.ndarray:
        """n trajectories from the conditioned model: shape (n, T, d)."""

    @abc.abstractmethod
    def save(self, path) -> pathlib.Path:
        """Write a self-describing safetensors file (weights + JSON metadata)."""

    @classmethod
    @abc.abstractmethod
    def load(cls, path) -> "MovementPrimitiveModel":
        """Read a file written by :meth:`save` (no pickle)."""


def split_for_validation(train_ds: DemoDataset, cfg: TrainConfig, val_ds: DemoDataset | None):
    """(train, validation) datasets: ``val_ds`` if given, else ``cfg.n_val`` demos (0: 10 %, at
    least 1) split off ``train_ds`` with ``cfg.seed`` — the split of :func:`deepprompt_ros.training.loop.train`."""
    if val_ds is not None:
        return train_ds, val_ds
    return train_ds.split(cfg.n_val or max(1, len(train_ds) // 10), seed=cfg.seed)


def provenance(train_ds: DemoDataset, val_ds: DemoDataset | None) -> dict:
    """The ``provenance`` metadata of a trained model's file (dataset, sizes, creation time, versions)."""
    return {"dataset": train_ds.source, "n_train": len(train_ds), "n_val": len(val_ds) if val_ds else 0,
            "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "deepprompt_ros": __version__, "torch": torch.__version__}


def context_mean(c: np.ndarray, norm: Normalization, name: str) -> np.ndarray:
    """(m, c) raw → (c,) normalized, averaged over the m vectors."""
    return ((c - norm.ctx_mean[name]) / norm.ctx_std[name]).mean(0)


def read_baseline_metadata(path, meta: Mapping, kind: str) -> tuple[InputSpec, dict]:
    """The :class:`InputSpec` and the JSON ``metadata`` of a baseline file of ``kind`` (``meta``: its
    safetensors metadata); ``ValueError`` naming ``path`` when it is another format or kind."""
    if meta.get("format") != BASELINE_FORMAT:
        raise ValueError(f"model file '{path}' has format '{meta.get('format')}'; expected '{BASELINE_FORMAT}' "
                         "(use load_model(path) to open any model file)")
    if meta.get("kind") != kind:
        raise ValueError(f"model file '{path}' holds a '{meta.get('kind')}' model, not '{kind}'; use "
                         "load_model(path) to open any model file")
    spec = metadata_json(meta, "spec", path)
    try:
        spec = InputSpec.from_json(spec)
    except ValueError as exc:
        raise ValueError(f"model file '{path}' has invalid metadata: {exc}") from exc
    return spec, metadata_json(meta, "metadata", path, default={})
