"""The linear part Φ(x)(b + A z) of a residual decoder (``TrainConfig.decoder_basis``): its
initialization as the PPCA of the demonstrations, the modes of the demonstrations' basis weights
(:func:`weight_modes`, ``TrainConfig.linear_modes``) whose offsets the PPCA leaves to the decoder's modes, the
closed-form MAP conditioning of that linear model, and the cross-validation of its hyper-parameters
on the training demonstrations alone. numpy float64 except :func:`init_basis_pca`, which writes into
the network.
"""
from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import numpy as np
import torch

from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.model.network import DeepProMPNet
from deepprompt_ros.model.phase import phase_basis
from deepprompt_ros.training.config import AUTO_DECODER_BASIS, BASIS_COV_REG_UNITS
from deepprompt_ros.training.tensors import TensorData, fit_normalization

__all__ = ["basis_weights", "pca_basis", "WeightModes", "weight_modes", "mode_dip", "PcaInit",
           "init_basis_pca",
           "MAX_MODES", "MODE_VARIANCE", "MODE_DEMOS_PER_DIM", "MODE_DIP", "MODE_MIN_SHARE", "MODE_MIN_DEMOS",
           "linear_map_condition", "fold_assignment", "cv_via_sets", "CV_CONDITIONINGS",
           "cv_score", "cv_modes", "MODE_NOISES", "MODE_MEAN_MARGIN", "PROMP_FORM", "AUTO_DECODER_BASIS",
           "AUTO_LATENT_LINEAR", "AUTO_COV_REGS", "CV_VIA_NOISES",
           "cv_basis_hyperparameters"]


def basis_weights(phi: np.ndarray, y: np.ndarray, ridge: float = 1e-6) -> np.ndarray:
    """Per demo the ridge-regression weights of the basis, (Φᵀ Φ + r I) W_i = Φᵀ y_i with r =
    ``ridge`` · mean(diag ΦᵀΦ).

    phi : (T, n_b) basis at the demos' phases; y : (D, T, d) demos. Returns (D, n_b·d), rows b·d + j."""
    gram = phi.T @ phi
    gram = gram + ridge * np.trace(gram) / gram.shape[0] * np.eye(gram.shape[0])
    w = np.linalg.solve(gram, np.einsum("tb,ntd->nbd", phi, y))  # (D, n_b, d)
    return w.reshape(w.shape[0], -1)


def pca_basis(phi: np.ndarray, y: np.ndarray, latent_dim: int, cov_reg: float = 0.0,
              ridge: float = 1e-6, joint_std: np.ndarray | None = None,
              labels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The PPCA of demonstrations in a basis (numpy, float64) — the computation behind
    :func:`init_basis_pca`: per demo the ridge-regression weights W_i (:func:`basis_weights`), b =
    their mean, the k = ``latent_dim`` columns of A = the top-k eigenvectors of their covariance C + R
    times the square root of the eigenvalue.

    ``labels`` (D,) — the mode of each demo (:func:`weight_modes`): C is then the pooled within-mode
    covariance, of each W_i minus its mode's mean (D − K degrees of freedom), so z ~ N(0, I) spans
    the variation inside a mode and not the offsets between the modes (the decoder's,
    ``ModelConfig.decoder_modes``); b stays the mean of all.

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
    d = y.shape[2]
    w = basis_weights(phi, y, ridge)
    n_b = w.shape[1] // d
    mean = w.mean(0)
    if labels is None:
        dev, dof = w - mean, max(1, w.shape[0] - 1)
    else:
        groups = np.unique(labels, return_inverse=True)[1]
        centres = np.stack([w[groups == g].mean(0) for g in range(groups.max() + 1)])
        dev, dof = w - centres[groups], max(1, w.shape[0] - centres.shape[0])
    if joint_std is None:
        _, sv, vt = np.linalg.svd(dev, full_matrices=True)  # vt: all n_b·d directions, data span first
        eig = np.zeros(vt.shape[0])
        eig[: sv.size] = sv ** 2 / dof
        eig += cov_reg * eig.sum() / eig.size
    else:
        std = np.tile(np.asarray(joint_std, dtype=np.float64).reshape(d), n_b)  # row b·d + j → std of joint j
        cov = dev.T @ dev / dof
        lam = cov_reg * float(np.mean(np.diag(cov) * std ** 2))
        eig, vec = np.linalg.eigh(cov + np.diag(lam / std ** 2))
        eig, vt = np.clip(eig[::-1], 0.0, None), vec[:, ::-1].T  # largest first
    r = min(latent_dim, vt.shape[0])
    scale = np.zeros(latent_dim)
    scale[:r] = np.sqrt(eig[:r])
    a = np.zeros((w.shape[1], latent_dim))
    a[:, :r] = (vt[:r] * scale[:r, None]).T
    return mean, a, scale


#: The mode analysis of :func:`weight_modes` (``TrainConfig.linear_modes`` under ``auto_select``):
#: mixtures of 1 … ``MAX_MODES`` Gaussians with one shared covariance (the within-mode covariance the
#: linear part holds) fitted to the leading principal components of the demos' basis weights — as many
#: as explain ``MODE_VARIANCE`` of their variance, at most one per ``MODE_DEMOS_PER_DIM`` demos — and
#: compared by BIC. A mixture counts only when its components are modes: every two are separated by
#: a dip of their mixture's density to at most ``MODE_DIP`` of the lower of its values at their means
#: (two equal components: means 4.9 within-mode standard deviations apart; the two halves of a
#: uniform spread, which BIC alone may split, dip to 0.44), and each holds at least ``MODE_MIN_SHARE``
#: of the demos and ``MODE_MIN_DEMOS`` of them (a few outlying demos are no mode).
MAX_MODES = 4
MODE_VARIANCE = 0.9
MODE_DEMOS_PER_DIM = 10
MODE_DIP = 0.1
MODE_MIN_SHARE = 0.1
MODE_MIN_DEMOS = 3
_MODE_INITS = 10  # k-means++ starts of each mixture's EM; the best likelihood is kept


class WeightModes(NamedTuple):
    """The modes of the demonstrations' basis weights (:func:`weight_modes`).

    Attributes
    ----------
    n_modes : int
        K, 1 when the weights form one group.
    labels : array of int, shape (D,)
        The mode of each demo (all 0 when K = 1).
    record : dict
        The criterion and its values (JSON types): the principal components used, per K the BIC,
        the mode sizes, the largest dip ratio of two modes and whether that K was admissible.
    """

    n_modes: int
    labels: np.ndarray
    record: dict


def mode_dip(separation: float, share_a: float, share_b: float, n_grid: int = 201) -> float:
    """How far the density of a two-component mixture with one shared covariance falls between the
    components' means: its minimum on the segment between them over the lower of its values at the
    two means (1: no dip, one mode; → 0: two separated modes). Along that segment the density is, up
    to a common factor, p(t) = π_a exp(−t²Δ²/2) + π_b exp(−(1 − t)²Δ²/2), Δ = ``separation`` the
    Mahalanobis distance of the means under the shared covariance and π = the components' shares."""
    t = np.linspace(0.0, 1.0, n_grid)
    p = share_a * np.exp(-0.5 * (t * separation) ** 2) + share_b * np.exp(-0.5 * ((1.0 - t) * separation) ** 2)
    return float(p.min() / min(p[0], p[-1]))


def weight_modes(w: np.ndarray, seed: int = 0, n_modes: int | None = None) -> WeightModes:
    """The modes of the basis weights ``w`` (D, P) of D demonstrations (:func:`basis_weights`).

    The weights are reduced to their r leading principal components (:data:`MODE_VARIANCE`,
    :data:`MODE_DEMOS_PER_DIM`) and mixtures of K Gaussians with one shared covariance are fitted by EM
    (:data:`_MODE_INITS` k-means++ starts seeded by ``seed``). With ``n_modes`` None, K is the one of the
    lowest BIC (Schwarz, "Estimating the dimension of a model", Ann. Stat. 6(2), 1978: −2 log L + p log D,
    p = K r + r(r + 1)/2 + K − 1) among K = 1 and the admissible K of 2 … :data:`MAX_MODES`: those
    whose components are modes (:data:`MODE_DIP`, :func:`mode_dip`) of enough demos
    (:data:`MODE_MIN_SHARE`, :data:`MODE_MIN_DEMOS`). With ``n_modes`` given, that K is fitted as is.
    Each demo's mode is its most probable component. Deterministic in ``seed``.
    """
    w = np.asarray(w, dtype=np.float64)
    n = w.shape[0]
    if n_modes is not None and not 1 <= n_modes <= n:
        raise ValueError(f"n_modes = {n_modes!r}: expected 1 <= n_modes <= {n} (the demonstrations)")
    if n_modes == 1:
        return WeightModes(1, np.zeros(n, dtype=int), {"n_modes": 1, "criterion": "one group (n_modes 1)"})
    _, sv, vt = np.linalg.svd(w - w.mean(0), full_matrices=False)
    total = float(sv @ sv)
    if total <= 0.0:
        return WeightModes(1, np.zeros(n, dtype=int), {"n_modes": 1, "criterion": "the weights do not vary"})
    r = int(min(np.searchsorted(np.cumsum(sv ** 2) / total, MODE_VARIANCE) + 1, max(1, n // MODE_DEMOS_PER_DIM)))
    x = (w - w.mean(0)) @ vt[:r].T  # (D, r) principal component scores
    min_size = max(MODE_MIN_DEMOS, math.ceil(MODE_MIN_SHARE * n))
    ks = [n_modes] if n_modes is not None else [1] + [k for k in range(2, MAX_MODES + 1) if k * min_size <= n]
    fits, rows = {}, {}
    for k in ks:
        loglik, shares, means, cov, resp = _tied_mixture(x, k, seed)
        labels = resp.argmax(1)
        sizes = np.bincount(labels, minlength=k)
        chol = np.linalg.cholesky(cov)
        dip = max((mode_dip(float(np.linalg.norm(np.linalg.solve(chol, means[a] - means[b]))), shares[a], shares[b])
                   for a in range(k) for b in range(a + 1, k)), default=None)
        bic = -2.0 * loglik + (k * r + r * (r + 1) / 2 + k - 1) * math.log(n)
        ok = k == 1 or (dip <= MODE_DIP and int(sizes.min()) >= min_size)
        fits[k] = labels
        rows[str(k)] = {"bic": bic, "sizes": sizes.tolist(), "dip": dip, "admissible": bool(ok)}
    best = n_modes if n_modes is not None else min((k for k in ks if rows[str(k)]["admissible"]),
                                                   key=lambda k: rows[str(k)]["bic"])
    labels = np.unique(fits[best], return_inverse=True)[1] if best > 1 else np.zeros(n, dtype=int)
    record = {"n_modes": int(labels.max() + 1),
              "criterion": f"BIC of Gaussian mixtures with one shared covariance on the {r} leading principal "
                           f"components of the {n} demonstrations' basis weights; modes dip to <= {MODE_DIP:g} "
                           f"and hold >= {min_size} demonstrations",
              "principal_components": r, "mixtures": rows}
    return WeightModes(record["n_modes"], labels, record)


def _tied_mixture(x: np.ndarray, k: int, seed: int, iterations: int = 500, rel_tol: float = 1e-10):
    """EM for a mixture of ``k`` Gaussians with one shared covariance on the rows of ``x`` (n, r), the
    best log-likelihood of :data:`_MODE_INITS` k-means++ starts (Arthur & Vassilvitskii, SODA 2007).
    The covariance gets 1e-6 of the mean variance on its diagonal (a mode of identical demos stays
    finite). Returns (log-likelihood, shares (k,), means (k, r), covariance (r, r), responsibilities (n, k))."""
    n, r = x.shape
    floor = 1e-6 * float(np.mean(x.var(0))) * np.eye(r)
    best = None
    for start in range(_MODE_INITS):
        rng = np.random.default_rng([seed, k, start])
        centres = x[[rng.integers(n)]]
        while centres.shape[0] < k:
            d2 = ((x[:, None] - centres[None]) ** 2).sum(-1).min(1)
            centres = np.vstack([centres, x[rng.choice(n, p=d2 / d2.sum()) if d2.sum() > 0 else rng.integers(n)]])
        resp = np.eye(k)[((x[:, None] - centres[None]) ** 2).sum(-1).argmin(1)]
        previous = -np.inf
        for _ in range(iterations):
            counts = np.maximum(resp.sum(0), 1e-12)
            shares, means = counts / n, (resp.T @ x) / counts[:, None]
            dev = x[:, None, :] - means[None]  # (n, k, r)
            cov = np.einsum("nk,nki,nkj->ij", resp, dev, dev) / n + floor
            chol = np.linalg.cholesky(cov)
            maha = (np.linalg.solve(chol, dev.reshape(-1, r).T) ** 2).sum(0).reshape(n, k)
            logp = np.log(shares) - 0.5 * maha - np.log(np.diag(chol)).sum() - 0.5 * r * math.log(2.0 * math.pi)
            top = logp.max(1, keepdims=True)
            loglik = float((top[:, 0] + np.log(np.exp(logp - top).sum(1))).sum())
            resp = np.exp(logp - top)
            resp /= resp.sum(1, keepdims=True)
            if loglik - previous <= rel_tol * abs(loglik):
                break
            previous = loglik
        if best is None or loglik > best[0]:
            best = (loglik, shares, means, cov, resp)
    return best


class PcaInit(NamedTuple):
    """What :func:`init_basis_pca` wrote and what the training needs from it.

    Attributes
    ----------
    scale : array, shape (k,)
        The standard deviations of the columns of A.
    modes : WeightModes
        The modes of the training demos' weights the PPCA was taken within (and the decoder holds).
    """

    scale: np.ndarray
    modes: WeightModes


@torch.no_grad()
def init_basis_pca(net: DeepProMPNet, data: TensorData, cov_reg: float = 0.0, ridge: float = 1e-6,
                   joint_std: np.ndarray | None = None, n_modes: int = 1, seed: int = 0) -> PcaInit:
    """Initialize the decoder's linear part Φ(x)(b + A z) as the PPCA of the training demos
    (``basis_init: pca``): per demo the ridge-regression weights W_i of the basis (normalized units),
    b = their mean, the columns of A = the top-k eigenvectors of their covariance C + λI scaled by
    the square root of the eigenvalue, so z ~ N(0, I) reproduces C + λI in those k directions.
    λ = ``cov_reg`` · mean(diag C) (ProMP's regularizer, :meth:`deepprompt_ros.baselines.promp.ProMP.fit`, uses 0.05):
    it gives the k − rank(C) directions beyond the demos' span a small variance instead of none.
    With λ = 0 those columns stay 0. ``joint_std`` (the normalization's, rad): λI in rad instead
    (``basis_cov_reg_units: raw``, :func:`pca_basis`). k is ``latent_linear`` when > 0 (A reads z_lin
    alone), else ``latent_dim``.

    ``n_modes`` K > 1 (``linear_modes``; ``net`` needs ``decoder_modes`` K): the demos' weights are
    grouped into K modes (:func:`weight_modes`, seed ``seed``), C is their within-mode covariance, and the
    decoder's ``mode_offsets`` m_k are each mode's mean weights minus b and ``mode_cumulative_shares``
    the modes' cumulative shares of the demos."""
    phi = net.basis_functions(data.x.double()).numpy()  # (T, n_b)
    y = data.y.double().numpy()
    k = net.cfg.latent_linear or net.cfg.latent_dim  # the columns of A: z_lin's, or all of z's
    w = basis_weights(phi, y, ridge)
    modes = weight_modes(w, seed, n_modes)
    labels = modes.labels if modes.n_modes > 1 else None
    if (net.cfg.decoder_modes or 1) != modes.n_modes:
        raise ValueError(f"init_basis_pca: {modes.n_modes} modes need a network with decoder_modes = "
                         f"{modes.n_modes if modes.n_modes > 1 else 0}, got decoder_modes {net.cfg.decoder_modes}")
    mean, a, scale = pca_basis(phi, y, k, cov_reg, ridge, joint_std, labels)
    net.basis.bias.copy_(torch.as_tensor(mean, dtype=torch.float32))
    net.basis.weight.copy_(torch.as_tensor(a, dtype=torch.float32))
    if labels is not None:  # the decoder holds the modes: weights b + m_k + A z_lin, mode k with share π_k
        offsets = np.stack([w[labels == g].mean(0) for g in range(modes.n_modes)]) - mean  # (K, n_b·d)
        net.mode_offsets.copy_(torch.as_tensor(offsets, dtype=torch.float32))
        cumulative = np.cumsum(np.bincount(labels, minlength=modes.n_modes)) / labels.size
        cumulative[-1] = 1.0
        net.mode_cumulative_shares.copy_(torch.as_tensor(cumulative, dtype=torch.float32))
    return PcaInit(scale, modes)


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
    points (seeded by ``[seed, demo, draw]``): the first three conditionings of :data:`CV_CONDITIONINGS`."""
    if n_points < 2 or not 1 <= n_via <= n_points or draws < 1:
        raise ValueError(f"cv_via_sets needs n_points >= 2, 1 <= n_via <= n_points and draws >= 1; got "
                         f"n_points={n_points}, n_via={n_via}, draws={draws}")
    fixed = [np.array([0]), np.array([0, n_points - 1])]
    return [fixed + [np.sort(np.random.default_rng([seed, i, r]).choice(n_points, int(n_via), replace=False))
                     for r in range(draws)] for i in range(n_demos)]


#: What the sets of :func:`cv_via_sets` are, in order (the random sets are averaged into one), and the
#: whole trajectory that :func:`cv_basis_hyperparameters` adds with ``whole_noise``.
CV_CONDITIONINGS = ("start", "start+end", "random via-points", "whole trajectory")


def cv_score(errors: np.ndarray, whole: np.ndarray | None = None) -> tuple[float, tuple[float, ...]]:
    """The cross-validation error of one grid point from its per-set whole-trajectory MSEs ``errors``
    (n_demos, 2 + draws) in the order of :func:`cv_via_sets`, and ``whole`` (n_demos,) those from every
    phase as via-points (optional).

    Returns (score, per-conditioning MSEs): the MSE of each conditioning of :data:`CV_CONDITIONINGS`
    (mean over demos, and over the random sets; the first three without ``whole``), and as the score
    their geometric mean, so that each conditioning weighs the same in relative terms: the start-only
    error, about the prior's spread, is orders of magnitude above the error from 5 via-points and
    would decide an arithmetic mean alone.
    """
    e = np.asarray(errors, dtype=np.float64)
    parts = (float(e[:, 0].mean()), float(e[:, 1].mean()), float(e[:, 2:].mean()))
    if whole is not None:
        parts += (float(np.mean(whole)),)
    return float(np.exp(np.mean(np.log(np.maximum(parts, 1e-300))))), parts


#: The grids of :func:`cv_basis_hyperparameters` (``TrainConfig.auto_select``): basis functions per
#: joint n_b (``training.config.AUTO_DECODER_BASIS``, which the configuration's checks read), linear latent sizes k_l (each n_b also tries k_l = n_b·d, the whole weight space, where
#: the linear part holds a full ProMP), PPCA regularizers λ (relative, :func:`pca_basis`) in both units,
#: and via-point noises (normalized joint units; ProMP's cross-validation uses the same). λ > 0 and
#: k_l >= ``reach_via_points`` · d keep a planner's via-points reachable: held-out demonstrations lie
#: near the span of the others, so the cross-validation alone would accept a linear block that can
#: move only within that span (λ = 0) or in fewer directions than the via-points constrain.
AUTO_LATENT_LINEAR = (8, 16, 32, 64)
AUTO_COV_REGS = (1e-3, 0.01, 0.03, 0.1, 0.3, 1.0)
CV_VIA_NOISES = (1e-4, 1e-3, 1e-2, 3e-2, 0.1)
#: The reference form of the linear part: ProMP's (``ProMPModel``'s 20 RBFs per joint, λ in rad, the
#: whole weight space as latent) — the default the cross-validation departs from only on evidence.
PROMP_FORM = (20, "raw")


def cv_basis_hyperparameters(ds: DemoDataset, n_points: int, decoder_bases: Sequence[int] = AUTO_DECODER_BASIS,
                             basis_width: float = 1.0, latent_linears: Sequence[int] = AUTO_LATENT_LINEAR,
                             cov_regs: Sequence[float] = AUTO_COV_REGS, via_noises: Sequence[float] = CV_VIA_NOISES,
                             cov_reg_units: Sequence[str] = BASIS_COV_REG_UNITS, n_via: int = 5, folds: int = 5,
                             draws: int = 2, seed: int = 0, reach_via_points: int = 5,
                             reference: tuple[int, str] | None = PROMP_FORM, meet: bool = False,
                             whole_noise: float | None = None) -> dict:
    """Choose the linear part Φ(x)(b + A z_lin) of a decoder — basis functions per joint n_b
    (``decoder_basis``), linear latent size k_l (``latent_linear``), PPCA regularizer λ
    (``basis_cov_reg``) and its units (``basis_cov_reg_units``), via-point noise (``via_noise``,
    normalized joint units) — by K-fold cross-validation on the demonstrations ``ds`` alone.

    Per fold: the normalization (:func:`fit_normalization`) and the PPCA (:func:`pca_basis`) are fitted
    to the other demos, and each held-out demo is reconstructed from the via-point sets of
    :func:`cv_via_sets` (start, start + end, ``draws`` sets of ``n_via`` points) by exact Gaussian
    conditioning of z_lin ~ N(0, I) (the posterior mean, :func:`linear_map_condition`'s closed form,
    noise ``via_noise`` on every joint in normalized units; with ``meet`` then moved onto the
    via-points); a grid point's score is
    :func:`cv_score` of the held-out whole-trajectory MSEs (rad²). Per n_b, k_l runs over the values
    of ``latent_linears`` from ``reach_via_points`` · d (the rows of that many full via-points) to below
    n_b·d, and n_b·d itself; n_b over the values of ``decoder_bases`` up to ``n_points`` / 2.
    ``folds``: at most one per demo. Deterministic in ``seed``.

    ``reference`` (n_b, units): the grid points of that basis with the whole weight space as latent
    (k_l = n_b·d) and λ in those units — a ProMP (:data:`PROMP_FORM`) — are the default: the best of
    them is replaced by the best grid point that :func:`_departs` from it — a per-demo log error
    (:func:`cv_score`'s terms, per demo) lower by more than one standard error of the paired difference
    and on no conditioning higher by more than one —; small differences on the cross-validation's few
    demos do not carry to other demos.

    ``meet``: score each grid point by the mean the server executes for a planner
    (:meth:`deepprompt_ros.primitive.deep_promp.DeepProMP.condition_planner`): the posterior mean at
    the row's noise moved onto the via-points by the smallest change of the linear part's trajectory
    (squared change over the ``n_points`` phases in rad, every joint:
    :func:`deepprompt_ros.primitive.linear_conditioning.smallest_change`, here by pseudo-inverses, and
    without the server's bound on that change, PLANNER_CHANGE_BOUND). A set of more rows than k_l
    (possible only with ``reach_via_points`` < ``n_via``) keeps the posterior mean at the row's noise,
    where the server would condition again at the planner's. Structure and noise are then chosen
    together by the error of what is deployed, as ProMP's own selection chooses its regularizer and
    noise by the error of its posterior mean
    (:func:`deepprompt_ros.baselines.promp_selection.select_promp`).

    ``whole_noise``: when given, every grid point is also scored on each held-out demo conditioned on
    all ``n_points`` phases (the paper's via-point reconstruction) by the posterior mean at that noise
    (normalized units; the planner's noise gives the least-squares fit of the linear part, which a set
    of more rows than k_l gets from the server), a fourth term of :func:`cv_score`: a basis or latent
    too small to follow the demonstrations costs there what the few via-points of the other sets do
    not show.

    Returns {"decoder_basis", "latent_linear", "basis_cov_reg", "basis_cov_reg_units", "via_noise",
    "cv_mse", "cv_mse_parts" (per conditioning of :data:`CV_CONDITIONINGS`), "folds", "draws", "n_demos",
    "meet", "whole_noise", "table": [[n_b, k_l, λ, units, noise, score, mse start, mse start+end, mse
    random (, mse whole)], ...], and when the reference is in the grid "reference": {"row", "best_row"
    (the lowest score), "log_difference" and
    "standard_error" (of best_row against row), "departure_row" (what replaces row, or None), "best_kept"
    (a departure chosen)}}.
    """
    demos = ds.demos
    n = len(demos)
    if n < 3:
        raise ValueError(f"cross-validation needs >= 3 demonstrations, got {n}")
    bad = [u for u in cov_reg_units if u not in BASIS_COV_REG_UNITS]
    if bad or not cov_reg_units:
        raise ValueError(f"cov_reg_units must be a non-empty selection of {BASIS_COV_REG_UNITS}, "
                         f"got {tuple(cov_reg_units)}")
    bases = sorted({int(b) for b in decoder_bases if 2 <= int(b) <= n_points // 2})
    if not bases or not latent_linears or not cov_regs or not via_noises or min(via_noises) <= 0:
        raise ValueError(f"the grids must be non-empty, decoder_bases in [2, n_points / 2 = {n_points // 2}] and "
                         f"via_noises > 0; got decoder_bases {tuple(decoder_bases)}, latent_linears "
                         f"{tuple(latent_linears)}, cov_regs {tuple(cov_regs)}, via_noises {tuple(via_noises)}")
    folds = max(2, min(int(folds), n))
    fold_of = fold_assignment(n, folds, seed)
    x = np.linspace(0.0, 1.0, n_points)
    y_all = np.stack([d.resampled(n_points) for d in demos])  # (n, T, d) rad
    d = y_all.shape[2]
    sets = cv_via_sets(n_points, n, n_via, draws, seed)
    noises = tuple(float(v) for v in via_noises)
    noise2 = np.asarray(noises, dtype=np.float64) ** 2
    if whole_noise is not None and not (math.isfinite(whole_noise) and whole_noise > 0):
        raise ValueError(f"whole_noise must be a finite noise > 0 or None, got {whole_noise!r}")
    units = tuple(dict.fromkeys(cov_reg_units))
    ks_of = {nb: sorted({int(k) for k in latent_linears if max(1, reach_via_points * d) <= int(k) < nb * d}
                        | {nb * d}) for nb in bases}
    err = {(nb, k, float(c), u): np.zeros((n, len(sets[0]), noise2.size))
           for nb in bases for k in ks_of[nb] for c in cov_regs for u in units}
    whole = {key: np.zeros(n) for key in err} if whole_noise is not None else None
    for f in range(folds):
        tr, te = np.flatnonzero(fold_of != f), np.flatnonzero(fold_of == f)
        norm = fit_normalization(DemoDataset(tuple(demos[i] for i in tr), ds.source), n_points)
        std = np.asarray(norm.y_std, dtype=np.float64)
        yn = (y_all - norm.y_mean) / std
        for nb in bases:
            phi = phase_basis(x, nb, basis_width, ds.phase_type == "rhythmic")
            ks = ks_of[nb]
            for u in units:
                for c in cov_regs:
                    mean, a, _ = pca_basis(phi, yn[tr], ks[-1], float(c), joint_std=std if u == "raw" else None)
                    cache: dict = {}  # the trajectory metric of this (phi, a, std), for every set
                    for j in range(len(sets[0])):  # the j-th set of every held-out demo (same size): one batch
                        sel = np.stack([sets[i][j] for i in te])  # (B, V)
                        for k, e in zip(ks, _conditioned_errors(phi, mean, a, ks, sel, yn[te], std, noise2, meet,
                                                                cache)):
                            err[(nb, k, float(c), u)][te, j] = e
                    if whole is not None:
                        for k, e in zip(ks, _whole_errors(phi, mean, a, ks, yn[te], std, float(whole_noise) ** 2)):
                            whole[(nb, k, float(c), u)][te] = e
    table, per_demo = [], {}
    for (nb, k, c, u), e in err.items():
        w = whole[(nb, k, c, u)] if whole is not None else None
        for s, v in enumerate(noises):
            score, parts = cv_score(e[:, :, s], w)
            table.append([nb, k, c, u, v, score, *parts])
            per_demo[(nb, k, c, u, v)] = _log_scores(e[:, :, s], w)
    best = min(table, key=lambda r: r[5])
    out = {"folds": folds, "draws": draws, "n_demos": n, "meet": bool(meet), "whole_noise": whole_noise,
           "table": table}
    ref_rows = [r for r in table if reference is not None and (r[0], r[1], r[3]) == (reference[0], reference[0] * d,
                                                                                     reference[1])]
    if ref_rows:  # ProMP's form, left only for a row better overall and not worse on any conditioning
        ref = min(ref_rows, key=lambda r: r[5])
        diff = per_demo[tuple(best[:5])].mean(1) - per_demo[tuple(ref[:5])].mean(1)
        se = float(diff.std(ddof=1) / np.sqrt(diff.size))
        departure = min((r for r in table if _departs(per_demo[tuple(r[:5])], per_demo[tuple(ref[:5])])),
                        key=lambda r: r[5], default=None)
        out["reference"] = {"row": ref, "log_difference": float(diff.mean()), "standard_error": se,
                            "best_row": best, "departure_row": departure, "best_kept": departure is not None}
        best = ref if departure is None else departure
    return {"decoder_basis": best[0], "latent_linear": best[1], "basis_cov_reg": best[2],
            "basis_cov_reg_units": best[3], "via_noise": best[4], "cv_mse": best[5], "cv_mse_parts": best[6:], **out}


def _log_scores(errors: np.ndarray, whole: np.ndarray | None = None) -> np.ndarray:
    """(n_demos, C) each held-out demo's log MSE per conditioning of :data:`CV_CONDITIONINGS` (the random
    sets averaged first; the whole trajectory's from ``whole`` (n_demos,) when given): their mean over
    the conditionings is the per-demo counterpart of :func:`cv_score`."""
    e = np.maximum(np.asarray(errors, dtype=np.float64), 1e-300)
    logs = [np.log(e[:, 0]), np.log(e[:, 1]), np.log(e[:, 2:].mean(1))]
    if whole is not None:
        logs.append(np.log(np.maximum(np.asarray(whole, dtype=np.float64), 1e-300)))
    return np.stack(logs, 1)


def _departs(row: np.ndarray, ref: np.ndarray) -> bool:
    """Whether a grid point of per-demo log errors ``row`` (n_demos, C) replaces the reference's ``ref``:
    lower on the mean over the conditionings by more than one standard error of the paired per-demo
    difference (the one-standard-error rule of :func:`deepprompt_ros.training.selection.keep_residual`)
    and, on each conditioning alone, higher by at most one standard error: a choice that trades one
    conditioning for another (a coarser basis that conditions better on few via-points and follows
    the whole trajectory worse) keeps the reference."""
    diff = row - ref
    n = diff.shape[0]
    total = diff.mean(1)
    if total.mean() + total.std(ddof=1) / np.sqrt(n) >= 0:
        return False
    return bool(np.all(diff.mean(0) <= diff.std(0, ddof=1) / np.sqrt(n)))


def _whole_errors(phi, mean, a, ks, y_true, std, noise2: float) -> list[np.ndarray]:
    """Whole-trajectory MSEs (rad²) of the posterior mean of z_lin ~ N(0, I) given every phase of B
    demos as via-points at noise variance ``noise2`` (normalized units), per latent size of ``ks``: the
    information form z = (G + noise² I)⁻¹ Jᵀ r, G = JᵀJ = Σ_j A_jᵀ ΦᵀΦ A_j the same for every demo (k × k,
    where the observation form would be T·d × T·d). phi (T, n_b), mean (n_b·d,), a (n_b·d, K), y_true
    (B, T, d) normalized, std (d,). Returns per k an array (B,)."""
    (t, nb), (b, _, d) = phi.shape, y_true.shape
    wm = mean.reshape(nb, d)
    res = y_true - (phi @ wm)[None]  # (B, T, d)
    jtr_all = (phi.T @ res).reshape(b, nb * d) @ a  # (B, K): Jᵀ r, weights b·d + j as the rows of a
    a3 = a.reshape(nb, d, -1)
    gram_all = sum(a3[:, j].T @ (phi.T @ phi) @ a3[:, j] for j in range(d))  # (K, K): JᵀJ
    out = []
    for k in ks:
        z = np.linalg.solve(gram_all[:k, :k] + noise2 * np.eye(k), jtr_all[:, :k].T)  # (k, B)
        pred = phi @ (a[:, :k] @ z).reshape(nb, d * b)  # (T, d·B), the change from the mean
        err = pred.reshape(t, d, b).transpose(2, 0, 1) - res  # (B, T, d)
        out.append(((err * std) ** 2).mean((1, 2)))
    return out


def _conditioned_errors(phi, mean, a, ks, sel, y_true, std, noise2, meet: bool = False,
                        cache: dict | None = None) -> list[np.ndarray]:
    """Whole-trajectory MSEs (rad²) of the posterior mean of z_lin ~ N(0, I) given the via-points of B
    demos, for each latent size of ``ks`` (the first k columns of ``a``) and each noise variance of
    ``noise2`` (S,): with J z + ε = r, ε ~ N(0, noise² I), z = Jᵀ (J Jᵀ + noise² I)⁻¹ r through the
    eigendecomposition of J Jᵀ (all noises at once). ``meet``: that mean then moved onto the via-points
    by the smallest change Δ of the trajectory, Δ = M⁻¹ Jᵀ (J M⁻¹ Jᵀ)⁻¹ (r − J z), M = Σ_j std_j² A_jᵀ
    ΦᵀΦ A_j the squared change over the phases in rad (A_j the rows of joint j), where J has at most k
    rows. phi (T, n_b), mean (n_b·d,), a (n_b·d, K), sel (B, V) phase indices, y_true (B, T, d)
    normalized, std (d,). ``cache``: a dict kept by the caller between calls with the same phi, a and
    std (M and its pseudo-inverses are computed once for them). Returns per k an array (B, S)."""
    (t, nb), (b, v), d, s = phi.shape, sel.shape, y_true.shape[2], noise2.size
    cache = {} if cache is None else cache
    wm = mean.reshape(nb, d)
    ph = phi[sel]  # (B, V, n_b)
    yv = np.take_along_axis(y_true, sel[:, :, None], 1)  # (B, V, d)
    res = (yv - ph @ wm).reshape(b, v * d)  # innovations, rows (via, joint)
    jac_all = (ph @ a.reshape(nb, -1)).reshape(b, v * d, -1)  # (B, V·d, K): row (v, j) = Σ_n φ_n(x_v) a[n·d + j]
    if meet and "metric" not in cache:
        cache["metric"] = _metric(phi, a, std)
    out = []
    for k in ks:
        if meet and v * d <= k and k not in cache:
            cache[k] = np.linalg.pinv(cache["metric"][:k, :k], hermitian=True)
        pred = _posterior_means(phi, wm, a[:, :k], jac_all[:, :, :k], res, noise2,
                                cache[k] if meet and v * d <= k else None)[0]
        out.append((((pred - y_true[..., None]) * std[:, None]) ** 2).mean((1, 2)))
    return out


def _posterior_means(phi, wm, a, jac, res, noise2, metric_inv=None):
    """The trajectories of the posterior means of z ~ N(0, I) in Φ(b + A z) given the innovations ``res``
    (B, M) = J z + ε, ε ~ N(0, noise² I), for each noise variance of ``noise2`` (S,): z = Jᵀ (J Jᵀ + noise²
    I)⁻¹ r through the eigendecomposition of J Jᵀ; with ``metric_inv`` (M⁻¹ of
    :func:`_conditioned_errors`) moved onto the via-points by the smallest change. phi (T, n_b), wm (n_b,
    d) the weights b, a (n_b·d, k), jac (B, M, k). Returns (trajectories (B, T, d, S), the eigenvalues
    e (B, M) of J Jᵀ, the innovations in its eigenvectors' basis Uᵀ r (B, M)): log N(r; 0, J Jᵀ + σ² I)
    = −½ Σ (Uᵀr)² / (e + σ²) − ½ Σ log(e + σ²) − M/2 log 2π."""
    (t, nb), (b, _, k), d, s = phi.shape, jac.shape, wm.shape[1], noise2.size
    e, u = np.linalg.eigh(jac @ jac.transpose(0, 2, 1))  # (B, M), (B, M, M)
    c = (u.transpose(0, 2, 1) @ res[:, :, None])  # Uᵀ r, (B, M, 1)
    coef = u @ (c / (np.clip(e, 0.0, None)[:, :, None] + noise2))  # (B, M, S)
    z = jac.transpose(0, 2, 1) @ coef  # (B, k, S) posterior means
    if metric_inv is not None:
        hm = jac @ metric_inv  # (B, M, k) = J M⁻¹
        gram = hm @ jac.transpose(0, 2, 1)  # (B, M, M) = J M⁻¹ Jᵀ
        z = z + hm.transpose(0, 2, 1) @ (np.linalg.pinv(gram, hermitian=True) @ (res[:, :, None] - jac @ z))
    w = (a @ z).reshape(b, nb, d * s)  # (B, n_b, d·S) weight offsets
    pred = (phi @ w).reshape(b, t, d, s) + (phi @ wm)[None, :, :, None]
    return pred, np.clip(e, 0.0, None), c[:, :, 0]


#: The noises of the modes' posterior probabilities :func:`cv_modes` tries (``ModelConfig.mode_noise``,
#: normalized joint units), those >= the chosen via-point noise.
MODE_NOISES = (*CV_VIA_NOISES, 0.3, 1.0)


#: The relative MSE by which the modes' means may be worse than one Gaussian's at a conditioning of
#: :func:`cv_modes` whatever its standard error, and must be better to count as evidence for them (2 %): the
#: within-mode covariance is estimated from fewer demos, and modes that are there (two branches of a sine,
#: 100–200 demos) cost about 1 % from the start point, where the inputs cannot tell them apart.
MODE_MEAN_MARGIN = 0.02


def cv_modes(ds: DemoDataset, n_points: int, linear_part: dict, n_modes: int, basis_width: float = 1.0,
             n_via: int = 5, folds: int = 5, draws: int = 2, seed: int = 0) -> dict:
    """Whether K = ``n_modes`` modes of the basis weights (:func:`weight_modes`) make the executed means of
    held-out demonstrations no worse than one Gaussian does: K-fold cross-validation on the demonstrations
    ``ds`` alone, of the linear part ``linear_part`` (``decoder_basis``, ``latent_linear``, ``basis_cov_reg``,
    ``basis_cov_reg_units``, ``via_noise`` as :func:`cv_basis_hyperparameters` chose them) with and without
    the modes, in closed form (the trained decoder's linear part is this PPCA, ``basis_lr_scale`` 0).

    Per fold, on the other demos: the normalization, the K modes (``n_modes`` fixed, seed ``seed``), the
    PPCA within them (:func:`pca_basis` with the labels) with each mode's mean weights and share, and the
    PPCA of all. Each held-out demo is conditioned on the sets of :func:`cv_via_sets` (start, start + end,
    ``draws`` sets of ``n_via`` points): one Gaussian by its posterior mean at ``via_noise`` moved onto the
    via-points (as :func:`cv_basis_hyperparameters` with ``meet``); the modes by each mode's such mean at a
    noise ν of :data:`CV_VIA_NOISES`, weighted by the mode's posterior probability (its share times the
    exact likelihood of the via-points at a noise ν_m >= ν of :data:`MODE_NOISES`): the executed mean of a
    decoder of several modes. The modes' noises are chosen as
    :func:`deepprompt_ros.training.selection.choose_mode_noise` chooses them on the validation demos after
    the training (the linear part within the modes is not the one the noise was cross-validated for): ν
    of the lowest MSE at the random sets (ν_m = ν), then ν_m of the lowest sum of the start's and the random
    sets' MSEs, each relative to its value at ν_m = ν.

    Modes of the weights are found on demonstrations spread over a continuum too, and their means are then
    worse: the modes are ``admitted`` only where no conditioning's mean MSE is higher with them by more than
    two standard errors (per-demo MSE differences relative to one Gaussian's mean MSE — the comparison the
    goal of never losing to ProMP makes; two for three tests at once, about 7 % false alarms where one each
    would give about 40 %) and by more than :data:`MODE_MEAN_MARGIN`; they are ``better`` where admitted and,
    at some conditioning, lower by more than two standard errors and that margin (the executed means' own
    evidence for the modes; their two noises are chosen on the same held-out errors, which favours them a
    little). Returns {"admitted", "better", "worse" (per conditioning), "via_noise", "mode_noise",
    "conditionings" (the first three of :data:`CV_CONDITIONINGS`), "relative_difference" and "standard_error"
    per conditioning, "mse_modes", "mse_one_mode" (rad², per conditioning: one Gaussian's are those of
    :func:`cv_basis_hyperparameters`' chosen row), "folds", "n_demos"}."""
    demos = ds.demos
    n = len(demos)
    if n < 3 or n_modes < 2:
        raise ValueError(f"cv_modes needs >= 3 demonstrations and n_modes >= 2, got {n} and {n_modes}")
    nb, k = int(linear_part["decoder_basis"]), int(linear_part["latent_linear"])
    lam, noise = float(linear_part["basis_cov_reg"]), float(linear_part["via_noise"])
    vias, weight_noises = np.asarray(CV_VIA_NOISES), np.asarray(MODE_NOISES)
    folds = max(2, min(int(folds), n))
    fold_of = fold_assignment(n, folds, seed)
    x = np.linspace(0.0, 1.0, n_points)
    phi = np.asarray(phase_basis(x, nb, basis_width, ds.phase_type == "rhythmic"))
    y_all = np.stack([dm.resampled(n_points) for dm in demos])  # (n, T, d) rad
    d = y_all.shape[2]
    sets = cv_via_sets(n_points, n, n_via, draws, seed)
    n_sets = len(sets[0])
    err_one = np.zeros((n, n_sets))
    err_modes = np.zeros((n, n_sets, vias.size, weight_noises.size))
    for f in range(folds):
        tr, te = np.flatnonzero(fold_of != f), np.flatnonzero(fold_of == f)
        norm = fit_normalization(DemoDataset(tuple(demos[i] for i in tr), ds.source), n_points)
        std = np.asarray(norm.y_std, dtype=np.float64)
        yn = (y_all - norm.y_mean) / std
        joint_std = std if linear_part["basis_cov_reg_units"] == "raw" else None
        w = basis_weights(phi, yn[tr])
        labels = weight_modes(w, seed, n_modes).labels
        groups = int(labels.max()) + 1
        mean_1, a_1, _ = pca_basis(phi, yn[tr], k, lam, joint_std=joint_std)
        a_k = pca_basis(phi, yn[tr], k, lam, joint_std=joint_std, labels=labels if groups > 1 else None)[1]
        centres = np.stack([w[labels == g].mean(0) for g in range(groups)]).reshape(groups, nb, d)
        log_shares = np.log(np.bincount(labels, minlength=groups) / labels.size)
        inv_1, inv_k = (np.linalg.pinv(_metric(phi, a, std), hermitian=True) for a in (a_1, a_k))
        for j in range(n_sets):
            sel = np.stack([sets[i][j] for i in te])  # (B, V)
            ph = phi[sel]  # (B, V, n_b)
            yv = np.take_along_axis(yn[te], sel[:, :, None], 1)  # (B, V, d)
            meet = sel.shape[1] * d <= k

            def means(centre, a, inverse, noise2):
                jac = (ph @ a.reshape(nb, -1)).reshape(len(te), -1, a.shape[1])
                res = (yv - ph @ centre).reshape(len(te), -1)
                return _posterior_means(phi, centre, a, jac, res, noise2, inverse if meet else None)
            pred = means(mean_1.reshape(nb, d), a_1, inv_1, np.array([noise ** 2]))[0][..., 0]
            err_one[te, j] = (((pred - yn[te]) * std) ** 2).mean((1, 2))
            preds, logliks = [], []
            for centre in centres:
                pred, e, c = means(centre, a_k, inv_k, vias ** 2)
                preds.append(pred)  # (B, T, d, S_v)
                var = e[:, :, None] + weight_noises[None, None, :] ** 2  # (B, M, S_m)
                logliks.append(-0.5 * ((c[:, :, None] ** 2 / var) + np.log(var)).sum(1))  # (B, S_m)
            log_w = np.stack(logliks) + log_shares[:, None, None]  # (K, B, S_m)
            wts = np.exp(log_w - log_w.max(0, keepdims=True))
            wts /= wts.sum(0, keepdims=True)
            mixed = np.einsum("kbm,kbtdv->bvmtd", wts, np.stack(preds))  # (B, S_v, S_m, T, d)
            err_modes[te, j] = (((mixed - yn[te][:, None, None]) * std) ** 2).mean((3, 4))
    at_own = [err_modes[:, 2:, v, int(np.flatnonzero(weight_noises == via)[0])].mean() for v, via in enumerate(vias)]
    v_best = int(np.argmin(at_own))
    m_own = int(np.flatnonzero(weight_noises == vias[v_best])[0])
    candidates = np.flatnonzero(weight_noises >= vias[v_best])
    base = np.array([err_modes[:, 0, v_best, m_own].mean(), err_modes[:, 2:, v_best, m_own].mean()])
    rel = [err_modes[:, 0, v_best, m].mean() / max(base[0], 1e-300) + err_modes[:, 2:, v_best, m].mean()
           / max(base[1], 1e-300) for m in candidates]
    m_best = int(candidates[int(np.argmin(rel))])
    chosen = err_modes[:, :, v_best, m_best]
    per = lambda e: np.stack([e[:, 0], e[:, 1], e[:, 2:].mean(1)], 1)  # noqa: E731  (n, 3): the random sets averaged
    diff = (per(chosen) - per(err_one)) / np.maximum(per(err_one).mean(0), 1e-300)
    mean, se = diff.mean(0), diff.std(0, ddof=1) / np.sqrt(n)
    worse = (mean > 2.0 * se) & (mean > MODE_MEAN_MARGIN)
    lower = (mean < -2.0 * se) & (mean < -MODE_MEAN_MARGIN)
    parts = lambda e: [float(e[:, 0].mean()), float(e[:, 1].mean()), float(e[:, 2:].mean())]  # noqa: E731
    return {"admitted": not bool(worse.any()), "better": not bool(worse.any()) and bool(lower.any()),
            "worse": worse.tolist(), "via_noise": float(vias[v_best]), "mode_noise": float(weight_noises[m_best]),
            "conditionings": list(CV_CONDITIONINGS[:3]), "relative_difference": mean.tolist(),
            "standard_error": se.tolist(), "mse_modes": parts(chosen), "mse_one_mode": parts(err_one),
            "folds": folds, "n_demos": n}


def _metric(phi, a, std) -> np.ndarray:
    """M = Σ_j std_j² A_jᵀ ΦᵀΦ A_j (K, K), the squared change of the trajectory over the phases in rad per
    change of z (A_j the rows of joint j of ``a`` (n_b·d, K); ``std`` (d,) the joints' normalization)."""
    nb, d = phi.shape[1], np.size(std)
    a_rad = a.reshape(nb, d, -1) * np.asarray(std, dtype=np.float64)[None, :, None]  # (n_b, d, K), joint units
    p_a = ((phi.T @ phi) @ a_rad.reshape(nb, -1)).reshape(nb * d, -1)  # ΦᵀΦ A, rows (n, j)
    return a_rad.reshape(nb * d, -1).T @ p_a
