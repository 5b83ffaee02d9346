"""ProMP behind the common interface (:class:`deepprompt_ros.baselines.interface.MovementPrimitiveModel`):
an adapter over :class:`deepprompt_ros.baselines.promp.ProMP` with contexts through its joint
Gaussian of weights and context vectors; files are safetensors like the other baselines'."""
from __future__ import annotations

import dataclasses
import json
import logging
import pathlib
import tempfile
import time
from typing import Callable

import numpy as np
import torch

from deepprompt_ros.baselines.interface import (BASELINE_FORMAT, InputSpec, MovementPrimitiveModel, context_mean,
                                                read_baseline_metadata, split_for_validation)
from deepprompt_ros.baselines.promp import ProMP
from deepprompt_ros.baselines.promp_selection import ProMPSelection, select_promp
from deepprompt_ros.evaluation.reconstruction import reconstruction_mse
from deepprompt_ros.model.checkpoint import (Normalization, check_tensors, normalization_shapes, normalization_tensors,
                                             read_normalization)
from deepprompt_ros.model.safetensors_file import metadata_json, read_safetensors, write_safetensors
from deepprompt_ros.training.tensors import fit_normalization

__all__ = ["ProMPModel"]


#: Used when the training split has fewer than 3 demonstrations (no cross-validation possible):
#: the regularizer scale of ProMP's own default and a via-point noise of 1e-3 normalized units.
FALLBACK_COV_REG_SCALE = 0.05
FALLBACK_VIA_NOISE = 1e-3


@dataclasses.dataclass(frozen=True)
class _ProMPOptions:
    n_basis: int = 20
    width: float = 1.0
    cov_reg_scale: float | str = "auto"
    via_noise: float | str = "auto"


class ProMPModel(MovementPrimitiveModel):
    """ProMP (:class:`deepprompt_ros.baselines.promp.ProMP`) behind the common interface.

    Contexts: the normalized low-dimensional modalities (each averaged over its m vectors, in sorted
    modality order) are stacked into one vector c per demonstration and modelled jointly Gaussian
    with the weights; conditioning on c is Gaussian conditioning of that joint distribution
    (:meth:`ProMP.condition_context`), then via-points condition the result (:meth:`ProMP.condition`,
    noise standard deviation ``via_noise`` · y_std_j for joint j, y_std the training normalization's).
    ProMP takes no images; all modalities or none. The conditioned object is a conditioned :class:`ProMP`.

    By default (``"auto"``) the covariance regularizer and the via-point noise are chosen by
    cross-validation on the training demos (:func:`deepprompt_ros.baselines.promp_selection.select_promp`);
    the values used are ``cov_reg_scale`` and ``via_noise`` after ``fit``, the cross-validation is
    ``selection`` (None when a value was given or the split has fewer than 3 demos), and ``fit`` logs them.

    Parameters
    ----------
    n_basis, width : basis of :class:`ProMP` (RBF, or von Mises for rhythmic datasets)
    cov_reg_scale : "auto" or float >= 0, λ relative to the weight variance (:class:`ProMP`'s ``cov_reg_scale``)
    via_noise : "auto" or float > 0, via-point standard deviation in normalized joint units used by ``condition``
    log : where ``fit`` reports the values used (default: this module's logger, level INFO)
    """

    kind = "promp"
    supports_images = False

    def __init__(self, n_basis: int = 20, width: float = 1.0, cov_reg_scale: float | str = "auto",
                 via_noise: float | str = "auto", log: Callable[[str], None] | None = None):
        super().__init__()
        for name, v, ok in (("cov_reg_scale", cov_reg_scale, lambda f: f >= 0), ("via_noise", via_noise, lambda f: f > 0)):
            if v != "auto" and not (isinstance(v, (int, float)) and np.isfinite(v) and ok(v)):
                raise ValueError(f"ProMPModel {name} must be 'auto' or a finite number "
                                 f"{'>= 0' if name == 'cov_reg_scale' else '> 0'}; got {v!r}")
        self.options = _ProMPOptions(int(n_basis), float(width),
                                     *(v if v == "auto" else float(v) for v in (cov_reg_scale, via_noise)))
        self.log = log or logging.getLogger(__name__).info
        self.promp: ProMP | None = None
        self.norm: Normalization | None = None
        self.cov_reg_scale = self.via_noise = float("nan")
        self.selection: ProMPSelection | None = None

    def fit(self, train_ds, config, val_ds=None):
        """Closed-form fit on ``train_ds`` resampled at ``config.n_points`` (deterministic in
        ``config.seed``). The "auto" hyper-parameters are chosen by cross-validation on the training
        split alone; the validation demos — ``val_ds`` or the same split as the deep models — are left
        out of the fit and of the selection and only fill ``history`` with their validation MSE."""
        t0 = time.perf_counter()
        train_ds, val_ds = split_for_validation(train_ds, config, val_ds)  # the same demos the deep models train on
        self.spec = InputSpec.from_dataset(self.kind, train_ds)
        self.norm = fit_normalization(train_ds, config.n_points)
        o = self.options
        Y = np.stack([d.resampled(config.n_points) for d in train_ds.demos])
        x = np.linspace(0.0, 1.0, config.n_points)
        rhythmic = train_ds.phase_type == "rhythmic"
        self._select(Y, x, rhythmic, config.seed)
        ctx = self._stack_contexts([d.contexts for d in train_ds.demos])
        self.promp = ProMP(self.spec.n_joints, o.n_basis, rhythmic=rhythmic, width=o.width,
                           cov_reg_scale=self.cov_reg_scale, joint_names=self.spec.joint_names).fit(Y, x, contexts=ctx)
        rec = {"step": 0, "wall_time_s": time.perf_counter() - t0}
        rec["val"] = {"via_point": reconstruction_mse(self, val_ds, "via_point", n_via=config.val_via_points,
                                                          n_points=config.n_points, seed=12345)}
        self.history = [rec]
        self.log(f"ProMP: cov_reg_scale {self.cov_reg_scale:g} (λ = {self.promp.cov_reg_used:.3g} rad²), via_noise "
                 f"{self.via_noise:g} normalized units; " + (
                     f"chosen by {self.selection.folds}-fold cross-validation on the {self.selection.n_demos} "
                     f"training demos (CV MSE {self.selection.cv_mse:.3e} rad²)" if self.selection else
                     "as given" if "auto" not in (o.cov_reg_scale, o.via_noise) else
                     f"fallback values: {len(Y)} training demos are too few to cross-validate"))
        return self

    def _select(self, Y: np.ndarray, x: np.ndarray, rhythmic: bool, seed: int) -> None:
        """``cov_reg_scale`` and ``via_noise``: the given values, else cross-validated on Y (N, T, d), the
        training demos (the fallback values below 3 demos)."""
        o = self.options
        self.selection = None
        auto = [v == "auto" for v in (o.cov_reg_scale, o.via_noise)]
        if any(auto) and len(Y) >= 3:
            grid = {} if all(auto) else ({"via_noises": (o.via_noise,)} if auto[0] else
                                         {"cov_reg_scales": (o.cov_reg_scale,)})
            self.selection = select_promp(Y, x, n_basis=o.n_basis, width=o.width, rhythmic=rhythmic, seed=seed,
                                          **grid)
        sel = self.selection
        self.cov_reg_scale = (sel.cov_reg_scale if sel else FALLBACK_COV_REG_SCALE) if auto[0] else o.cov_reg_scale
        self.via_noise = (sel.via_noise if sel else FALLBACK_VIA_NOISE) if auto[1] else o.via_noise

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
            pm = pm.condition(inp.via_x, inp.via_y, noise_var=self.via_noise_var)
        return pm

    @property
    def via_noise_var(self) -> np.ndarray:
        """(d,) the via-point noise variance of each joint in ``condition``, rad²: (``via_noise`` · y_std_j)²."""
        self._require_fitted()
        return (self.via_noise * np.asarray(self.norm.y_std, dtype=np.float64)) ** 2

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
                "metadata": json.dumps({"history": self.history, "cov_reg_scale": self.cov_reg_scale,
                                        "via_noise": self.via_noise,
                                        "selection": self.selection.to_json() if self.selection else None},
                                       default=str)}
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
        try:
            out.cov_reg_scale, out.via_noise = float(extra["cov_reg_scale"]), float(extra["via_noise"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"model file '{path}': metadata lacks a number for the ProMP's cov_reg_scale and "
                             f"via_noise ({exc!r})") from None
        if not (np.isfinite(out.via_noise) and out.via_noise > 0):
            raise ValueError(f"model file '{path}': via_noise must be a number > 0; got {out.via_noise}")
        sel = extra.get("selection")
        if sel is not None:
            try:
                out.selection = ProMPSelection(**{**sel, "table": tuple(tuple(r) for r in sel["table"])})
            except (TypeError, KeyError) as exc:
                raise ValueError(f"model file '{path}': invalid ProMP selection metadata ({exc})") from None
        return out
