"""Self-describing model files: safetensors weights + JSON metadata, loaded with no pickle.

A checkpoint carries its architecture (:class:`ModelConfig`), joint names, phase type, the
normalization of joints and contexts, training configuration, provenance and metrics. Loading
never executes code from the file: safetensors stores raw tensors and a JSON header only
(:mod:`deepprompt_ros.model.safetensors_file`), and anything that is not a well-formed DeepProMP
safetensors file is refused with a message.

The normalization is stored the same way in the baselines' files
(:func:`normalization_tensors`, :func:`read_normalization`), and their loaders check their tensors
against the architecture their file describes the same way (:func:`module_shapes`,
:func:`normalization_shapes`, :func:`check_tensors`).
"""
from __future__ import annotations

import dataclasses
import json
import pathlib
from typing import Callable, Mapping, Sequence

import numpy as np
import torch

from deepprompt_ros.model.network import DeepProMPNet, ModelConfig
from deepprompt_ros.model.safetensors_file import metadata_json, read_safetensors, write_safetensors

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
    ``norm.ctx_std.<name>`` under which a model file stores ``norm`` (copies: the normalization's
    arrays may be read-only, which torch does not support, and stay unshared)."""
    def tensor(v) -> torch.Tensor:
        return torch.as_tensor(np.array(v, dtype=np.float64, copy=True))

    tensors = {"norm.y_mean": tensor(norm.y_mean), "norm.y_std": tensor(norm.y_std)}
    for name in norm.ctx_mean:
        tensors[f"norm.ctx_mean.{name}"] = tensor(norm.ctx_mean[name])
        tensors[f"norm.ctx_std.{name}"] = tensor(norm.ctx_std[name])
    return tensors


def normalization_shapes(n_joints: int, context_dims: Sequence[tuple[str, int]]) -> dict[str, tuple[int, ...]]:
    """Name -> shape of the tensors :func:`normalization_tensors` writes for a model of ``n_joints``
    joints and the contexts ``context_dims`` ((name, c) pairs)."""
    shapes = {"norm.y_mean": (n_joints,), "norm.y_std": (n_joints,)}
    for name, c in context_dims:
        shapes[f"norm.ctx_mean.{name}"] = shapes[f"norm.ctx_std.{name}"] = (c,)
    return shapes


def module_shapes(make: Callable[[], torch.nn.Module], prefix: str = "") -> dict[str, tuple[int, ...]]:
    """Name (``prefix`` + state-dict key) -> shape of the weights of the module ``make()`` builds,
    built on the ``meta`` device: no memory is allocated, so the architecture a file describes can
    be compared with its tensors before a network of that size is built."""
    with torch.device("meta"):
        module = make()
    return {prefix + k: tuple(v.shape) for k, v in module.state_dict().items()}


def check_tensors(tensors: Mapping[str, torch.Tensor], shapes: Mapping[str, tuple[int, ...] | None], path,
                  what: str, error: type[ValueError] = ValueError) -> None:
    """Refuse the tensors of the model file ``path`` unless they are exactly those of ``shapes``
    (name -> shape; None: any shape): none missing, none extra, every shape as given, every tensor
    floating point and finite. ``what`` names where the shapes come from (e.g. "its model
    config"); the message names the first tensor that is wrong."""
    def names(keys):
        keys = sorted(keys)
        return ", ".join(f"'{k}'" for k in keys[:4]) + (f" and {len(keys) - 4} more" if len(keys) > 4 else "")

    missing, extra = set(shapes) - set(tensors), set(tensors) - set(shapes)
    if missing:
        raise error(f"model file '{path}' lacks tensor(s) {names(missing)} that {what} needs")
    if extra:
        raise error(f"model file '{path}' has tensor(s) {names(extra)} that {what} does not have")
    for k, shape in shapes.items():
        v = tensors[k]
        if shape is not None and tuple(v.shape) != tuple(shape):
            raise error(f"model file '{path}': tensor '{k}' has shape {tuple(v.shape)} but {what} needs "
                        f"{tuple(shape)}")
        if not v.is_floating_point():
            raise error(f"model file '{path}': tensor '{k}' has dtype {str(v.dtype).replace('torch.', '')}; "
                        f"expected floating point")
        if not torch.isfinite(v).all():
            raise error(f"model file '{path}': tensor '{k}' contains NaN or inf")


def joint_names_json(meta: Mapping[str, str], key: str, path, error: type[ValueError] = ValueError) -> tuple[str, ...]:
    """The joint names stored as a JSON array under the metadata entry ``key``: distinct non-empty
    strings, else ``error`` naming the file."""
    names = metadata_json(meta, key, path, kind=list, error=error)
    if not all(isinstance(n, str) and n for n in names):
        raise error(f"model file '{path}': metadata entry '{key}' must list joint names as non-empty strings; "
                    f"got {names[:8]}")
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise error(f"model file '{path}': metadata entry '{key}' names joint(s) {dup} more than once")
    return tuple(names)


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
    """Load and validate a checkpoint; raise :class:`CheckpointError` with what is wrong.

    Refused: a path that does not exist or is not a file, a file that is not safetensors (a pickle,
    a truncated or corrupt file, an implausible header size), another format tag, metadata that is
    missing or not the JSON expected (model config, joint names, metadata object), a model config
    that is invalid (e.g. a ``latent_linear`` without a linear basis, larger than the latent or than
    the basis's weights, a ``via_noise`` <= 0) or disagrees with the joint names or the phase type, tensors missing, extra or
    of another shape than the model config's architecture (compared before the network is built,
    so a config that describes a huge network allocates nothing), non-float, NaN or inf tensors,
    and a normalization whose standard deviations are not positive.
    """
    path = pathlib.Path(path)
    meta, tensors = read_safetensors(path, error=CheckpointError, **_WORDING)
    if "format" not in meta:
        raise CheckpointError(f"model file '{path}' has no format tag; expected '{FORMAT}' ({_WORDING['written']})")
    if meta["format"] != FORMAT:
        raise CheckpointError(f"model file '{path}' has format '{meta['format']}'; expected '{FORMAT}'")
    config = metadata_json(meta, "model_config", path, error=CheckpointError)
    try:
        cfg = ModelConfig.from_json(config)
    except (ValueError, TypeError) as exc:
        raise CheckpointError(f"model file '{path}' has invalid metadata: model_config: {exc}") from exc
    joint_names = joint_names_json(meta, "joint_names", path, CheckpointError)
    extra = metadata_json(meta, "metadata", path, default={}, error=CheckpointError)
    if len(joint_names) != cfg.n_joints:
        raise CheckpointError(f"model file '{path}' names {len(joint_names)} joints but its model has {cfg.n_joints}")
    if meta.get("phase_type", cfg.phase_type) != cfg.phase_type:
        raise CheckpointError(f"model file '{path}' has phase type '{meta['phase_type']}' but its model config "
                              f"'{cfg.phase_type}'")
    shapes = module_shapes(lambda: DeepProMPNet(cfg), "net.") | normalization_shapes(cfg.n_joints, cfg.context_dims)
    check_tensors(tensors, shapes, path, f"its model config ({cfg.n_joints} joints, latent_dim {cfg.latent_dim}, "
                  f"hidden {cfg.hidden}, decoder_basis {cfg.decoder_basis}, latent_linear {cfg.latent_linear})",
                  CheckpointError)
    if cfg.decoder_modes:  # the modes' cumulative shares: rising within (0, 1], the last 1
        cum = tensors["net.mode_cumulative_shares"].double()
        if not (bool((cum > 0).all()) and bool((cum[1:] > cum[:-1]).all()) and abs(float(cum[-1]) - 1.0) <= 1e-6):
            raise CheckpointError(f"model file '{path}': tensor 'net.mode_cumulative_shares' is {cum.tolist()}; "
                                  "expected the modes' cumulative shares, strictly rising in (0, 1] and ending at 1")
    norm = read_normalization(tensors, cfg.n_joints, cfg.context_dims, path, CheckpointError)
    state = {k[4:]: v for k, v in tensors.items() if k.startswith("net.")}
    ck = Checkpoint(cfg, state, norm, joint_names, extra)
    ck.build()  # the weights load into the architecture now, so a bad file is refused at load time
    return ck
