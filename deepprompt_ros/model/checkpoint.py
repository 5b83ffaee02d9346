"""Self-describing model files: safetensors weights + JSON metadata, loaded with no pickle.

A checkpoint carries its architecture (:class:`ModelConfig`), joint names, phase type, the
normalization of joints and contexts, training configuration, provenance and metrics. Loading
never executes code from the file: safetensors stores raw tensors and a JSON header only
(:mod:`deepprompt_ros.model.safetensors_file`), and anything that is not a well-formed DeepProMP
safetensors file is refused with a message.

The normalization is stored the same way in the baselines' files
(:func:`normalization_tensors`, :func:`read_normalization`).
"""
from __future__ import annotations

import dataclasses
import json
import pathlib
from typing import Mapping, Sequence

import numpy as np
import torch

from deepprompt_ros.model.network import DeepProMPNet, ModelConfig
from deepprompt_ros.model.safetensors_file import read_safetensors, write_safetensors

FORMAT = "deepprompt_ros.deepprompt/1"
_WORDING = {"expected": "a .safetensors DeepProMP checkpoint", "written": "a checkpoint written by deepprompt_ros",
            "refused": "pickled torch files"}


class CheckpointError(ValueError):
    """A model file is missing, malformed, or not a DeepProMP checkpoint."""


@dataclasses.dataclass(frozen=True)
class Normalization:
    """Per-joint and per-context standardization: v_norm = (v - mean) / std.

    Attributes
    ----------
    y_mean, y_std : array, shape (d,)
    ctx_mean, ctx_std : mapping modality -> array, shape (c,)
    """

    y_mean: np.ndarray
    y_std: np.ndarray
    ctx_mean: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)
    ctx_std: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)


def normalization_tensors(norm: Normalization) -> dict[str, torch.Tensor]:
    """The float64 tensors ``norm.y_mean``, ``norm.y_std``, ``norm.ctx_mean.<name>``,
    ``norm.ctx_std.<name>`` under which a model file stores ``norm``."""
    tensors = {"norm.y_mean": torch.as_tensor(np.asarray(norm.y_mean, dtype=np.float64)),
               "norm.y_std": torch.as_tensor(np.asarray(norm.y_std, dtype=np.float64))}
    for name in norm.ctx_mean:
        tensors[f"norm.ctx_mean.{name}"] = torch.as_tensor(np.asarray(norm.ctx_mean[name], dtype=np.float64))
        tensors[f"norm.ctx_std.{name}"] = torch.as_tensor(np.asarray(norm.ctx_std[name], dtype=np.float64))
    return tensors


def read_normalization(tensors: Mapping[str, torch.Tensor], n_joints: int,
                       context_dims: Sequence[tuple[str, int]], path,
                       error: type[ValueError] = ValueError) -> Normalization:
    """The :class:`Normalization` stored by :func:`normalization_tensors`, checked against the
    model's ``n_joints`` and ``context_dims`` ((name, c) pairs); what is missing or invalid raises
    ``error`` naming the file ``path``."""
    try:
        norm = Normalization(
            y_mean=tensors["norm.y_mean"].numpy(), y_std=tensors["norm.y_std"].numpy(),
            ctx_mean={n: tensors[f"norm.ctx_mean.{n}"].numpy() for n, _ in context_dims},
            ctx_std={n: tensors[f"norm.ctx_std.{n}"].numpy() for n, _ in context_dims})
    except KeyError as exc:
        raise error(f"model file '{path}' lacks normalization tensor {exc}") from exc
    if norm.y_mean.shape != (n_joints,) or norm.y_std.shape != (n_joints,) or not np.all(norm.y_std > 0):
        raise error(f"model file '{path}' has invalid joint normalization")
    for n, cdim in context_dims:
        if norm.ctx_mean[n].shape != (cdim,) or not np.all(norm.ctx_std[n] > 0):
            raise error(f"model file '{path}' has invalid normalization for context '{n}'")
    return norm


@dataclasses.dataclass(frozen=True)
class Checkpoint:
    config: ModelConfig
    state_dict: Mapping[str, torch.Tensor]
    normalization: Normalization
    joint_names: tuple[str, ...]
    metadata: Mapping[str, object]

    def build(self) -> DeepProMPNet:
        net = DeepProMPNet(self.config)
        try:
            net.load_state_dict(self.state_dict, strict=True)
        except RuntimeError as exc:
            raise CheckpointError(f"weights do not match the architecture stored in the file: {exc}") from exc
        net.eval()
        return net


def save_checkpoint(path, net: DeepProMPNet, normalization: Normalization, joint_names,
                    metadata: Mapping[str, object] | None = None) -> pathlib.Path:
    """Write a checkpoint atomically (temp file + rename)."""
    tensors = {f"net.{k}": v for k, v in net.state_dict().items()} | normalization_tensors(normalization)
    meta = {
        "format": FORMAT,
        "model_config": json.dumps(net.cfg.to_json()),
        "joint_names": json.dumps(list(joint_names)),
        "phase_type": net.cfg.phase_type,
        "metadata": json.dumps(dict(metadata or {}), default=str),
    }
    return write_safetensors(path, tensors, meta)


def load_checkpoint(path) -> Checkpoint:
    """Load and validate a checkpoint; raise :class:`CheckpointError` with what is wrong."""
    path = pathlib.Path(path)
    meta, tensors = read_safetensors(path, error=CheckpointError, **_WORDING)
    if meta.get("format") != FORMAT:
        raise CheckpointError(f"model file '{path}' has format '{meta.get('format')}'; expected '{FORMAT}'")
    try:
        cfg = ModelConfig.from_json(json.loads(meta["model_config"]))
        joint_names = tuple(json.loads(meta["joint_names"]))
        extra = json.loads(meta.get("metadata", "{}"))
    except (KeyError, ValueError, TypeError) as exc:
        raise CheckpointError(f"model file '{path}' has invalid metadata: {exc}") from exc
    if len(joint_names) != cfg.n_joints:
        raise CheckpointError(f"model file '{path}' names {len(joint_names)} joints but its model has {cfg.n_joints}")
    norm = read_normalization(tensors, cfg.n_joints, cfg.context_dims, path, CheckpointError)
    for k, v in tensors.items():
        if v.is_floating_point() and not torch.isfinite(v).all():
            raise CheckpointError(f"model file '{path}': tensor '{k}' contains NaN or inf")
    state = {k[4:]: v for k, v in tensors.items() if k.startswith("net.")}
    ck = Checkpoint(cfg, state, norm, joint_names, extra)
    ck.build()  # shape check now, so a bad file is refused at load time
    return ck

