"""Self-describing model files: safetensors weights + JSON metadata, loaded with no pickle.

A checkpoint carries its architecture (:class:`ModelConfig`), joint names, phase type, the
normalization of joints and contexts, training configuration, provenance and metrics. Loading
never executes code from the file: safetensors stores raw tensors and a JSON header only, and
anything that is not a well-formed DeepProMP safetensors file is refused with a message.
"""
from __future__ import annotations

import dataclasses
import json
import pathlib
from typing import Mapping

import numpy as np
import torch

from deepprompt_ros.model.network import DeepProMPNet, ModelConfig

FORMAT = "deepprompt_ros.deepprompt/1"
_MAGIC_MAX_HEADER = 100 * 1024 * 1024


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
    from safetensors.torch import save_file

    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tensors = {f"net.{k}": v.detach().cpu().contiguous() for k, v in net.state_dict().items()}
    tensors["norm.y_mean"] = torch.as_tensor(np.asarray(normalization.y_mean, dtype=np.float64))
    tensors["norm.y_std"] = torch.as_tensor(np.asarray(normalization.y_std, dtype=np.float64))
    for name in normalization.ctx_mean:
        tensors[f"norm.ctx_mean.{name}"] = torch.as_tensor(np.asarray(normalization.ctx_mean[name], dtype=np.float64))
        tensors[f"norm.ctx_std.{name}"] = torch.as_tensor(np.asarray(normalization.ctx_std[name], dtype=np.float64))
    meta = {
        "format": FORMAT,
        "model_config": json.dumps(net.cfg.to_json()),
        "joint_names": json.dumps(list(joint_names)),
        "phase_type": net.cfg.phase_type,
        "metadata": json.dumps(dict(metadata or {}), default=str),
    }
    tmp = path.with_name(path.name + ".part")
    save_file(tensors, str(tmp), metadata=meta)
    tmp.replace(path)
    return path


def load_checkpoint(path) -> Checkpoint:
    """Load and validate a checkpoint; raise :class:`CheckpointError` with what is wrong."""
    from safetensors import safe_open

    path = pathlib.Path(path)
    if not path.is_file():
        raise CheckpointError(f"model file '{path}' does not exist; expected a .safetensors DeepProMP checkpoint")
    with open(path, "rb") as f:
        head = f.read(8)
    if len(head) < 8 or int.from_bytes(head, "little") > min(_MAGIC_MAX_HEADER, path.stat().st_size):
        raise CheckpointError(
            f"model file '{path}' is not a safetensors file (pickled torch files are refused: they can run code); "
            "expected a checkpoint written by deepprompt_ros")
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as exc:  # safetensors raises its own error types for corrupt headers
        raise CheckpointError(f"model file '{path}' is corrupt or not a safetensors file: {exc}") from exc
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
    try:
        norm = Normalization(
            y_mean=tensors["norm.y_mean"].numpy(), y_std=tensors["norm.y_std"].numpy(),
            ctx_mean={n: tensors[f"norm.ctx_mean.{n}"].numpy() for n in cfg.context_names},
            ctx_std={n: tensors[f"norm.ctx_std.{n}"].numpy() for n in cfg.context_names})
    except KeyError as exc:
        raise CheckpointError(f"model file '{path}' lacks normalization tensor {exc}") from exc
    if norm.y_mean.shape != (cfg.n_joints,) or not np.all(norm.y_std > 0):
        raise CheckpointError(f"model file '{path}' has invalid joint normalization")
    for n, cdim in cfg.context_dims:
        if norm.ctx_mean[n].shape != (cdim,) or not np.all(norm.ctx_std[n] > 0):
            raise CheckpointError(f"model file '{path}' has invalid normalization for context '{n}'")
    for k, v in tensors.items():
        if v.is_floating_point() and not torch.isfinite(v).all():
            raise CheckpointError(f"model file '{path}': tensor '{k}' contains NaN or inf")
    state = {k[4:]: v for k, v in tensors.items() if k.startswith("net.")}
    ck = Checkpoint(cfg, state, norm, joint_names, extra)
    ck.build()  # shape check now, so a bad file is refused at load time
    return ck
