"""The linear part Φ(x)(b + A z) of a residual decoder (``TrainConfig.decoder_basis``): its
initialization as the PPCA of the demonstrations, the closed-form MAP conditioning of that linear
model, and the cross-validation of its hyper-parameters on the training demonstrations alone.
numpy float64 except :func:`init_basis_pca`, which writes into the network.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.model.network import DeepProMPNet
from deepprompt_ros.model.phase import phase_basis
from deepprompt_ros.training.config import BASIS_COV_REG_UNITS
from deepprompt_ros.training.tensors import TensorData, fit_normalization

__all__ = ["pca_basis", "init_basis_pca", "linear_map_condition", "fold_assignment", "cv_via_sets", "CV_CONDITIONINGS",
           "cv_score", "cv_basis_hyperparameters"]


def pca_basis(phi: np.ndarray, y: np.ndarray, latent_dim: int, cov_reg: float = 0.0,
              ridge: float = 1e-6, joint_std: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The PPCA of demonstrations in a basis (numpy, float64) — the computation behind
    :func:`init_basis_pca`: per demo the ridge-regression weights W_i (rows b·d + j), b = their mean,
    the k = ``latent_dim`` columns of A = the top-k eigenvectors of their covariance C + R times the
    square root of the eigenvalue.

    The regularizer R (``basis_cov_reg_units``): with ``joint_std`` None, R = λI in the normalized
    units of ``y``, λ = ``cov_reg`` · mean(diag C); with ``joint_std`` (d,) — the joints' normalization
    standard deviations, rad — R is λI in rad, ProMP's regularizer
    (:meth:`deepprompt_ros.baselines.promp.ProMP.fit`):
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
    λ = ``cov_reg`` · mean(diag C) (ProMP's regularizer, :meth:`deepprompt_ros.baselines.promp.ProMP.fit`, uses 0.05):
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


def cv_via_sets(n_points: int, n_demos: int, n_via: int = 5, draws: int = 2, seed: int = 0) -> list[list[np.ndarray]]:
    """The conditionings a held-out demonstration is reconstructed from in the cross-validations of the
    linear part (:func:`cv_basis_hyperparameters`) and of ProMP
    (:func:`deepprompt_ros.baselines.promp_selection.select_promp`), as indices into ``n_points``
    equally spaced phases: per demo ``[start], [start, end]`` and ``draws`` sets of ``n_via`` random
    points (seeded by ``[seed, demo, draw]``). :data:`CV_CONDITIONINGS` names them."""
    if n_points < 2 or not 1 <= n_via <= n_points or draws < 1:
        raise ValueError(f"cv_via_sets needs n_points >= 2, 1 <= n_via <= n_points and draws >= 1; got "
                         f"n_points={n_points}, n_via={n_via}, draws={draws}")
    fixed = [np.array([0]), np.array([0, n_points - 1])]
    return [fixed + [np.sort(np.random.default_rng([seed, i, r]).choice(n_points, int(n_via), replace=False))
                     for r in range(draws)] for i in range(n_demos)]


#: What the sets of :func:`cv_via_sets` are, in order (the random sets are averaged into one).
CV_CONDITIONINGS = ("start", "start+end", "random via-points")


def cv_score(errors: np.ndarray) -> tuple[float, tuple[float, float, float]]:
    """The cross-validation error of one grid point from its per-set whole-trajectory MSEs ``errors``
    (n_demos, 2 + draws) in the order of :func:`cv_via_sets`.

    Returns (score, per-conditioning MSEs): the MSE of each conditioning of :data:`CV_CONDITIONINGS`
    (mean over demos, and over the random sets), and as the score their geometric mean, so that each
    conditioning weighs the same in relative terms: the start-only error, about the prior's spread, is
    orders of magnitude above the error from 5 via-points and would decide an arithmetic mean alone.
    """
    e = np.asarray(errors, dtype=np.float64)
    parts = (float(e[:, 0].mean()), float(e[:, 1].mean()), float(e[:, 2:].mean()))
    return float(np.exp(np.mean(np.log(np.maximum(parts, 1e-300))))), parts


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
