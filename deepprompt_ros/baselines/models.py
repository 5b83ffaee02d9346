"""The paper's baselines (Sec. IV "Empirical Analysis") behind one interface shared with DeepProMP.

Six models, one code path for an evaluation harness::

    for cls in MODEL_CLASSES:
        model = cls().fit(train_ds, TrainConfig(...), val_ds)
        err = reconstruction_mse(model, test_ds, "low_dim")

==================  =====================================================================
kind                model
==================  =====================================================================
``deepprompt``      :class:`DeepProMPModel` — adapter: :func:`core.train.train` + :class:`core.primitive.DeepProMP`
``promp``           :class:`ProMPModel` — adapter: :class:`core.promp.ProMP`, contexts through its joint Gaussian
``cnmp``            :class:`CNMP` — Seker et al. 2019 (paper Sec. II-A): ONE encoder φ on the concatenation
                    [via-point, low-dim contexts, image embedding] of each element, mean aggregation
                    r = 1/n Σ_i φ(a_i, c) (a deterministic latent), decoder N(μ_y(r, x), σ_y(r, x)²)
                    with σ_y = softplus + floor, trained by the Gaussian NLL of the demo's points.
``vae_cnmp``        :class:`VAECNMP` — one encoder on the same concatenation giving (μ_i, σ²_i),
                    averaged (μ_z = mean μ_i, σ²_z = mean σ²_i; no Bayesian aggregation), z ~ N(μ_z, σ²_z),
                    KL to the isotropic prior N(0, I) (β-weighted, annealed), decoder like DeepProMP's
                    (fixed σ_y).
``cnmp_indep``      :class:`CNMPIndep`, :class:`VAECNMPIndep` — the same networks trained with zero
``vae_cnmp_indep``  padding for missing inputs, sub-sampling input combinations as DeepProMP does.
==================  =====================================================================

Zero padding (paper Sec. IV): a missing via-point part is a zero vector (q(z | a⁰, c) with a⁰ = 0),
a missing context modality or missing images a zero block. The non-Indep models are trained on
every update with via-points (a random count in [1, max_via_points]) AND every context modality
and the images ("because of the concatenation operation"); the Indep models with the combinations
of :func:`core.train.sample_subset_weights` (via-points, each context modality, images, both,
nothing). At evaluation, every model gets the same zero padding for what is missing. Several
vectors of one context modality (m > 1) are averaged (after normalization) before concatenation,
as the images of one demonstration are averaged in embedding space. With no input at all, the
encoder sees the single all-zero element.

Training (:meth:`_ConcatBaseline.fit`) reads the same :class:`core.train.TrainConfig` as DeepProMP:
latent_dim, hidden, phase_harmonics, lr, batch_size, steps, n_points, max_via_points, the
sub-sampling probabilities p_via_points / p_context / p_empty (Indep), n_val, val_every,
val_via_points, seed, threads; VAE-CNMP also sigma_y, var_floor, beta and kl_anneal_steps. The
DeepProMP-only keys (objective, consistency_*, prior_kl_weight) are ignored. Every
``val_every`` updates the validation MSE is measured as in :func:`core.train.validation_mse`
(via-points only, contexts only, both; their mean) and the weights with the lowest mean are kept.

Units: phases x in [0, 1], joint positions in the demonstrations' units (rad), contexts raw;
internally joint positions and low-dimensional contexts are standardized with the training set's
statistics (:func:`core.train.fit_normalization`). MSEs are in rad².

Files: safetensors (weights, normalization) + JSON metadata; loaded without pickle.
"""
from __future__ import annotations

import abc
import dataclasses
import datetime
import json
import math
import pathlib
import tempfile
import time
from typing import Any, Callable, ClassVar, Mapping, NamedTuple

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from deepprompt_ros import __version__
from deepprompt_ros.model.checkpoint import FORMAT as DEEPPROMP_FORMAT
from deepprompt_ros.model.checkpoint import Normalization, load_checkpoint, save_checkpoint
from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.model.network import ImageEncoder, _mlp_trunk, config_from_json, config_to_json, gaussian_kl, phase_features
from deepprompt_ros.primitive.deep_promp import DeepProMP, LatentGaussian, check_images, check_phases, joint_list_text
from deepprompt_ros.baselines.promp import ProMP
from deepprompt_ros.training.loop import TensorData, TrainConfig, fit_normalization, sample_subset_weights, to_tensors, train, validation_weights

__all__ = [
    "MovementPrimitiveModel", "DeepProMPModel", "ProMPModel", "CNMP", "CNMPIndep", "VAECNMP", "VAECNMPIndep",
    "MODEL_CLASSES", "ConcatNetConfig", "ConcatEncoderNet", "DeterministicLatent", "load_model",
    "CONDITIONINGS", "available_conditionings", "reconstruction_mse", "reconstruction_table",
]

BASELINE_FORMAT = "deepprompt_ros.baseline/1"
_MAX_HEADER = 100 * 1024 * 1024


# ================================================================================================
# Input validation shared by every model
# ================================================================================================

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
        return cls(str(d["name"]), tuple(str(j) for j in d["joint_names"]), str(d["phase_type"]),
                   tuple((str(n), int(c)) for n, c in d["context_dims"]),
                   tuple(int(v) for v in d["image_shape"]) if d.get("image_shape") else None)


# ================================================================================================
# The common interface
# ================================================================================================

class MovementPrimitiveModel(abc.ABC):
    """fit / condition / mean_trajectory / sample / save / load, the same for all six models.

    ``condition`` returns an opaque conditioned object that only the model that made it reads.
    Inputs follow :meth:`core.primitive.DeepProMP.condition`: via_x (n,) phases in [0, 1], via_y (n, d),
    contexts {modality: (m, c) or (c,)}, images (n_img, H, W, 3) uint8.
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


def _split(train_ds: DemoDataset, cfg: TrainConfig, val_ds: DemoDataset | None):
    if val_ds is not None:
        return train_ds, val_ds
    return train_ds.split(cfg.n_val or max(1, len(train_ds) // 10), seed=cfg.seed)


def _provenance(train_ds: DemoDataset, val_ds: DemoDataset | None) -> dict:
    return {"dataset": train_ds.source, "n_train": len(train_ds), "n_val": len(val_ds) if val_ds else 0,
            "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "deepprompt_ros": __version__, "torch": torch.__version__}


def _ctx_mean(c: np.ndarray, norm: Normalization, name: str) -> np.ndarray:
    """(m, c) raw → (c,) normalized, averaged over the m vectors."""
    return ((c - norm.ctx_mean[name]) / norm.ctx_std[name]).mean(0)


# ================================================================================================
# Safetensors files
# ================================================================================================

def _check_header(path) -> pathlib.Path:
    """Refuse a missing file or one that is not safetensors (e.g. a pickle) before opening it."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise ValueError(f"model file '{path}' does not exist; expected a .safetensors model file")
    with open(path, "rb") as f:
        head = f.read(8)
    if len(head) < 8 or int.from_bytes(head, "little") > min(_MAX_HEADER, path.stat().st_size):
        raise ValueError(f"model file '{path}' is not a safetensors file (pickled files are refused: they can run "
                         "code); expected a model written by deepprompt_ros")
    return path


def _read_safetensors(path, tensors: bool = True) -> tuple[dict, dict]:
    """(metadata, tensors) of a safetensors file; anything else raises ValueError."""
    from safetensors import safe_open

    path = _check_header(path)
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = dict(f.metadata() or {})
            out = {k: f.get_tensor(k) for k in f.keys()} if tensors else {}
    except Exception as exc:  # safetensors raises its own error types for corrupt headers
        raise ValueError(f"model file '{path}' is corrupt or not a safetensors file: {exc}") from exc
    return meta, out


def _write_safetensors(path, tensors: Mapping[str, torch.Tensor], meta: Mapping[str, str]) -> pathlib.Path:
    from safetensors.torch import save_file

    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    save_file({k: v.detach().cpu().contiguous() for k, v in tensors.items()}, str(tmp), metadata=dict(meta))
    tmp.replace(path)
    return path


def _norm_tensors(norm: Normalization) -> dict:
    t = {"norm.y_mean": torch.as_tensor(np.asarray(norm.y_mean, dtype=np.float64)),
         "norm.y_std": torch.as_tensor(np.asarray(norm.y_std, dtype=np.float64))}
    for n in norm.ctx_mean:
        t[f"norm.ctx_mean.{n}"] = torch.as_tensor(np.asarray(norm.ctx_mean[n], dtype=np.float64))
        t[f"norm.ctx_std.{n}"] = torch.as_tensor(np.asarray(norm.ctx_std[n], dtype=np.float64))
    return t


def _norm_from(tensors: Mapping, spec: InputSpec, path) -> Normalization:
    try:
        norm = Normalization(
            tensors["norm.y_mean"].numpy(), tensors["norm.y_std"].numpy(),
            {n: tensors[f"norm.ctx_mean.{n}"].numpy() for n, _ in spec.context_dims},
            {n: tensors[f"norm.ctx_std.{n}"].numpy() for n, _ in spec.context_dims})
    except KeyError as exc:
        raise ValueError(f"model file '{path}' lacks normalization tensor {exc}") from exc
    if norm.y_mean.shape != (spec.n_joints,) or norm.y_std.shape != (spec.n_joints,) or not np.all(norm.y_std > 0):
        raise ValueError(f"model file '{path}' has invalid joint normalization")
    for n, c in spec.context_dims:
        if norm.ctx_mean[n].shape != (c,) or not np.all(norm.ctx_std[n] > 0):
            raise ValueError(f"model file '{path}' has invalid normalization for context '{n}'")
    return norm


def _baseline_meta(path, meta: Mapping, kind: str) -> tuple[InputSpec, dict]:
    if meta.get("format") != BASELINE_FORMAT:
        raise ValueError(f"model file '{path}' has format '{meta.get('format')}'; expected '{BASELINE_FORMAT}' "
                         "(use load_model(path) to open any model file)")
    if meta.get("kind") != kind:
        raise ValueError(f"model file '{path}' holds a '{meta.get('kind')}' model, not '{kind}'; use "
                         "load_model(path) to open any model file")
    try:
        spec = InputSpec.from_json(json.loads(meta["spec"]))
        extra = json.loads(meta.get("metadata", "{}"))
    except (KeyError, ValueError, TypeError) as exc:
        raise ValueError(f"model file '{path}' has invalid metadata: {exc}") from exc
    return spec, extra


# ================================================================================================
# Adapters: DeepProMP and ProMP
# ================================================================================================

class DeepProMPModel(MovementPrimitiveModel):
    """DeepProMP (:func:`core.train.train` + :class:`core.primitive.DeepProMP`) behind the common interface.

    The conditioned object is a :class:`core.primitive.LatentGaussian`; files are ordinary DeepProMP
    checkpoints (:func:`core.checkpoint.save_checkpoint`), so the primitive server can load them too.
    """

    kind = "deepprompt"

    def __init__(self, log: Callable[[str], None] | None = None):
        super().__init__()
        self.log = log
        self.primitive: DeepProMP | None = None

    def fit(self, train_ds, config, val_ds=None):
        train_ds, val_ds = _split(train_ds, config, val_ds)
        net, norm, hist = train(train_ds, config, out_path=None, log=self.log or (lambda s: None), val_ds=val_ds)
        self.history = hist
        meta = {"train_config": dataclasses.asdict(config), "provenance": _provenance(train_ds, val_ds),
                "metrics": {"best_val_mse_rad2": min(h["val"]["mean"] for h in hist)}, "model_kind": self.kind}
        self._set(DeepProMP(net, norm, train_ds.joint_names, name=self.kind, metadata=meta))
        return self

    def _set(self, prim: DeepProMP):
        self.primitive = prim
        self.spec = InputSpec(self.kind, prim.joint_names, prim.phase_type, tuple(prim.cfg.context_dims),
                              prim.image_shape)

    def condition(self, via_x=None, via_y=None, contexts=None, images=None) -> LatentGaussian:
        inp = self.check_inputs(via_x, via_y, contexts, images)
        has_via = inp.via_x.size > 0
        return self.primitive.condition(inp.via_x if has_via else None, inp.via_y if has_via else None,
                                        contexts=inp.contexts or None, images=inp.images)

    def _latent(self, cond) -> LatentGaussian:
        if not isinstance(cond, LatentGaussian) or cond.mean.shape != (self.primitive.latent_dim,):
            raise ValueError("expected the conditioned object returned by this DeepProMPModel's condition()")
        return cond

    def mean_trajectory(self, cond, x):
        return self.primitive.mean_trajectory(self._latent(cond), self.spec.check_phases(x))

    def sample(self, cond, x, n, rng=None):
        return self.primitive.sample(self._latent(cond), self.spec.check_phases(x), self._check_n(n), rng)

    def save(self, path):
        self._require_fitted()
        p = self.primitive
        return save_checkpoint(path, p.net, p.norm, p.joint_names, {**p.metadata, "model_kind": self.kind})

    @classmethod
    def load(cls, path):
        out = cls()
        ck = load_checkpoint(path)  # CheckpointError is a ValueError
        out._set(DeepProMP.from_checkpoint(ck, name=cls.kind))
        return out


@dataclasses.dataclass(frozen=True)
class _ProMPOptions:
    n_basis: int = 20
    width: float = 1.0
    via_noise_var: float = 1e-6


class ProMPModel(MovementPrimitiveModel):
    """ProMP (:class:`core.promp.ProMP`) behind the common interface.

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
        train_ds, val_ds = _split(train_ds, config, val_ds)  # the same demos the deep models train on
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
        return np.stack([np.concatenate([_ctx_mean(c[n], self.norm, n) for n, _ in self.spec.context_dims])
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
        tensors = {f"promp.{k}": torch.as_tensor(v) for k, v in arrays.items()} | _norm_tensors(self.norm)
        meta = {"format": BASELINE_FORMAT, "kind": self.kind, "spec": json.dumps(self.spec.to_json()),
                "promp": promp_meta, "options": json.dumps(dataclasses.asdict(self.options)),
                "metadata": json.dumps({"history": self.history}, default=str)}
        return _write_safetensors(path, tensors, meta)

    @classmethod
    def load(cls, path):
        meta, tensors = _read_safetensors(path)
        spec, extra = _baseline_meta(path, meta, cls.kind)
        try:
            out = cls(**json.loads(meta["options"]))
            arrays = {k: tensors[f"promp.{k}"].numpy() for k in ("mean", "cov", "obs_var")}
            promp_meta = meta["promp"]
        except (KeyError, ValueError, TypeError) as exc:
            raise ValueError(f"model file '{path}' has invalid ProMP data: {exc}") from exc
        with tempfile.TemporaryDirectory() as tmp:
            f = pathlib.Path(tmp) / "promp.npz"
            with open(f, "wb") as fh:
                np.savez(fh, meta=np.array(promp_meta), **arrays)
            out.promp = ProMP.load(f)
        out.spec, out.norm = spec, _norm_from(tensors, spec, path)
        out.history = list(extra.get("history", []))
        return out


# ================================================================================================
# CNMP and VAE-CNMP: one encoder on concatenated inputs
# ================================================================================================

VARIANTS = ("cnmp", "vae_cnmp")


@dataclasses.dataclass(frozen=True)
class ConcatNetConfig:
    """Architecture of a CNMP / VAE-CNMP (stored in every file).

    Attributes
    ----------
    variant : {"cnmp", "vae_cnmp"}
    n_joints, phase_type, latent_dim, hidden, context_dims, image_shape, phase_harmonics :
        as :class:`core.model.ModelConfig` (2 hidden ReLU layers of ``hidden`` units everywhere).
    sigma_y : float
        VAE-CNMP's fixed decoder standard deviation (normalized units).
    var_floor : float
        VAE-CNMP's floor of every encoder variance σ²_i.
    std_floor : float
        CNMP's floor of the predicted σ_y(r, x) (normalized units): σ_y = softplus(·) + std_floor.
    """

    variant: str
    n_joints: int
    phase_type: str = "linear"
    latent_dim: int = 16
    hidden: int = 128
    context_dims: tuple[tuple[str, int], ...] = ()
    image_shape: tuple[int, int] | None = None
    sigma_y: float = 0.05
    var_floor: float = 1e-4
    std_floor: float = 1e-2
    phase_harmonics: int = 0

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"variant '{self.variant}' unknown; expected one of {VARIANTS}")
        if self.n_joints < 1 or self.latent_dim < 1 or self.hidden < 1:
            raise ValueError("n_joints, latent_dim and hidden must be >= 1")
        if not (self.sigma_y > 0 and self.var_floor > 0 and self.std_floor > 0):
            raise ValueError("sigma_y, var_floor and std_floor must be > 0")

    @property
    def phase_dim(self) -> int:
        return 2 * max(1, self.phase_harmonics) if self.phase_type == "rhythmic" else 1 + 2 * self.phase_harmonics

    @property
    def context_names(self) -> tuple[str, ...]:
        return tuple(n for n, _ in self.context_dims)

    @property
    def via_dim(self) -> int:
        return self.phase_dim + self.n_joints

    @property
    def input_dim(self) -> int:
        """[φ(x), y] + Σ c_dims + (hidden if images)."""
        return self.via_dim + sum(c for _, c in self.context_dims) + (self.hidden if self.image_shape else 0)

    def to_json(self) -> dict:
        return config_to_json(self)

    @classmethod
    def from_json(cls, d: Mapping) -> "ConcatNetConfig":
        return config_from_json(cls, d, "network config")


class ConcatEncoderNet(nn.Module):
    """Encoder on concatenated element inputs + mean aggregation + decoder (normalized units).

    Element i of a demonstration is e_i = [φ(x_i), y_i, c, emb(images)] (zero blocks for what is
    missing); with no via-point the set is the single element [0, c, emb]. Shapes: B batch, N elements,
    T phases, k latent, d joints.
    """

    def __init__(self, cfg: ConcatNetConfig):
        super().__init__()
        self.cfg = cfg
        h, k = cfg.hidden, cfg.latent_dim
        self.encoder = _mlp_trunk(cfg.input_dim, h)
        self.head = nn.Linear(h, k if cfg.variant == "cnmp" else 2 * k)
        self.image_encoder = ImageEncoder(h) if cfg.image_shape else None
        n_out = 2 * cfg.n_joints if cfg.variant == "cnmp" else cfg.n_joints
        self.decoder = nn.Sequential(nn.Linear(k + cfg.phase_dim, h), nn.ReLU(), nn.Linear(h, h), nn.ReLU(),
                                     nn.Linear(h, n_out))

    def phase_features(self, x: torch.Tensor) -> torch.Tensor:
        return phase_features(x, self.cfg.phase_type, self.cfg.phase_harmonics)

    def elements(self, via: torch.Tensor, via_mask: torch.Tensor, shared: torch.Tensor):
        """Concatenated element inputs with zero padding.

        Parameters
        ----------
        via : (B, N, p + d)   [φ(x_i), y_i] of the candidate via-points
        via_mask : (B, N)     1 = given
        shared : (B, S)       [contexts, image embedding], zeros where missing

        Returns
        -------
        inp : (B, N + 1, input_dim), mask : (B, N + 1) — element N is the zero-via-point element,
        present only when no via-point is given.
        """
        b = via.shape[0]
        via = torch.cat([via * via_mask.unsqueeze(-1), via.new_zeros(b, 1, via.shape[-1])], 1)
        none = (via_mask.sum(1, keepdim=True) == 0).to(via.dtype)
        mask = torch.cat([via_mask, none], 1)
        inp = torch.cat([via, shared.unsqueeze(1).expand(-1, via.shape[1], -1)], -1)
        return inp, mask

    def encode(self, inp: torch.Tensor, mask: torch.Tensor):
        """Mean aggregation over the given elements.

        CNMP: r = 1/n Σ_i φ(e_i) → (r (B, k), None).
        VAE-CNMP: μ_z = 1/n Σ_i μ_i, σ²_z = 1/n Σ_i σ²_i → (μ_z, σ²_z), each (B, k).
        """
        out = self.head(self.encoder(inp))  # (B, N, k or 2k)
        m = mask.unsqueeze(-1)
        n = m.sum(1).clamp_min(1.0)
        if self.cfg.variant == "cnmp":
            return (out * m).sum(1) / n, None
        mu, raw = out.chunk(2, -1)
        var = F.softplus(raw) + self.cfg.var_floor
        return (mu * m).sum(1) / n, (var * m).sum(1) / n

    def decode(self, z: torch.Tensor, x: torch.Tensor):
        """z (B, k), x (T,) → mean (B, T, d) and, for CNMP, σ_y(z, x) (B, T, d) (else None)."""
        zz = z.unsqueeze(1).expand(-1, x.shape[0], -1)
        xf = self.phase_features(x).unsqueeze(0).expand(z.shape[0], -1, -1)
        out = self.decoder(torch.cat([zz, xf], -1))
        if self.cfg.variant == "cnmp":
            mean, raw = out.chunk(2, -1)
            return mean, F.softplus(raw) + self.cfg.std_floor
        return out, None


@dataclasses.dataclass(frozen=True)
class DeterministicLatent:
    """CNMP's conditioned representation r = 1/n Σ_i φ(e_i) (normalized units), shape (k,)."""

    r: np.ndarray


def _kinds(data: TensorData):
    """(kind, slice) columns in the layout of :func:`core.train.sample_subset_weights`."""
    t = data.y.shape[1]
    kinds, start = [("via", slice(0, t))], t
    for name, c in data.ctx.items():
        kinds.append((name, slice(start, start + c.shape[1])))
        start += c.shape[1]
    if data.images is not None:
        kinds.append(("image", slice(start, start + 1)))
    return kinds


def _batch_elements(net: ConcatEncoderNet, data: TensorData, idx: torch.Tensor, w: torch.Tensor, kinds):
    """Element inputs of demos ``idx`` given the input weights w (B, N_total) (1 given, 0 withheld)."""
    y = data.y[idx]
    b = y.shape[0]
    xf = net.phase_features(data.x).unsqueeze(0).expand(b, -1, -1)
    shared = []
    via_mask = None
    for kind, sl in kinds:
        ws = w[:, sl]
        if kind == "via":
            via_mask = ws
        elif kind == "image":
            emb = net.image_encoder(data.images[idx], data.image_mask[idx])  # (B, h)
            shared.append(emb * ws)
        else:  # a low-dim modality: mean of its given vectors, zeros when withheld
            c = data.ctx[kind][idx]
            shared.append((c * ws.unsqueeze(-1)).sum(1) / ws.sum(1, keepdim=True).clamp_min(1.0))
    shared = torch.cat(shared, -1) if shared else y.new_zeros(b, 0)
    return net.elements(torch.cat([xf, y], -1), via_mask, shared)


def _all_inputs_weights(cfg: TrainConfig, data: TensorData, idx, kinds, gen):
    """Non-Indep sub-sampling: a random via-point subset (as DeepProMP's, count in [1, max_via_points])
    AND every context modality AND the images, on every update."""
    always = dataclasses.replace(cfg, p_via_points=1.0, p_context=1.0, p_empty=0.0,
                                 max_via_points=max(1, cfg.max_via_points))
    return sample_subset_weights(always, data, idx, kinds, gen)[0]


class _ConcatBaseline(MovementPrimitiveModel):
    """Shared implementation of the four CNMP / VAE-CNMP models (see module docstring)."""

    variant: ClassVar[str] = ""
    indep: ClassVar[bool] = False

    def __init__(self, std_floor: float = 1e-2, log: Callable[[str], None] | None = None):
        super().__init__()
        self.std_floor = float(std_floor)
        self.log = log
        self.net: ConcatEncoderNet | None = None
        self.norm: Normalization | None = None
        self.metadata: dict = {}

    # -- training ---------------------------------------------------------------------------------
    def input_weights(self, cfg: TrainConfig, data: TensorData, idx, kinds, gen) -> torch.Tensor:
        """Which inputs each demo of the batch is given this update, (B, N_total) in the layout of
        :func:`core.train.sample_subset_weights`: Indep → its combinations; else via-points AND all contexts."""
        if self.indep:
            return sample_subset_weights(cfg, data, idx, kinds, gen)[0]
        return _all_inputs_weights(cfg, data, idx, kinds, gen)

    def loss(self, cfg: TrainConfig, data: TensorData, idx, gen, beta: float):
        """Per-batch loss: CNMP Gaussian NLL of the demos' points; VAE-CNMP negative ELBO (one z per demo).

        Returns
        -------
        loss (tensor), nll (float), kl (float)
        """
        kinds = _kinds(data)
        w = self.input_weights(cfg, data, idx, kinds, gen)
        inp, mask = _batch_elements(self.net, data, idx, w, kinds)
        mu_z, var_z = self.net.encode(inp, mask)
        y = data.y[idx]
        if var_z is None:  # CNMP: deterministic r, decoder predicts N(μ_y, σ_y²)
            mean, std = self.net.decode(mu_z, data.x)
            nll = (torch.log(std) + 0.5 * ((y - mean) / std) ** 2).sum((1, 2))
            return nll.mean(), nll.mean().item(), 0.0
        z = mu_z + torch.randn(mu_z.shape, generator=gen) * var_z.sqrt()  # ONE z per trajectory
        mean, _ = self.net.decode(z, data.x)
        nll = 0.5 * ((y - mean) ** 2).sum((1, 2)) / self.net.cfg.sigma_y ** 2
        zero = torch.zeros(())
        kl = gaussian_kl(mu_z, var_z, zero, zero + 1.0)  # KL(q(z | inputs) ‖ N(0, I))
        loss = (nll + beta * kl).mean()
        return loss, nll.mean().item(), kl.mean().item()

    @torch.no_grad()
    def validation_mse(self, cfg: TrainConfig, data: TensorData) -> dict:
        """Held-out MSE (rad²) of the mean prediction, with the conditionings of
        :func:`core.train.validation_mse`: ``via`` (val_via_points seeded random points, contexts
        zero-padded), ``context`` (all contexts and images, no via-point), ``both``; ``mean`` of those."""
        net = self.net.eval()
        kinds = _kinds(data)
        idx = torch.arange(data.y.shape[0])
        scale = torch.tensor(self.norm.y_std, dtype=torch.float32)
        out = {}
        for name, w in validation_weights(cfg, data, kinds).items():
            inp, mask = _batch_elements(net, data, idx, w, kinds)
            z, _ = net.encode(inp, mask)
            mean, _ = net.decode(z, data.x)
            out[name] = float((((mean - data.y) * scale) ** 2).mean())
        out["mean"] = float(np.mean(list(out.values())))
        net.train()
        return out

    def fit(self, train_ds, config, val_ds=None):
        """Adam on mini-batches (batch → loss → backward → eval → best weights), like :func:`core.train.train`:
        same normalization, sub-sampling, KL annealing (VAE-CNMP), validation and seeds."""
        cfg = config
        torch.manual_seed(cfg.seed)
        torch.set_num_threads(cfg.threads)
        train_ds, val_ds = _split(train_ds, cfg, val_ds)
        self.spec = InputSpec.from_dataset(self.kind, train_ds)
        self.norm = fit_normalization(train_ds, cfg.n_points)
        data = to_tensors(train_ds, self.norm, cfg.n_points)
        val = to_tensors(val_ds, self.norm, cfg.n_points)
        ncfg = ConcatNetConfig(self.variant, len(train_ds.joint_names), train_ds.phase_type, cfg.latent_dim,
                               cfg.hidden, tuple(train_ds.context_dims.items()), train_ds.image_shape, cfg.sigma_y,
                               cfg.var_floor, self.std_floor, cfg.phase_harmonics)
        self.net = ConcatEncoderNet(ncfg)
        opt = torch.optim.Adam(self.net.parameters(), lr=cfg.lr)
        gen = torch.Generator().manual_seed(cfg.seed)
        log = self.log or (lambda s: None)
        self.history, best, best_state = [], math.inf, None
        t0 = time.perf_counter()
        n_train = data.y.shape[0]
        for step in range(1, cfg.steps + 1):
            idx = torch.randint(0, n_train, (cfg.batch_size,), generator=gen)
            beta = cfg.beta * min(1.0, step / max(1, cfg.kl_anneal_steps))  # KL annealing (VAE-CNMP)
            loss, nll, kl = self.loss(cfg, data, idx, gen, beta)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            if step % cfg.val_every == 0 or step == cfg.steps:
                v = self.validation_mse(cfg, val)
                elapsed = time.perf_counter() - t0
                rec = {"step": step, "loss": loss.item(), "nll": nll, "kl": kl, "beta": beta, "val": v,
                       "samples_per_s": step * cfg.batch_size / elapsed}
                self.history.append(rec)
                mark = ""
                if v["mean"] < best:
                    best, mark = v["mean"], " *best"
                    best_state = {k: t.clone() for k, t in self.net.state_dict().items()}
                log(f"[{self.kind}] step {step:6d}/{cfg.steps}  loss {loss.item():10.3f}  nll {nll:9.3f}  "
                    f"kl {kl:8.3f}  val_mse {v['mean']:.3e} rad²{mark}")
        self.net.load_state_dict(best_state)
        self.net.eval()
        self.metadata = {"train_config": dataclasses.asdict(cfg), "provenance": _provenance(train_ds, val_ds),
                         "metrics": {"best_val_mse_rad2": best, "wall_time_s": time.perf_counter() - t0}}
        return self

    # -- operations ---------------------------------------------------------------------------
    @torch.no_grad()
    def _encode(self, inp: Inputs):
        """Validated inputs → aggregated latent, (k,) numpy arrays (μ or r, and σ² or None)."""
        net, norm, cfg = self.net, self.norm, self.net.cfg
        yn = (inp.via_y - norm.y_mean) / norm.y_std
        via = np.concatenate([phase_features(inp.via_x, cfg.phase_type, cfg.phase_harmonics).reshape(-1, cfg.phase_dim),
                              yn], 1)
        shared = []
        for name, c in cfg.context_dims:
            shared.append(_ctx_mean(inp.contexts[name], norm, name) if name in inp.contexts else np.zeros(c))
        shared = torch.tensor(np.concatenate(shared) if shared else np.zeros(0), dtype=torch.float32)[None]
        if net.image_encoder is not None:
            if inp.images is None:
                emb = torch.zeros(1, cfg.hidden)
            else:
                im = torch.from_numpy(np.ascontiguousarray(inp.images)).permute(0, 3, 1, 2).float()[None] / 255.0
                emb = net.image_encoder(im, torch.ones(1, im.shape[1]))
            shared = torch.cat([shared, emb], -1)
        via_t = torch.tensor(via, dtype=torch.float32)[None]
        elems, mask = net.elements(via_t, torch.ones(1, via_t.shape[1]), shared)
        z, var = net.encode(elems, mask)
        return z[0].double().numpy(), None if var is None else var[0].double().numpy()

    @torch.no_grad()
    def _decode(self, z: np.ndarray, x: np.ndarray):
        """z (n, k) normalized → mean (n, T, d) rad, std (n, T, d) rad or None."""
        mean, std = self.net.decode(torch.tensor(z, dtype=torch.float32), torch.tensor(x, dtype=torch.float32))
        y_std = np.asarray(self.norm.y_std)
        mean = mean.double().numpy() * y_std + self.norm.y_mean
        return mean, None if std is None else std.double().numpy() * y_std

    def save(self, path):
        self._require_fitted()
        tensors = {f"net.{k}": v for k, v in self.net.state_dict().items()} | _norm_tensors(self.norm)
        meta = {"format": BASELINE_FORMAT, "kind": self.kind, "spec": json.dumps(self.spec.to_json()),
                "net_config": json.dumps(self.net.cfg.to_json()),
                "metadata": json.dumps({**self.metadata, "history": self.history}, default=str)}
        return _write_safetensors(path, tensors, meta)

    @classmethod
    def load(cls, path):
        meta, tensors = _read_safetensors(path)
        spec, extra = _baseline_meta(path, meta, cls.kind)
        try:
            ncfg = ConcatNetConfig.from_json(json.loads(meta["net_config"]))
        except (KeyError, ValueError, TypeError) as exc:
            raise ValueError(f"model file '{path}' has an invalid network config: {exc}") from exc
        if ncfg.variant != cls.variant or ncfg.n_joints != spec.n_joints:
            raise ValueError(f"model file '{path}': network config ({ncfg.variant}, {ncfg.n_joints} joints) does not "
                             f"match a '{cls.kind}' model of {spec.n_joints} joints")
        for k, v in tensors.items():
            if v.is_floating_point() and not torch.isfinite(v).all():
                raise ValueError(f"model file '{path}': tensor '{k}' contains NaN or inf")
        out = cls(std_floor=ncfg.std_floor)
        out.net = ConcatEncoderNet(ncfg)
        try:
            out.net.load_state_dict({k[4:]: v for k, v in tensors.items() if k.startswith("net.")}, strict=True)
        except RuntimeError as exc:
            raise ValueError(f"model file '{path}': weights do not match the stored architecture: {exc}") from exc
        out.net.eval()
        out.spec, out.norm = spec, _norm_from(tensors, spec, path)
        out.history = list(extra.pop("history", []))
        out.metadata = extra
        return out


class CNMP(_ConcatBaseline):
    """Conditional Neural Movement Primitive (Seker et al. 2019; paper Sec. II-A, IV).

    ``condition`` returns a :class:`DeterministicLatent` r; ``mean_trajectory`` is μ_y(r, x);
    ``sample`` draws y = μ_y(r, x) + σ_y(r, x) ε with ε independent per phase and joint (the
    model's predictive distribution — r is deterministic, so all of its uncertainty is per point).
    """

    kind = "cnmp"
    variant = "cnmp"
    indep = False
    independent_inputs = False

    def condition(self, via_x=None, via_y=None, contexts=None, images=None) -> DeterministicLatent:
        """Zero padding for what is missing (see module docstring)."""
        r, _ = self._encode(self.check_inputs(via_x, via_y, contexts, images))
        return DeterministicLatent(r)

    def _r(self, cond) -> np.ndarray:
        if not isinstance(cond, DeterministicLatent) or cond.r.shape != (self.net.cfg.latent_dim,):
            raise ValueError(f"expected the conditioned object returned by this {type(self).__name__}'s condition()")
        return cond.r

    def mean_trajectory(self, cond, x):
        return self._decode(self._r(cond)[None], self.spec.check_phases(x))[0][0]

    def std_trajectory(self, cond, x) -> np.ndarray:
        """σ_y(r, x) in joint units, shape (T, d)."""
        return self._decode(self._r(cond)[None], self.spec.check_phases(x))[1][0]

    def sample(self, cond, x, n, rng=None):
        mean, std = self._decode(self._r(cond)[None], self.spec.check_phases(x))
        rng = np.random.default_rng(rng)
        return mean + std * rng.standard_normal((self._check_n(n),) + mean.shape[1:])


class CNMPIndep(CNMP):
    """CNMP trained with zero padding and sub-sampled input combinations (paper: "CNMP (Indep)")."""

    kind = "cnmp_indep"
    indep = True
    independent_inputs = True


class VAECNMP(_ConcatBaseline):
    """VAE-CNMP (paper Sec. IV): concatenated inputs, averaged (μ_i, σ²_i), isotropic prior.

    ``condition`` returns a :class:`core.primitive.LatentGaussian` N(μ_z, σ²_z) (normalized latent);
    ``mean_trajectory`` decodes μ_z; ``sample`` draws ONE z per trajectory and decodes it.
    With no input at all the encoder sees one all-zero element; :meth:`prior` gives N(0, I).
    """

    kind = "vae_cnmp"
    variant = "vae_cnmp"
    indep = False
    independent_inputs = False

    def condition(self, via_x=None, via_y=None, contexts=None, images=None) -> LatentGaussian:
        mu, var = self._encode(self.check_inputs(via_x, via_y, contexts, images))
        return LatentGaussian(mu, var)

    def prior(self) -> LatentGaussian:
        k = self.net.cfg.latent_dim
        return LatentGaussian(np.zeros(k), np.ones(k))

    def _latent(self, cond) -> LatentGaussian:
        if not isinstance(cond, LatentGaussian) or cond.mean.shape != (self.net.cfg.latent_dim,):
            raise ValueError(f"expected the conditioned object returned by this {type(self).__name__}'s condition()")
        return cond

    def mean_trajectory(self, cond, x):
        return self._decode(self._latent(cond).mean[None], self.spec.check_phases(x))[0][0]

    def sample(self, cond, x, n, rng=None):
        lat = self._latent(cond)
        x = self.spec.check_phases(x)
        rng = np.random.default_rng(rng)
        z = lat.mean + rng.standard_normal((self._check_n(n), lat.mean.shape[0])) * lat.std
        return self._decode(z, x)[0]


class VAECNMPIndep(VAECNMP):
    """VAE-CNMP trained with zero padding and sub-sampled input combinations ("VAE-CNMP (Indep)")."""

    kind = "vae_cnmp_indep"
    indep = True
    independent_inputs = True


MODEL_CLASSES: tuple[type[MovementPrimitiveModel], ...] = (
    DeepProMPModel, ProMPModel, CNMP, CNMPIndep, VAECNMP, VAECNMPIndep)
_BY_KIND = {c.kind: c for c in MODEL_CLASSES}


def load_model(path) -> MovementPrimitiveModel:
    """Open any model file written by one of :data:`MODEL_CLASSES` (dispatch on its metadata)."""
    meta, _ = _read_safetensors(path, tensors=False)
    if meta.get("format") == DEEPPROMP_FORMAT:
        return DeepProMPModel.load(path)
    if meta.get("format") == BASELINE_FORMAT and meta.get("kind") in _BY_KIND:
        return _BY_KIND[meta["kind"]].load(path)
    raise ValueError(f"model file '{path}' has format '{meta.get('format')}' kind '{meta.get('kind')}'; expected "
                     f"'{DEEPPROMP_FORMAT}' or '{BASELINE_FORMAT}' with kind in {sorted(_BY_KIND)}")


# ================================================================================================
# Reconstruction metric (paper Sec. IV, Fig. "radar plots")
# ================================================================================================

CONDITIONINGS = ("via_point", "image", "low_dim", "image+low", "aggregate")


def available_conditionings(model: MovementPrimitiveModel, ds: DemoDataset) -> tuple[str, ...]:
    """The conditionings of :data:`CONDITIONINGS` (without "aggregate") that ``model`` and ``ds`` both
    support: "via_point" always; "low_dim" if the data has low-dim contexts; "image" if it has images
    and the model takes them (not ProMP); "image+low" if both."""
    low = bool(ds.context_dims) and bool(model.context_dims)
    img = ds.image_shape is not None and model.supports_images and model.image_shape is not None
    out = ["via_point"]
    if img:
        out.append("image")
    if low:
        out.append("low_dim")
    if img and low:
        out.append("image+low")
    return tuple(out)


def reconstruction_mse(model: MovementPrimitiveModel, test: DemoDataset, conditioning: str,
                       n_via: int | None = None, n_points: int = 100, seed: int = 0) -> float:
    """Mean squared error (rad²) of reconstructing held-out demonstrations (paper Sec. IV).

    Each demo is resampled on ``n_points`` equally spaced phases; the model is conditioned and its
    ``mean_trajectory`` compared with the demo on that grid (mean over demos, phases and joints).

    Conditionings (paper: "for each context variable input, we include the initial robot position"):

    ``via_point``  via-points only, no context. ``n_via=None`` (default, the paper's setting): the
                   full trajectory as via-points (all ``n_points`` points); an int k: k points per demo
                   drawn without replacement by ``np.random.default_rng([seed, demo index])`` (a fixed
                   seeded set, identical for every model).
    ``image``      the first point (x=0, y_0) + the demo's images.
    ``low_dim``    the first point + every low-dimensional context modality.
    ``image+low``  the first point + images + low-dimensional contexts.
    ``aggregate``  the mean of the MSEs of the above that :func:`available_conditionings` lists.

    Raises ValueError for an unknown conditioning or one the model / data do not support.
    """
    if conditioning not in CONDITIONINGS:
        raise ValueError(f"conditioning '{conditioning}' unknown; expected one of {CONDITIONINGS}")
    if int(n_points) != n_points or n_points < 2:
        raise ValueError(f"n_points must be an integer >= 2, got {n_points}")
    if n_via is not None and (int(n_via) != n_via or not 1 <= n_via <= n_points):
        raise ValueError(f"n_via must be None (all points) or an integer in [1, n_points={n_points}], got {n_via}")
    avail = available_conditionings(model, test)
    if conditioning == "aggregate":
        return float(np.mean([reconstruction_mse(model, test, c, n_via, n_points, seed) for c in avail]))
    if conditioning not in avail:
        raise ValueError(f"conditioning '{conditioning}' is not available for model '{model.kind}' on dataset "
                         f"'{test.source}' (contexts {test.context_dims or 'none'}, images "
                         f"{'yes' if test.image_shape else 'none'}); available: {avail}")
    x = np.linspace(0.0, 1.0, n_points)
    errs = []
    for i, demo in enumerate(test.demos):
        y = demo.resampled(n_points)
        kw = {}
        if conditioning == "via_point":
            sel = np.arange(n_points) if n_via is None else np.sort(
                np.random.default_rng([seed, i]).choice(n_points, int(n_via), replace=False))
            kw.update(via_x=x[sel], via_y=y[sel])
        else:
            kw.update(via_x=x[:1], via_y=y[:1])
            if conditioning in ("low_dim", "image+low"):
                kw["contexts"] = dict(demo.contexts)
            if conditioning in ("image", "image+low"):
                kw["images"] = demo.images
        pred = model.mean_trajectory(model.condition(**kw), x)
        errs.append(float(((pred - y) ** 2).mean()))
    return float(np.mean(errs))


def reconstruction_table(model: MovementPrimitiveModel, test: DemoDataset, n_via: int | None = None,
                         n_points: int = 100, seed: int = 0) -> dict[str, float]:
    """All available conditionings and their "aggregate": {conditioning: MSE (rad²)}."""
    out = {c: reconstruction_mse(model, test, c, n_via, n_points, seed) for c in available_conditionings(model, test)}
    out["aggregate"] = float(np.mean(list(out.values())))
    return out
