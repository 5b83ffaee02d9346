"""ProMP behind the common interface (:class:`deepprompt_ros.baselines.interface.MovementPrimitiveModel`):
an adapter over :class:`deepprompt_ros.baselines.promp.ProMP` with contexts through its joint
Gaussian of weights and context vectors; files are safetensors like the other baselines'."""
from __future__ import annotations

import dataclasses
import json
import pathlib
import tempfile
import time

import numpy as np
import torch

from deepprompt_ros.baselines.interface import (BASELINE_FORMAT, InputSpec, MovementPrimitiveModel, context_mean,
                                                read_baseline_metadata, split_for_validation)
from deepprompt_ros.baselines.promp import ProMP
from deepprompt_ros.evaluation.reconstruction import reconstruction_mse
from deepprompt_ros.model.checkpoint import (Normalization, check_tensors, normalization_shapes, normalization_tensors,
                                             read_normalization)
from deepprompt_ros.model.safetensors_file import metadata_json, read_safetensors, write_safetensors
from deepprompt_ros.training.tensors import fit_normalization

__all__ = ["ProMPModel"]


@dataclasses.dataclass(frozen=True)
class _ProMPOptions:
    n_basis: int = 20
    width: float = 1.0
    via_noise_var: float = 1e-6


class ProMPModel(MovementPrimitiveModel):
    """ProMP (:class:`deepprompt_ros.baselines.promp.ProMP`) behind the common interface.

    Contexts: the normalized low-dimensional modalities (each averaged over its m vectors, in sorted
    modality order) are stacked into one vector c per demonstration and modelled jointly Gaussian
    with the weights; conditioning on c is Gaussian conditioning of that joint distribution
    (:meth:`ProMP.condition_context`), then via-points condition the result (:meth:`ProMP.condition`,
    noise variance ``via_noise_var`` rad²). ProMP takes no images; all modalities or none.
    The conditioned object is a conditioned :class:`ProMP`.

    Parameters
    ----------
    n_basis, width : basis of :class:`ProMP` (RBF, or von Mises for rhythmic datasets)
    via_noise_var : float, via-point variance used by ``condition``
    """

    kind = "promp"
    supports_images = False

    def __init__(self, n_basis: int = 20, width: float = 1.0, via_noise_var: float = 1e-6):
        super().__init__()
        self.options = _ProMPOptions(int(n_basis), float(width), float(via_noise_var))
        self.promp: ProMP | None = None
        self.norm: Normalization | None = None

    def fit(self, train_ds, config, val_ds=None):
        """Closed-form fit on ``train_ds`` resampled at ``config.n_points`` (deterministic: there are no
        weights to select; the validation demos — ``val_ds`` or the same split as the deep models —
        are left out of the fit and only fill ``history`` with their validation MSE)."""
        t0 = time.perf_counter()
        train_ds, val_ds = split_for_validation(train_ds, config, val_ds)  # the same demos the deep models train on
        self.spec = InputSpec.from_dataset(self.kind, train_ds)
        self.norm = fit_normalization(train_ds, config.n_points)
        o = self.options
        Y = np.stack([d.resampled(config.n_points) for d in train_ds.demos])
        x = np.linspace(0.0, 1.0, config.n_points)
        ctx = self._stack_contexts([d.contexts for d in train_ds.demos])
        self.promp = ProMP(self.spec.n_joints, o.n_basis, rhythmic=train_ds.phase_type == "rhythmic",
                           width=o.width, joint_names=self.spec.joint_names).fit(Y, x, contexts=ctx)
        rec = {"step": 0, "wall_time_s": time.perf_counter() - t0}
        rec["val"] = {"via_point": reconstruction_mse(self, val_ds, "via_point", n_via=config.val_via_points,
                                                          n_points=config.n_points, seed=12345)}
        self.history = [rec]
        return self

    def _stack_contexts(self, ctx_list) -> np.ndarray | None:
        if not self.spec.context_dims:
            return None
        return np.stack([np.concatenate([context_mean(c[n], self.norm, n) for n, _ in self.spec.context_dims])
                         for c in ctx_list])

    def condition(self, via_x=None, via_y=None, contexts=None, images=None) -> ProMP:
        if images is not None:
            raise ValueError("ProMP takes no images (its context conditioning is a joint Gaussian of weights and "
                             "low-dimensional context vectors); condition on via-points and low-dimensional "
                             "contexts")
        inp = self.check_inputs(via_x, via_y, contexts)
        pm = self.promp
        if inp.contexts:
            missing = sorted(set(self.context_dims) - set(inp.contexts))
            if missing:
                raise ValueError(f"ProMP conditions on all its context modalities {sorted(self.context_dims)} at "
                                 f"once; missing {missing}")
            pm = pm.condition_context(self._stack_contexts([inp.contexts])[0])
        if inp.via_x.size:
            pm = pm.condition(inp.via_x, inp.via_y, noise_var=self.options.via_noise_var)
        return pm

    @staticmethod
    def _promp(cond) -> ProMP:
        if not isinstance(cond, ProMP):
            raise ValueError("expected the conditioned object returned by this ProMPModel's condition()")
        return cond

    def mean_trajectory(self, cond, x):
        return self._promp(cond).mean_trajectory(self.spec.check_phases(x))

    def sample(self, cond, x, n, rng=None):
        return self._promp(cond).sample(self.spec.check_phases(x), self._check_n(n), rng)

    def save(self, path):
        self._require_fitted()
        with tempfile.TemporaryDirectory() as tmp:
            f = pathlib.Path(tmp) / "promp.npz"
            self.promp.save(f)
            with np.load(f, allow_pickle=False) as z:
                arrays = {k: z[k] for k in ("mean", "cov", "obs_var")}
                promp_meta = str(z["meta"])
        tensors = {f"promp.{k}": torch.as_tensor(v) for k, v in arrays.items()} | normalization_tensors(self.norm)
        meta = {"format": BASELINE_FORMAT, "kind": self.kind, "spec": json.dumps(self.spec.to_json()),
                "promp": promp_meta, "options": json.dumps(dataclasses.asdict(self.options)),
                "metadata": json.dumps({"history": self.history}, default=str)}
        return write_safetensors(path, tensors, meta)

    @classmethod
    def load(cls, path):
        meta, tensors = read_safetensors(path)
        spec, extra = read_baseline_metadata(path, meta, cls.kind)
        options = metadata_json(meta, "options", path)
        try:
            out = cls(**options)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"model file '{path}' has invalid ProMP options {options}: {exc}") from exc
        if "promp" not in meta:
            raise ValueError(f"model file '{path}' lacks the metadata entry 'promp'; expected a file written by "
                             "deepprompt_ros")
        arrays = ("mean", "cov", "obs_var")  # shapes: checked against the ProMP metadata below
        check_tensors(tensors, {f"promp.{k}": None for k in arrays}
                      | normalization_shapes(spec.n_joints, spec.context_dims), path, "a ProMP model of its spec")
        out.promp = ProMP.from_arrays(*(tensors[f"promp.{k}"].numpy() for k in arrays), meta["promp"],
                                      f"model file '{path}'")
        if out.promp.n_joints != spec.n_joints:
            raise ValueError(f"model file '{path}': its ProMP has {out.promp.n_joints} joints, its spec "
                             f"{spec.n_joints}")
        out.spec, out.norm = spec, read_normalization(tensors, spec.n_joints, spec.context_dims, path)
        history = extra.get("history", [])
        if not isinstance(history, list):
            raise ValueError(f"model file '{path}': metadata 'history' must be a list; got {type(history).__name__}")
        out.history = list(history)
        return out
