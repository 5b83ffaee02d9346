"""Training a DeepProMP (paper Sec. III-B): read top to bottom — batch → loss → backward → eval → checkpoint.

Command line::

    python -m deepprompt_ros.training.loop --data DATASET_DIR --config config/train.yaml --out models/NAME.safetensors
    python -m deepprompt_ros.training.loop --builtin bimodal_sine --config config/train_bimodal_sine.yaml --out ...

Objectives (``objective`` in the YAML):

``paper``  the paper's rewritten ELBO: z ~ q(z | subset), reconstruct the whole demonstration,
           plus β Σ_i KL(q(z|a_i) ‖ p0) over the given elements (the "KL of each per-element
           posterior to the prior"). The literal term E_q[log q(z|a_i) − log p0(z)] is unbounded
           below (μ_i far away with small σ_i drives it to −∞: measured −7e14 within 200 updates),
           so the per-element KL, which is ≥ 0, is used.
``np``     Neural-Process form: z ~ q(z | all points + all contexts), reconstruct the demonstration,
           β KL(q(z | all) ‖ q(z | subset)). With a subset that cannot tell modes apart, q(z|subset)
           must cover every mode that is consistent with it — the property that keeps conditioned
           samples multimodal (the paper's objective averages the modes instead; see README).

Every update sub-samples which inputs are given: via-points (a random count), each context
modality, images, their combinations, and sometimes nothing (the prior).
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import pathlib
import sys
import time
from typing import Mapping, Sequence

import numpy as np
import torch

from deepprompt_ros import __version__
from deepprompt_ros.model.checkpoint import Normalization, save_checkpoint
from deepprompt_ros.data.builtin import builtin_dataset
from deepprompt_ros.data.demo_dataset import DemoDataset, load_dataset
from deepprompt_ros.data.demonstration import DatasetError
from deepprompt_ros.model.network import DeepProMPNet, ModelConfig, bayesian_aggregate, gaussian_kl, phase_basis

OBJECTIVES = ("paper", "np")
CONSISTENCY_ENCODER = ("none", "coverage", "all")
BASIS_INITS = ("random", "pca")
BASIS_COV_REG_UNITS = ("normalized", "raw")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Training hyper-parameters (YAML keys of the same names; unknown keys are refused)."""

    latent_dim: int = 16
    hidden: int = 128
    sigma_y: float = 0.05
    var_floor: float = 1e-4
    variance_head: str = "softplus"
    phase_harmonics: int = 0
    decoder_basis: int = 0
    basis_width: float = 1.0
    residual_scale: float = 1.0
    basis_init: str = "random"
    basis_lr_scale: float = 1.0
    basis_cov_reg: float = 0.0
    basis_cov_reg_units: str = "normalized"  # λI added in normalized or in raw (rad) weight units; see pca_basis
    objective: str = "np"
    beta: float = 1.0
    kl_anneal_steps: int = 1000
    lr: float = 1e-3
    batch_size: int = 16
    steps: int = 4000
    n_points: int = 100
    max_via_points: int = 10
    p_via_points: float = 0.7
    p_context: float = 0.5
    p_empty: float = 0.1
    p_low_info: float = 0.0
    low_info_fraction: float = 0.2
    consistency_weight: float = 0.0
    prior_kl_weight: float = 0.0
    consistency_tol: float = 0.15
    consistency_samples: int = 8
    consistency_encoder: str = "none"
    n_val: int = 0  # 0 → 10 % of the demonstrations (at least 1)
    val_every: int = 250
    val_via_points: int = 5
    seed: int = 0
    threads: int = 2

    def __post_init__(self):
        checks = [
            (self.objective in OBJECTIVES, f"objective must be one of {OBJECTIVES}, got '{self.objective}'"),
            (self.latent_dim >= 1 and self.hidden >= 1, "latent_dim and hidden must be >= 1"),
            (self.sigma_y > 0 and self.var_floor > 0, "sigma_y and var_floor must be > 0"),
            (self.beta >= 0, f"beta must be >= 0, got {self.beta}"),
            (self.prior_kl_weight >= 0, f"prior_kl_weight must be >= 0, got {self.prior_kl_weight}"),
            (self.consistency_weight >= 0 and self.consistency_tol > 0,
             "consistency_weight must be >= 0 and consistency_tol > 0"),
            (self.consistency_encoder in CONSISTENCY_ENCODER,
             f"consistency_encoder must be one of {CONSISTENCY_ENCODER}, got '{self.consistency_encoder}'"),
            (self.lr > 0, f"lr must be > 0, got {self.lr}"),
            (self.batch_size >= 1 and self.steps >= 1, "batch_size and steps must be >= 1"),
            (self.n_points >= 2, f"n_points must be >= 2, got {self.n_points}"),
            (0 <= self.max_via_points <= self.n_points, f"max_via_points must be in [0, n_points={self.n_points}]"),
            (all(0 <= p <= 1 for p in (self.p_via_points, self.p_context, self.p_empty, self.p_low_info)),
             "p_via_points, p_context, p_empty, p_low_info must be probabilities in [0, 1]"),
            (0 < self.low_info_fraction <= 1, f"low_info_fraction must be in (0, 1], got {self.low_info_fraction}"),
            (self.val_every >= 1 and self.threads >= 1, "val_every and threads must be >= 1"),
            (self.decoder_basis == 0 or self.decoder_basis >= 2, "decoder_basis must be 0 or >= 2"),
            (self.basis_width > 0 and self.residual_scale >= 0, "basis_width must be > 0 and residual_scale >= 0"),
            (self.basis_cov_reg >= 0, f"basis_cov_reg must be >= 0, got {self.basis_cov_reg}"),
            (self.basis_lr_scale >= 0, f"basis_lr_scale must be >= 0, got {self.basis_lr_scale}"),
            (self.basis_cov_reg_units in BASIS_COV_REG_UNITS,
             f"basis_cov_reg_units must be one of {BASIS_COV_REG_UNITS}, got '{self.basis_cov_reg_units}'"),
            (self.basis_init in BASIS_INITS, f"basis_init must be one of {BASIS_INITS}, got '{self.basis_init}'"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ValueError(f"invalid training config: {msg}")

    @classmethod
    def from_yaml(cls, path) -> "TrainConfig":
        import yaml

        path = pathlib.Path(path)
        if not path.is_file():
            raise ValueError(f"training config '{path}' does not exist; expected a YAML file")
        try:
            raw = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise ValueError(f"training config '{path}' is not valid YAML: {exc}") from exc
        if not isinstance(raw, dict):
            raise ValueError(f"training config '{path}' must be a mapping of keys to values")
        return cls.from_dict(raw, str(path))

    @classmethod
    def from_dict(cls, raw: Mapping, where: str = "config") -> "TrainConfig":
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(raw) - set(fields))
        if unknown:
            raise ValueError(f"{where}: unknown keys {unknown}; valid keys: {sorted(fields)}")
        kw = {}
        for k, v in raw.items():
            typ = type(getattr(cls(), k))
            if typ is float and isinstance(v, int) and not isinstance(v, bool):
                v = float(v)
            if not isinstance(v, typ) or (typ is int and isinstance(v, bool)):
                raise ValueError(f"{where}: '{k}' must be {typ.__name__}, got {v!r}")
            kw[k] = v
        return cls(**kw)


@dataclasses.dataclass(frozen=True)
class TensorData:
    """A dataset as padded tensors (normalized units).

    y : (D, T, d); x : (T,); ctx[name] : (D, M, c) with ctx_mask[name] (D, M);
    images : (D, n, 3, H, W) float in [0, 1] with image_mask (D, n), or None.
    """

    y: torch.Tensor
    x: torch.Tensor
    ctx: Mapping[str, torch.Tensor]
    ctx_mask: Mapping[str, torch.Tensor]
    images: torch.Tensor | None
    image_mask: torch.Tensor | None


def fit_normalization(ds: DemoDataset, n_points: int) -> Normalization:
    y = np.stack([d.resampled(n_points) for d in ds.demos])  # (D, T, d)
    y_std = np.maximum(y.reshape(-1, y.shape[-1]).std(0), 1e-3)
    ctx_mean, ctx_std = {}, {}
    for name in ds.context_dims:
        c = np.concatenate([d.contexts[name] for d in ds.demos], 0)
        ctx_mean[name] = c.mean(0)
        ctx_std[name] = np.maximum(c.std(0), 1e-3)
    return Normalization(y.reshape(-1, y.shape[-1]).mean(0), y_std, ctx_mean, ctx_std)


def to_tensors(ds: DemoDataset, norm: Normalization, n_points: int) -> TensorData:
    y = np.stack([d.resampled(n_points) for d in ds.demos])
    y = (y - norm.y_mean) / norm.y_std
    ctx, ctx_mask = {}, {}
    for name in ds.context_dims:
        m = max(d.contexts[name].shape[0] for d in ds.demos)
        arr = np.zeros((len(ds), m, ds.context_dims[name]))
        mask = np.zeros((len(ds), m))
        for i, d in enumerate(ds.demos):
            c = d.contexts[name]
            arr[i, : len(c)] = (c - norm.ctx_mean[name]) / norm.ctx_std[name]
            mask[i, : len(c)] = 1.0
        ctx[name] = torch.tensor(arr, dtype=torch.float32)
        ctx_mask[name] = torch.tensor(mask, dtype=torch.float32)
    images = image_mask = None
    if ds.image_shape is not None:
        n = max(d.images.shape[0] for d in ds.demos)
        h, w = ds.image_shape
        images = torch.zeros(len(ds), n, 3, h, w)
        image_mask = torch.zeros(len(ds), n)
        for i, d in enumerate(ds.demos):
            images[i, : len(d.images)] = torch.from_numpy(d.images).permute(0, 3, 1, 2).float() / 255.0
            image_mask[i, : len(d.images)] = 1.0
    return TensorData(torch.tensor(y, dtype=torch.float32), torch.linspace(0, 1, n_points), ctx, ctx_mask,
                      images, image_mask)


def encode_all(net: DeepProMPNet, data: TensorData, idx: torch.Tensor):
    """Encode every element of the demos ``idx``: all T points as via-points, all contexts, images.

    Returns
    -------
    mu, var : (B, N_total, k); kinds : list of (kind, slice) naming which columns are which.
    """
    b = idx.shape[0]
    y = data.y[idx]
    x = data.x.unsqueeze(0).expand(b, -1)
    mus, vars_, kinds, start = [], [], [], 0
    mu, var = net.encode_via_points(x, y)
    mus.append(mu), vars_.append(var)
    kinds.append(("via", slice(0, y.shape[1])))
    start = y.shape[1]
    for name in net.cfg.context_names:
        mu, var = net.encode_context(name, data.ctx[name][idx])
        mus.append(mu), vars_.append(var)
        kinds.append((name, slice(start, start + mu.shape[1])))
        start += mu.shape[1]
    if net.image_encoder is not None:
        mu, var = net.encode_images(data.images[idx], data.image_mask[idx])
        mus.append(mu), vars_.append(var)
        kinds.append(("image", slice(start, start + 1)))
        start += 1
    return torch.cat(mus, 1), torch.cat(vars_, 1), kinds


def sample_subset_weights(cfg: TrainConfig, data: TensorData, idx: torch.Tensor, kinds, gen: torch.Generator):
    """Which inputs each trajectory of the batch is given this update (1 = given, 0 = withheld).

    Via-points: with probability p_via_points, a random count in [1, max_via_points] (skewed towards
    small counts) of randomly placed points; each context modality / the images: with probability p_context;
    with probability p_empty nothing at all (the prior).

    Low-information subsets (``p_low_info``): that fraction of the via-point subsets is drawn only
    from the phases where the demonstrations of the batch agree most (the ``low_info_fraction`` of
    phases with the smallest across-demo spread: shared start points, the zero crossings of the
    bimodal sines). Such points cannot tell the demonstrations apart, so the NP objective teaches the
    encoder to give them a large σ²_i — otherwise a few of them aggregate into a narrow posterior
    that sits between the modes (the failure in README "Multimodality").

    Returns
    -------
    w_sub, w_all : (B, N_total)   subset weights and all-elements weights (padding masked).
    """
    b, t = idx.shape[0], data.y.shape[1]
    parts_sub, parts_all = [], []
    empty = torch.rand(b, generator=gen) < cfg.p_empty
    for kind, sl in kinds:
        n = sl.stop - sl.start
        if kind == "via":
            use = (torch.rand(b, generator=gen) < cfg.p_via_points) & ~empty
            # count in [1, max_via_points], skewed towards few points (count = 1 + ⌊u² max⌋): small
            # sets are where a primitive must stay uncertain, and they are the rare case otherwise
            u = torch.rand(b, generator=gen)
            count = 1 + (u * u * cfg.max_via_points).long().clamp_max(max(cfg.max_via_points - 1, 0))
            key = torch.rand(b, t, generator=gen)
            if cfg.p_low_info > 0:
                spread = data.y[idx].std(0).mean(-1)  # (T,) across-demo spread per phase (normalized units)
                n_low = max(1, int(round(cfg.low_info_fraction * t)))
                high = torch.ones(t, dtype=torch.bool)
                high[spread.argsort()[:n_low]] = False
                low_rows = torch.rand(b, generator=gen) < cfg.p_low_info
                key = key + 2.0 * (low_rows.unsqueeze(1) & high.unsqueeze(0)).float()  # informative phases last
                # uniform counts here: several uninformative points must stay as uninformative as one
                low_count = 1 + (torch.rand(b, generator=gen) * min(cfg.max_via_points, n_low)).long()
                count = torch.where(low_rows, low_count.clamp_max(n_low), count)
            rank = key.argsort(1).argsort(1)  # random rank of each point
            sub = (rank < count.unsqueeze(1)) & use.unsqueeze(1)
            parts_sub.append(sub.float())
            parts_all.append(torch.ones(b, n))
        else:
            mask = data.image_mask[idx].amax(1, keepdim=True) if kind == "image" else data.ctx_mask[kind][idx]
            use = (torch.rand(b, generator=gen) < cfg.p_context) & ~empty
            parts_sub.append(mask * use.float().unsqueeze(1))
            parts_all.append(mask)
    return torch.cat(parts_sub, 1), torch.cat(parts_all, 1)


def consistent_demos(cfg: TrainConfig, data: TensorData, idx, kinds, w_sub) -> torch.Tensor:
    """C[i, j] = True when demo j of the batch agrees with everything demo i's subset gives:
    its joint positions at i's via-points (within ``consistency_tol``, normalized units), its
    contexts of the given modalities (same tolerance), and — images being high-dimensional —
    j == i when i's images are given. C[i, i] is always True; an empty subset admits every demo.
    """
    b = idx.shape[0]
    ok = torch.ones(b, b, dtype=torch.bool)
    for kind, sl in kinds:
        w = w_sub[:, sl] > 0  # (B, n)
        if kind == "via":
            y = data.y[idx]  # (B, T, d)
            dev = (y.unsqueeze(0) - y.unsqueeze(1)).abs().amax(-1)  # (B_i, B_j, T)
            dev = torch.where(w.unsqueeze(1), dev, torch.zeros(()))
            ok &= dev.amax(-1) <= cfg.consistency_tol
        elif kind == "image":
            ok &= ~w[:, 0:1] | torch.eye(b, dtype=torch.bool)
        else:
            c = data.ctx[kind][idx]  # (B, M, c)
            dev = (c.unsqueeze(0) - c.unsqueeze(1)).abs().amax(-1)  # (B_i, B_j, M)
            dev = torch.where(w.unsqueeze(1), dev, torch.zeros(()))
            ok &= dev.amax(-1) <= cfg.consistency_tol
    return ok | torch.eye(b, dtype=torch.bool)


def loss_fn(net: DeepProMPNet, cfg: TrainConfig, data: TensorData, idx, gen, beta: float):
    """Negative ELBO per trajectory (mean over the batch) plus the sample-consistency term.

    Returns
    -------
    loss (tensor), nll, kl, consistency (floats, batch means)
    """
    mu, var, kinds = encode_all(net, data, idx)
    w_sub, w_all = sample_subset_weights(cfg, data, idx, kinds, gen)
    mu_s, var_s = bayesian_aggregate(mu, var, w_sub)
    y = data.y[idx]
    if cfg.objective == "np":
        mu_a, var_a = bayesian_aggregate(mu, var, w_all)
        z = mu_a + torch.randn(mu_a.shape, generator=gen) * var_a.sqrt()  # ONE z per trajectory
        kl = gaussian_kl(mu_a, var_a, mu_s, var_s)
        if cfg.prior_kl_weight > 0:  # VAE term: the posteriors of whole demos fill the prior
            zeros = torch.zeros(())
            kl = kl + cfg.prior_kl_weight * gaussian_kl(mu_a, var_a, zeros, zeros + 1.0)
    else:
        z = mu_s + torch.randn(mu_s.shape, generator=gen) * var_s.sqrt()
        zeros = torch.zeros(())
        kl = (w_sub * gaussian_kl(mu, var, zeros, zeros + 1.0)).sum(1)  # Σ_i ω_i KL(q(z|a_i) ‖ p0)
    y_hat = net.decode(z, data.x)
    nll = 0.5 * ((y - y_hat) ** 2).sum((1, 2)) / cfg.sigma_y ** 2
    loss = nll + beta * kl
    cons = torch.zeros(())
    if cfg.consistency_weight > 0:
        # Sample consistency (Chamfer distance between sets): the M trajectories decoded from
        # z ~ q(z | subset) and the demonstrations of the batch that agree with the subset must
        # match as sets — every sample near SOME consistent demo (no sample between modes) and
        # every consistent demo near some sample (no mode dropped). ``consistency_encoder`` says
        # which part reaches the encoder through z: "none" (only the KL shapes q(z | subset); this
        # term shapes the decoder), "coverage" (the coverage part widens q(z | subset) until its
        # samples reach every consistent mode; the precision part, which any single mode
        # satisfies, stays a decoder term), "all".
        m = cfg.consistency_samples
        eps = torch.randn((mu_s.shape[0], m, mu_s.shape[1]), generator=gen)
        z_s = mu_s.unsqueeze(1) + eps * var_s.sqrt().unsqueeze(1)  # (B, M, k)
        ok = consistent_demos(cfg, data, idx, kinds, w_sub).unsqueeze(1)  # (B_i, 1, B_j)

        def sample_errors(z):  # (B_i, M, B_j): squared distance of every sample to every demo
            y_s = net.decode(z.reshape(-1, z.shape[-1]), data.x).reshape(z.shape[0], m, *y.shape[1:])
            return ((y_s.unsqueeze(2) - y.unsqueeze(0).unsqueeze(0)) ** 2).sum((3, 4))

        err = sample_errors(z_s if cfg.consistency_encoder == "all" else z_s.detach())
        inf = torch.full((), float("inf"))
        precision = torch.where(ok, err, inf).amin(2).mean(1)  # nearest consistent demo per sample
        cover = (sample_errors(z_s) if cfg.consistency_encoder == "coverage" else err).amin(1)  # nearest sample per demo
        okf = ok.squeeze(1).float()
        coverage = (cover * okf).sum(1) / okf.sum(1)
        cons = 0.5 * (precision + coverage) / cfg.sigma_y ** 2
        loss = loss + cfg.consistency_weight * cons
    return loss.mean(), nll.mean().item(), kl.mean().item(), cons.mean().item()


def validation_weights(cfg: TrainConfig, data: TensorData, kinds) -> dict:
    """The fixed (seeded) conditionings of the validation MSE, as element weights (B, N_total):
    ``via`` (val_via_points random points per demo), and — when there are contexts or images —
    ``context`` (all of them, no via-point) and ``both``."""
    b, t = data.y.shape[:2]
    gen = torch.Generator().manual_seed(12345)
    rank = torch.rand(b, t, generator=gen).argsort(1).argsort(1)
    via = (rank < cfg.val_via_points).float()
    weights = {"via": [], "context": [], "both": []}
    for kind, sl in kinds:
        n = sl.stop - sl.start
        if kind == "via":
            weights["via"].append(via), weights["both"].append(via), weights["context"].append(torch.zeros(b, n))
        else:
            mask = data.image_mask.amax(1, keepdim=True) if kind == "image" else data.ctx_mask[kind]
            weights["via"].append(torch.zeros(b, n)), weights["context"].append(mask), weights["both"].append(mask)
    return {name: torch.cat(parts, 1) for name, parts in weights.items() if name == "via" or len(kinds) > 1}


@torch.no_grad()
def validation_mse(net: DeepProMPNet, cfg: TrainConfig, data: TensorData, norm: Normalization) -> dict:
    """Held-out reconstruction MSE (rad²), decoding at the posterior mean, for the conditionings of
    :func:`validation_weights`; ``mean`` averages the available ones."""
    net.eval()
    mu, var, kinds = encode_all(net, data, torch.arange(data.y.shape[0]))
    scale = torch.tensor(norm.y_std, dtype=torch.float32)
    out = {}
    for name, w in validation_weights(cfg, data, kinds).items():
        mu_z, _ = bayesian_aggregate(mu, var, w)
        err = (net.decode(mu_z, data.x) - data.y) * scale
        out[name] = float((err ** 2).mean())
    out["mean"] = float(np.mean(list(out.values())))
    net.train()
    return out


def pca_basis(phi: np.ndarray, y: np.ndarray, latent_dim: int, cov_reg: float = 0.0,
              ridge: float = 1e-6, joint_std: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The PPCA of demonstrations in a basis (numpy, float64) — the computation behind
    :func:`init_basis_pca`: per demo the ridge-regression weights W_i (rows b·d + j), b = their mean,
    the k = ``latent_dim`` columns of A = the top-k eigenvectors of their covariance C + R times the
    square root of the eigenvalue.

    The regularizer R (``basis_cov_reg_units``): with ``joint_std`` None, R = λI in the normalized
    units of ``y``, λ = ``cov_reg`` · mean(diag C); with ``joint_std`` (d,) — the joints' normalization
    standard deviations, rad — R is λI in rad, ProMP's regularizer (:meth:`core.promp.ProMP.fit`):
    R = λ D⁻², D = diag(std of each row's joint), λ = ``cov_reg`` · mean(diag DCD). The two differ when
    the joints' ranges differ: in normalized units a small-range joint gets as much extra variance as a
    large-range one, in rad as much in absolute terms.

    Parameters
    ----------
    phi : (T, n_b) basis at the demos' phases; y : (D, T, d) demos (normalized units)

    Returns
    -------
    mean (n_b·d,), a (n_b·d, k), scale (k,) — the columns' standard deviations (0 beyond n_b·d)
    """
    gram = phi.T @ phi
    gram = gram + ridge * np.trace(gram) / gram.shape[0] * np.eye(gram.shape[0])
    w = np.linalg.solve(gram, np.einsum("tb,ntd->nbd", phi, y))  # (D, n_b, d)
    n_b, d = w.shape[1], w.shape[2]
    w = w.reshape(w.shape[0], -1)
    mean = w.mean(0)
    if joint_std is None:
        _, sv, vt = np.linalg.svd(w - mean, full_matrices=True)  # vt: all n_b·d directions, data span first
        eig = np.zeros(vt.shape[0])
        eig[: sv.size] = sv ** 2 / max(1, w.shape[0] - 1)
        eig += cov_reg * eig.sum() / eig.size
    else:
        std = np.tile(np.asarray(joint_std, dtype=np.float64).reshape(d), n_b)  # row b·d + j → std of joint j
        dev = w - mean
        cov = dev.T @ dev / max(1, w.shape[0] - 1)
        lam = cov_reg * float(np.mean(np.diag(cov) * std ** 2))
        eig, vec = np.linalg.eigh(cov + np.diag(lam / std ** 2))
        eig, vt = np.clip(eig[::-1], 0.0, None), vec[:, ::-1].T  # largest first
    r = min(latent_dim, vt.shape[0])
    scale = np.zeros(latent_dim)
    scale[:r] = np.sqrt(eig[:r])
    a = np.zeros((w.shape[1], latent_dim))
    a[:, :r] = (vt[:r] * scale[:r, None]).T
    return mean, a, scale


@torch.no_grad()
def init_basis_pca(net: DeepProMPNet, data: TensorData, cov_reg: float = 0.0, ridge: float = 1e-6,
                   joint_std: np.ndarray | None = None) -> np.ndarray:
    """Initialize the decoder's linear part Φ(x)(b + A z) as the PPCA of the training demos
    (``basis_init: pca``): per demo the ridge-regression weights W_i of the basis (normalized units),
    b = their mean, the columns of A = the top-k eigenvectors of their covariance C + λI scaled by
    the square root of the eigenvalue, so z ~ N(0, I) reproduces C + λI in those k directions.
    λ = ``cov_reg`` · mean(diag C) (ProMP's regularizer, :meth:`core.promp.ProMP.fit`, uses 0.05):
    it gives the k − rank(C) directions beyond the demos' span a small variance instead of none.
    With λ = 0 those columns stay 0. ``joint_std`` (the normalization's, rad): λI in rad instead
    (``basis_cov_reg_units: raw``, :func:`pca_basis`). Returns the standard deviations of the k columns."""
    phi = net.basis_functions(data.x.double()).numpy()  # (T, n_b)
    mean, a, scale = pca_basis(phi, data.y.double().numpy(), net.cfg.latent_dim, cov_reg, ridge, joint_std)
    net.basis.bias.copy_(torch.as_tensor(mean, dtype=torch.float32))
    net.basis.weight.copy_(torch.as_tensor(a, dtype=torch.float32))
    return scale


def linear_map_condition(phi_all: np.ndarray, mean: np.ndarray, a: np.ndarray, sel: np.ndarray, y_via: np.ndarray,
                         noise: np.ndarray) -> np.ndarray:
    """MAP (= posterior mean) of the latent linear-Gaussian model y(x) = Φ(x)(b + A z) + ε, z ~ N(0, I),
    ε_j ~ N(0, noise_j²), given y at the phases ``phi_all[sel]`` (normalized units): the closed form of
    :meth:`DeepProMP.refine_map` (prior ``standard``) for a decoder with ``residual_scale`` 0.

    phi_all : (T, n_b); mean (n_b·d,), a (n_b·d, k) of :func:`pca_basis`; y_via (V, d); noise (d,).
    Returns the trajectory at all T phases, (T, d)."""
    T, n_b = phi_all.shape
    d = y_via.shape[1]
    k = a.shape[1]
    wm = mean.reshape(n_b, d)
    wa = a.reshape(n_b, d, k)
    ph = phi_all[sel]  # (V, n_b)
    jac = np.einsum("vb,bdk->vdk", ph, wa) / noise[None, :, None]  # (V, d, k)
    res = (y_via - ph @ wm) / noise[None, :]
    J = jac.reshape(-1, k)
    z = np.linalg.solve(J.T @ J + np.eye(k), J.T @ res.reshape(-1))
    return phi_all @ (wm + wa @ z)


def fold_assignment(n: int, folds: int, seed: int) -> np.ndarray:
    """The fold (0 … ``folds`` − 1) of each of ``n`` items for K-fold cross-validation: a seeded
    permutation dealt round-robin, so fold sizes differ by at most one."""
    fold_of = np.empty(n, dtype=int)
    fold_of[np.random.default_rng(seed).permutation(n)] = np.arange(n) % folds
    return fold_of


def cv_basis_hyperparameters(ds: DemoDataset, n_points: int, n_basis: int, basis_width: float = 1.0,
                             latent_dims=(64,), cov_regs=(0.05,), noise_stds=(1e-3,), n_via: int = 5,
                             folds: int = 0, draws: int = 4, seed: int = 0,
                             cov_reg_units: Sequence[str] = ("normalized",)) -> dict:
    """Choose the linear part's latent size, ``basis_cov_reg`` λ, the units of λ
    (``basis_cov_reg_units``, :func:`pca_basis`) and the via-point noise (rad, one value for all
    joints) of MAP conditioning by K-fold cross-validation on the demonstrations ``ds`` alone.

    Per fold: the normalization (:func:`fit_normalization`) and the PPCA (:func:`pca_basis`) are fitted
    to the other demos, and each held-out demo is conditioned on ``draws`` sets of ``n_via`` random
    via-points (:func:`linear_map_condition`, the closed form of MAP refinement with the standard
    prior); the score is the mean held-out MSE (rad²) over all 100 phases. ``folds`` 0 = leave-one-out.
    Deterministic in ``seed``.

    Returns {"latent_dim", "basis_cov_reg", "basis_cov_reg_units", "noise_std", "cv_mse",
    "table": [[k, λ, s, mse, units], ...]}.
    """
    demos = ds.demos
    n = len(demos)
    if n < 3:
        raise ValueError(f"cross-validation needs >= 3 demonstrations, got {n}")
    folds = n if folds <= 0 else min(int(folds), n)
    fold_of = fold_assignment(n, folds, seed)
    x = np.linspace(0.0, 1.0, n_points)
    phi = phase_basis(x, n_basis, basis_width, ds.phase_type == "rhythmic")
    y_all = np.stack([d.resampled(n_points) for d in demos])  # (n, T, d) rad
    sels = [[np.sort(np.random.default_rng([seed, i, r]).choice(n_points, int(n_via), replace=False))
             for r in range(draws)] for i in range(n)]
    bad = [u for u in cov_reg_units if u not in BASIS_COV_REG_UNITS]
    if bad or not cov_reg_units:
        raise ValueError(f"cov_reg_units must be a non-empty selection of {BASIS_COV_REG_UNITS}, "
                         f"got {tuple(cov_reg_units)}")
    grid = [(int(k), float(c), float(s), str(u)) for k in latent_dims for c in cov_regs for s in noise_stds
            for u in dict.fromkeys(cov_reg_units)]
    err = {g: [] for g in grid}
    for f in range(folds):
        tr = np.flatnonzero(fold_of != f)
        te = np.flatnonzero(fold_of == f)
        norm = fit_normalization(DemoDataset(tuple(demos[i] for i in tr), ds.source), n_points)
        yn = (y_all - norm.y_mean) / norm.y_std
        std = np.asarray(norm.y_std, dtype=np.float64)
        fits = {(k, c, u): pca_basis(phi, yn[tr], k, c, joint_std=std if u == "raw" else None)
                for (k, c, _, u) in grid}
        for g in grid:
            k, c, s, u = g
            mean, a, _ = fits[(k, c, u)]
            noise = s / std
            for i in te:
                for sel in sels[i]:
                    pred = linear_map_condition(phi, mean, a, sel, yn[i, sel], noise) * norm.y_std + norm.y_mean
                    err[g].append(float(((pred - y_all[i]) ** 2).mean()))
    table = [[k, c, s, float(np.mean(err[(k, c, s, u)])), u] for (k, c, s, u) in grid]
    best = min(table, key=lambda r: r[3])
    return {"latent_dim": best[0], "basis_cov_reg": best[1], "basis_cov_reg_units": best[4], "noise_std": best[2],
            "cv_mse": best[3],
            "folds": folds, "draws": draws, "n_demos": n, "table": table}


def train(ds: DemoDataset, cfg: TrainConfig, out_path=None, log=print, val_ds: DemoDataset | None = None):
    """Train on ``ds`` (a validation split is held out unless ``val_ds`` is given).

    Returns
    -------
    net : DeepProMPNet (best validation weights), norm : Normalization, history : list of dict
    """
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    if val_ds is None:
        n_val = cfg.n_val or max(1, len(ds) // 10)
        train_ds, val_ds = ds.split(n_val, seed=cfg.seed)
    else:
        train_ds = ds
    norm = fit_normalization(train_ds, cfg.n_points)
    data = to_tensors(train_ds, norm, cfg.n_points)
    val = to_tensors(val_ds, norm, cfg.n_points)
    mcfg = ModelConfig(n_joints=len(ds.joint_names), phase_type=ds.phase_type, latent_dim=cfg.latent_dim,
                       hidden=cfg.hidden, context_dims=tuple(ds.context_dims.items()), image_shape=ds.image_shape,
                       sigma_y=cfg.sigma_y, var_floor=cfg.var_floor, phase_harmonics=cfg.phase_harmonics,
                       decoder_basis=cfg.decoder_basis, basis_width=cfg.basis_width,
                       residual_scale=cfg.residual_scale, variance_head=cfg.variance_head)
    net = DeepProMPNet(mcfg)
    if cfg.decoder_basis and cfg.basis_init == "pca":
        init_basis_pca(net, data, cfg.basis_cov_reg,
                       joint_std=np.asarray(norm.y_std) if cfg.basis_cov_reg_units == "raw" else None)
    if cfg.decoder_basis:  # the linear part learns at lr · basis_lr_scale (0: kept as initialized)
        rest = [p for n, p in net.named_parameters() if not n.startswith("basis.")]
        groups = [{"params": rest}]
        if cfg.basis_lr_scale > 0:
            groups.append({"params": list(net.basis.parameters()), "lr": cfg.lr * cfg.basis_lr_scale})
        else:
            net.basis.requires_grad_(False)
        opt = torch.optim.Adam(groups, lr=cfg.lr)
    else:
        opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    gen = torch.Generator().manual_seed(cfg.seed)
    history, best, best_state = [], math.inf, None
    t0 = time.perf_counter()
    n_train = data.y.shape[0]
    for step in range(1, cfg.steps + 1):
        idx = torch.randint(0, n_train, (cfg.batch_size,), generator=gen)
        beta = cfg.beta * min(1.0, step / max(1, cfg.kl_anneal_steps))  # KL annealing
        loss, nll, kl, cons = loss_fn(net, cfg, data, idx, gen, beta)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step % cfg.val_every == 0 or step == cfg.steps:
            v = validation_mse(net, cfg, val, norm)
            elapsed = time.perf_counter() - t0
            rec = {"step": step, "loss": loss.item(), "nll": nll, "kl": kl, "consistency": cons, "beta": beta, "val": v,
                   "samples_per_s": step * cfg.batch_size / elapsed}
            history.append(rec)
            mark = ""
            if v["mean"] < best:
                best, best_state, mark = v["mean"], {k: t.clone() for k, t in net.state_dict().items()}, " *best"
            log(f"step {step:6d}/{cfg.steps}  loss {loss.item():10.3f}  nll {nll:9.3f}  kl {kl:8.3f}  "
                f"val_mse {v['mean']:.3e} rad²  {rec['samples_per_s']:.0f} traj/s{mark}")
    net.load_state_dict(best_state)
    net.eval()
    if out_path is not None:
        meta = {
            "train_config": dataclasses.asdict(cfg),
            "provenance": {"dataset": ds.source, "n_train": len(train_ds), "n_val": len(val_ds),
                           "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                           "deepprompt_ros": __version__, "torch": torch.__version__},
            "metrics": {"best_val_mse_rad2": best, "wall_time_s": time.perf_counter() - t0},
        }
        save_checkpoint(out_path, net, norm, ds.joint_names, meta)
    return net, norm, history


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="train", description="Train a DeepProMP on demonstrations.")
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--data", help="dataset folder of .npz/.csv demonstrations (see deepprompt_ros.data.demonstration)")
    src.add_argument("--builtin", help="built-in generated dataset: bimodal_sine | rhythmic_shake | wam_shake | "
                     "gen3_lite_reach, or a PyBullet task (core.tasks; full sets take minutes to generate): "
                     "reach | close_box | pour | kinova_pick_place")
    ap.add_argument("--config", help="training YAML (keys of TrainConfig); defaults if omitted")
    ap.add_argument("--out", required=True, help="output checkpoint path (.safetensors)")
    ap.add_argument("--steps", type=int, help="override the number of updates")
    args = ap.parse_args(argv)
    try:
        cfg = TrainConfig.from_yaml(args.config) if args.config else TrainConfig()
        if args.steps is not None:
            cfg = dataclasses.replace(cfg, steps=args.steps)
        ds = load_dataset(args.data) if args.data else builtin_dataset(args.builtin, seed=cfg.seed)
    except (ValueError, DatasetError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"training on {len(ds)} demonstrations from {ds.source}: joints {list(ds.joint_names)}, "
          f"phase {ds.phase_type}, contexts {ds.context_dims or 'none'}, images {ds.image_shape or 'none'}")
    _, _, hist = train(ds, cfg, out_path=args.out)
    best = min(h["val"]["mean"] for h in hist)
    print(f"best validation MSE {best:.3e} rad²; checkpoint written to {pathlib.Path(args.out).resolve()}")
    print(json.dumps({"out": str(pathlib.Path(args.out).resolve()), "best_val_mse_rad2": best}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
