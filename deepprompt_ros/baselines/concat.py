"""CNMP and VAE-CNMP, the paper's concatenation baselines (Sec. IV "Empirical Analysis"), and their
Indep variants, behind the common interface
(:class:`deepprompt_ros.baselines.interface.MovementPrimitiveModel`); the network is
:mod:`deepprompt_ros.baselines.concat_net`.

``cnmp``: :class:`CNMP` — Seker et al. 2019 (paper Sec. II-A): ONE encoder φ on the concatenation
[via-point, low-dim contexts, image embedding] of each element, mean aggregation
r = 1/n Σ_i φ(a_i, c) (a deterministic latent), decoder N(μ_y(r, x), σ_y(r, x)²) with
σ_y = softplus + floor, trained by the Gaussian NLL of the demo's points.
``vae_cnmp``: :class:`VAECNMP` — one encoder on the same concatenation giving (μ_i, σ²_i), averaged
(μ_z = mean μ_i, σ²_z = mean σ²_i; no Bayesian aggregation), z ~ N(μ_z, σ²_z), KL to the isotropic
prior N(0, I) (β-weighted, annealed), decoder like DeepProMP's (fixed σ_y).
``cnmp_indep``, ``vae_cnmp_indep``: :class:`CNMPIndep`, :class:`VAECNMPIndep` — the same networks
trained with zero padding for missing inputs, sub-sampling input combinations as DeepProMP does.

Zero padding (paper Sec. IV): a missing via-point part is a zero vector (q(z | a⁰, c) with a⁰ = 0),
a missing context modality or missing images a zero block. The non-Indep models are trained on
every update with via-points (a random count in [1, max_via_points]) AND every context modality
and the images ("because of the concatenation operation"); the Indep models with the combinations
of :func:`deepprompt_ros.training.objectives.sample_subset_weights` (via-points, each context
modality, images, both, nothing). At evaluation, every model gets the same zero padding for what
is missing. Several vectors of one context modality (m > 1) are averaged (after normalization)
before concatenation, as the images of one demonstration are averaged in embedding space. With no
input at all, the encoder sees the single all-zero element.

Training (:meth:`_ConcatBaseline.fit`) reads the same :class:`deepprompt_ros.training.config.TrainConfig`
as DeepProMP: latent_dim, hidden, phase_harmonics, lr, batch_size, steps, n_points,
max_via_points, the sub-sampling probabilities p_via_points / p_context / p_empty (Indep), n_val,
val_every, val_via_points, seed, threads; VAE-CNMP also sigma_y, var_floor, beta and
kl_anneal_steps. The DeepProMP-only keys (objective, consistency_*, prior_kl_weight) are ignored.
Every ``val_every`` updates the validation MSE is measured as in
:func:`deepprompt_ros.training.objectives.validation_mse` (via-points only, contexts only, both;
their mean) and the weights with the lowest mean are kept.

Units: phases x in [0, 1], joint positions in the demonstrations' units (rad), contexts raw;
internally joint positions and low-dimensional contexts are standardized with the training set's
statistics (:func:`deepprompt_ros.training.tensors.fit_normalization`). MSEs are in rad².
Files: safetensors (weights, normalization) + JSON metadata; loaded without pickle.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import math
import time
from typing import Callable, ClassVar

import numpy as np
import torch

from deepprompt_ros.baselines.concat_net import ConcatEncoderNet, ConcatNetConfig
from deepprompt_ros.baselines.interface import (BASELINE_FORMAT, Inputs, InputSpec, MovementPrimitiveModel,
                                                context_mean, provenance, read_baseline_metadata,
                                                split_for_validation)
from deepprompt_ros.model.aggregation import gaussian_kl
from deepprompt_ros.model.checkpoint import (Normalization, check_tensors, module_shapes, normalization_shapes,
                                             normalization_tensors, read_normalization)
from deepprompt_ros.model.phase import phase_features
from deepprompt_ros.model.safetensors_file import metadata_json, read_safetensors, write_safetensors
from deepprompt_ros.primitive.latent import LatentGaussian
from deepprompt_ros.training.config import TrainConfig
from deepprompt_ros.training.objectives import sample_subset_weights, validation_weights
from deepprompt_ros.training.tensors import TensorData, fit_normalization, to_tensors

__all__ = ["DeterministicLatent", "CNMP", "CNMPIndep", "VAECNMP", "VAECNMPIndep"]


@dataclasses.dataclass(frozen=True)
class DeterministicLatent:
    """CNMP's conditioned representation r = 1/n Σ_i φ(e_i) (normalized units), shape (k,)."""

    r: np.ndarray


def _kinds(data: TensorData):
    """(kind, slice) columns in the layout of :func:`deepprompt_ros.training.objectives.sample_subset_weights`."""
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


@functools.lru_cache(maxsize=8)
def _all_inputs_config(cfg: TrainConfig) -> TrainConfig:
    """``cfg`` with every input given on every update (made once per configuration, not per update)."""
    return dataclasses.replace(cfg, p_via_points=1.0, p_context=1.0, p_empty=0.0,
                               max_via_points=max(1, cfg.max_via_points))


def _all_inputs_weights(cfg: TrainConfig, data: TensorData, idx, kinds, gen):
    """Non-Indep sub-sampling: a random via-point subset (as DeepProMP's, count in [1, max_via_points])
    AND every context modality AND the images, on every update."""
    return sample_subset_weights(_all_inputs_config(cfg), data, idx, kinds, gen)[0]


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
        :func:`deepprompt_ros.training.objectives.sample_subset_weights`: Indep → its combinations; else
        via-points AND all contexts."""
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
        :func:`deepprompt_ros.training.objectives.validation_mse`: ``via`` (val_via_points seeded random
        points, contexts zero-padded), ``context`` (all contexts and images, no via-point), ``both``;
        ``mean`` of those."""
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
        """Adam on mini-batches (batch → loss → backward → eval → best weights), like
        :func:`deepprompt_ros.training.loop.train`: same normalization, sub-sampling, KL annealing
        (VAE-CNMP), validation and seeds."""
        cfg = config
        torch.manual_seed(cfg.seed)
        torch.set_num_threads(cfg.threads)
        train_ds, val_ds = split_for_validation(train_ds, cfg, val_ds)
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
        self.metadata = {"train_config": dataclasses.asdict(cfg), "provenance": provenance(train_ds, val_ds),
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
            shared.append(context_mean(inp.contexts[name], norm, name) if name in inp.contexts else np.zeros(c))
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
        tensors = {f"net.{k}": v for k, v in self.net.state_dict().items()} | normalization_tensors(self.norm)
        meta = {"format": BASELINE_FORMAT, "kind": self.kind, "spec": json.dumps(self.spec.to_json()),
                "net_config": json.dumps(self.net.cfg.to_json()),
                "metadata": json.dumps({**self.metadata, "history": self.history}, default=str)}
        return write_safetensors(path, tensors, meta)

    @classmethod
    def load(cls, path):
        meta, tensors = read_safetensors(path)
        spec, extra = read_baseline_metadata(path, meta, cls.kind)
        net_config = metadata_json(meta, "net_config", path)
        try:
            ncfg = ConcatNetConfig.from_json(net_config)
        except (ValueError, TypeError) as exc:
            raise ValueError(f"model file '{path}' has an invalid network config: {exc}") from exc
        if ncfg.variant != cls.variant or ncfg.n_joints != spec.n_joints or ncfg.context_dims != spec.context_dims:
            raise ValueError(f"model file '{path}': network config ({ncfg.variant}, {ncfg.n_joints} joints, contexts "
                             f"{list(ncfg.context_dims)}) does not match a '{cls.kind}' model of {spec.n_joints} "
                             f"joints and contexts {list(spec.context_dims)}")
        history = extra.pop("history", [])
        if not isinstance(history, list):
            raise ValueError(f"model file '{path}': metadata 'history' must be a list; got {type(history).__name__}")
        # shapes first, on the meta device: a config that describes a huge network allocates nothing
        check_tensors(tensors, module_shapes(lambda: ConcatEncoderNet(ncfg), "net.")
                      | normalization_shapes(spec.n_joints, spec.context_dims), path,
                      f"its network config ({ncfg.variant}, latent_dim {ncfg.latent_dim}, hidden {ncfg.hidden})")
        out = cls(std_floor=ncfg.std_floor)
        out.net = ConcatEncoderNet(ncfg)
        try:
            out.net.load_state_dict({k[4:]: v for k, v in tensors.items() if k.startswith("net.")}, strict=True)
        except RuntimeError as exc:
            raise ValueError(f"model file '{path}': weights do not match the stored architecture: {exc}") from exc
        out.net.eval()
        out.spec, out.norm = spec, read_normalization(tensors, spec.n_joints, spec.context_dims, path)
        out.history = history
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

    ``condition`` returns a :class:`deepprompt_ros.primitive.latent.LatentGaussian` N(μ_z, σ²_z) (normalized latent);
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
