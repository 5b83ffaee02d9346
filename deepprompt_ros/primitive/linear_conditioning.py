"""Exact conditioning of the linear latent block on via-points (``ModelConfig.latent_linear`` k_l > 0).

The decoder μ_y(z, x) = Φ(x)(b + A z_lin) + s·MLP(z_nl, x) is linear in z_lin for a fixed z_nl, so a
via-point y_v at phase x_v is a linear observation of z_lin — ProMP's conditioning inside the latent:

    y_v − s·MLP(z_nl, x_v) − Φ(x_v) b = Φ(x_v) A z_lin + ε,   ε_j ~ N(0, ν² σ_j² / ω_v),

one row per observed joint j of each via-point (a joint mask drops rows, a weight ω_v = 0 all of
them), ν = ``via_noise`` (normalized units) and σ_j the joint's normalization std. The prior of
z_lin is the aggregation of the contexts and images (q_c, diagonal). The posterior is Gaussian with
a full k_l × k_l covariance, the same for every z_nl; its mean depends on z_nl through the offset.

z_nl is not linear: candidates (the mean of its aggregation q_all(z_nl) of all inputs and seeded
quasi-random points of it) are weighted by the closed-form marginal likelihood of the via-points,
N(r; H m, H Σ Hᵀ + R) (up to the factor every candidate shares), times q_c(z_nl) / q_all(z_nl):
importance weights of the posterior under the prior q_c of the contexts and images, the proposal
q_all. With several modes of the decoder (``decoder_modes``) and no MLP residual the candidates are one
per mode, weighted by the mode's share times the exact likelihood: the exact mixture posterior, whose
mean trajectory is what the robot executes; the prior of z_lin the contexts' and images' encodings give is
moved to each mode's coordinates (they do not know the mode). See :meth:`deepprompt_ros.primitive.deep_promp.DeepProMP.condition`.

Numerics (float64): everything is whitened (rows divided by their noise, columns times the prior
std), then factored by Cholesky — of I + G Gᵀ (M × M) when there are no more rows M than k_l, of the
precision I + Gᵀ G (k_l × k_l) otherwise. The information form solves with the triangular factor; the
observation form solves for the mean with I + G Gᵀ itself (LU, one call) and keeps the factor for the
covariance, which is computed only when it is read
(:meth:`~deepprompt_ros.primitive.latent.LinearBlock.variance`); the planner's one-candidate path, whose
mean needs no factor, leaves the factoring to the block as well
(:attr:`~deepprompt_ros.primitive.latent.LinearBlock.chol`).
No inverse of an ill-conditioned matrix is formed (the L⁻¹ the covariance uses is that of the Cholesky
factor, whose condition number is the square root of the factored matrix's).

A planner's via-points (:meth:`~deepprompt_ros.primitive.deep_promp.DeepProMP.condition_planner`) are
met exactly, but the points themselves carry the noise of the demonstrations they come from: the
exact posterior mean interpolates that noise into the whole trajectory along the demonstrations'
correlations. With ``smooth_noise`` the mean is instead the posterior mean at the model's
cross-validated noise, moved onto the via-points by the smallest change of the trajectory
(:func:`smallest_change`); the distribution around it stays the exact posterior's.

Speed: the conditioning stays in numpy, one BLAS library with one pool of threads (a second
library's pool stalls against numpy's on few cores). Its LAPACK steps, the Cholesky factorization
and the solves, call numpy's gufuncs directly in :func:`_cholesky`, :func:`_lower_solve` and
:func:`_general_solve`, the one seam that does: ``np.linalg``'s per-call checks cost more than these
small factorizations (bench_core's ``condition_ratio``); a test compares the two paths.
"""
from __future__ import annotations

import dataclasses
import math
import statistics
import time
from typing import TYPE_CHECKING

import numpy as np
from numpy.linalg import _umath_linalg

from deepprompt_ros.primitive.latent import (FACTORABLE_INPUTS, PLANNER_CHANGE_BOUND, LatentGaussian,
                                            LinearBlock)

if TYPE_CHECKING:
    from deepprompt_ros.primitive.numpy_net import NumpyNet

__all__ = ["whitened_posterior", "condition_split", "moved_prior_means", "smallest_change", "linear_block_variance",
           "SplitRefinement", "refine_split", "TIE_TOLERANCE", "MODE_GATE_VAR", "normal_points", "mode_candidates"]

#: Candidates of z_nl whose log posterior densities are within this relative amount of the best are
#: tied (rounding, not evidence); the executed mean is the first of them, the mean of q_all(z_nl) when
#: it is among them.
TIE_TOLERANCE = 1e-9
#: With several modes (``decoder_modes``): the variance a conditioned latent records for z_nl's first
#: coordinate, whose candidates sit at their modes' medians (:func:`mode_candidates`). Small against the
#: distance of a median to its interval's edges (>= 0.12 for shares >= 0.1), so a latent perturbed by its
#: recorded spread keeps its mode.
MODE_GATE_VAR = 1e-4


def whitened_posterior(g: np.ndarray, d: np.ndarray, with_loglik: bool = True, gram: np.ndarray | None = None,
                       with_mean: bool = True) -> tuple[str, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Posterior of u ~ N(0, I) given d_c = G u + e, e ~ N(0, I), for C right-hand sides at once.

    Parameters
    ----------
    g : array, shape (M, k), the whitened design G
    d : array, shape (C, M), the whitened residuals of C candidates
    with_loglik : bool
        Whether to compute ``loglik`` (a single candidate needs no weight).
    gram : array, shape (M, M), optional
        G Gᵀ when the caller has it (not modified).
    with_mean : bool
        False: ``u`` is None in the observation form (a caller that computes its own mean).

    Returns
    -------
    form : "observation" (M <= k) or "information"
    chol : array, lower Cholesky factor L of I + G Gᵀ (M, M) or of I + Gᵀ G (k, k): the posterior
        covariance Q = (I + GᵀG)⁻¹ (:meth:`~deepprompt_ros.primitive.latent.LinearBlock.whitened_var`)
    u : array, shape (C, k), the posterior means (I + GᵀG)⁻¹ Gᵀ d_c = Gᵀ (I + GGᵀ)⁻¹ d_c
    loglik : array, shape (C,), or None without ``with_loglik``
        −½ d_cᵀ (I + G Gᵀ)⁻¹ d_c = −½ (‖d_c − G u_c‖² + ‖u_c‖²): the log marginal likelihood of d_c
        up to the term −½ log det(I + G Gᵀ) every candidate shares.
    """
    m, k = g.shape
    c = d.shape[0]
    if m == 0:
        return "observation", np.zeros((0, 0)), np.zeros((c, k)), np.zeros(c) if with_loglik else None
    if m <= k:
        s = g @ g.T if gram is None else gram.copy()
        s.flat[::m + 1] += 1.0  # I + G Gᵀ
        chol = _cholesky(s)  # (kept for the covariance; a matrix that is not positive definite is refused here)
        u = loglik = None
        if with_mean or with_loglik:
            a = _general_solve(s, d.T)  # (M, C) (I + GGᵀ)⁻¹ dᵀ
            u = (g.T @ a).T if with_mean else None
            loglik = -0.5 * np.einsum("cm,mc->c", d, a) if with_loglik else None
        return "observation", chol, u, loglik
    # information form: L⁻¹ [Gᵀdᵀ] gives u = L⁻ᵀ L⁻¹ Gᵀ d
    p = g.T @ g
    p.flat[::k + 1] += 1.0  # I + Gᵀ G
    chol = _cholesky(p)
    v = _lower_solve(chol, g.T @ d.T)
    u = _general_solve(chol.T, v).T  # Lᵀ is upper triangular: the LU of gesv is Lᵀ itself (no pivoting)
    loglik = None
    if with_loglik:
        res = d - u @ g.T
        loglik = -0.5 * (np.einsum("cm,cm->c", res, res) + np.einsum("ck,ck->c", u, u))
    return "information", chol, u, loglik


def _cholesky(a: np.ndarray) -> np.ndarray:
    """The lower Cholesky factor of a symmetric positive definite matrix ``a`` (float64, (n, n)): the
    array ``np.linalg.cholesky`` gives, from the gufunc it calls, without its per-call checks. For a
    matrix that is not positive definite in floating point numpy returns NaN, raised here (numpy also
    warns unless invalid values are ignored, as every caller here does).

    Raises
    ------
    numpy.linalg.LinAlgError
        When ``a`` is not positive definite in floating point (or holds NaN).
    """
    chol = _umath_linalg.cholesky_lo(a, signature="d->d")
    if math.isnan(chol[0, 0]):
        raise np.linalg.LinAlgError("the matrix is not positive definite")
    return chol


def _lower_solve(chol: np.ndarray, b: np.ndarray) -> np.ndarray:
    """L⁻¹ b for a Cholesky factor L (positive diagonal) and b (n, m): the array ``np.linalg.solve``
    gives (LAPACK gesv; numpy has no triangular solver, and the LU of a triangular matrix costs little
    beside the substitution), from the gufunc it calls, without its per-call checks."""
    return _general_solve(chol, b)


def _general_solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a⁻¹ b for a square non-singular ``a`` (n, n) and b (n, m), by the gufunc of ``np.linalg.solve``
    (LAPACK gesv) without its per-call checks; a singular ``a`` gives inf or NaN (numpy's warning
    unless invalid values are ignored)."""
    return _umath_linalg.solve(a, b, signature="dd->d")


_EPS_CACHE: dict[tuple[int, int, int], np.ndarray] = {}


def _primes(n: int) -> list[int]:
    """The first ``n`` primes."""
    out, c = [], 2
    while len(out) < n:
        if all(c % p for p in out if p * p <= c):
            out.append(c)
        c += 1
    return out


def normal_points(n: int, dim: int, seed: int) -> np.ndarray:
    """``n`` quasi-random standard normal points in ``dim`` dimensions, (n, dim): the Halton sequence
    (the radical inverses of 1 … n in the first ``dim`` prime bases; J. H. Halton, Numer. Math. 2, 1960)
    shifted modulo 1 by a uniform vector seeded by ``seed`` (Cranley & Patterson, SIAM J. Numer. Anal.
    13(6), 1976), through the inverse normal distribution function. They cover the distribution more
    evenly than as many independent draws: fewer candidates of z_nl leave no mode unvisited and fewer
    fall between the modes."""
    u = np.empty((n, dim))
    for j, base in enumerate(_primes(dim)):
        for i in range(n):
            k, f, r = i + 1, 1.0, 0.0
            while k:
                f /= base
                r += f * (k % base)
                k //= base
            u[i, j] = r
    u = (u + np.random.default_rng(seed).random(dim)) % 1.0
    inv = statistics.NormalDist().inv_cdf
    return np.vectorize(lambda v: inv(min(max(v, 1e-12), 1.0 - 1e-12)), otypes=[float])(u)


def _candidates(mean_nl: np.ndarray, var_nl: np.ndarray, n: int, seed: int) -> np.ndarray:
    """The mean of q(z_nl) and ``n`` seeded quasi-random points of it (:func:`normal_points`),
    (n + 1, k − k_l). The standard normal points of a (n, k − k_l, seed) are made once (read-only,
    shared by every call and thread)."""
    key = (n, mean_nl.shape[0], seed)
    eps = _EPS_CACHE.get(key)
    if eps is None:
        eps = normal_points(n, mean_nl.shape[0], seed)
        eps.flags.writeable = False
        if len(_EPS_CACHE) >= 16:
            _EPS_CACHE.clear()
        _EPS_CACHE[key] = eps
    out = np.empty((n + 1, mean_nl.shape[0]))
    out[0] = mean_nl
    np.multiply(eps, np.sqrt(var_nl), out=out[1:])
    out[1:] += mean_nl
    return out


def mode_candidates(net: "NumpyNet", prior_mean: np.ndarray, prior_var: np.ndarray, n: int, seed: int) -> np.ndarray:
    """The candidates of z_nl of a decoder of several modes (``decoder_modes`` K), (C, k − k_l), each with its
    first coordinate (the mode's) at the median of its mode's interval (:attr:`NumpyNet.mode_medians`): K
    candidates, one per mode, the rest of z_nl at the prior mean, when the decoder reads z_nl through the
    mode alone (no MLP residual) — the exact mixture; else the ``n`` quasi-random points of the prior and its
    mean (:func:`_candidates`), each moved to its mode's median."""
    if not net.mlp_active or n <= 0:
        out = np.repeat(prior_mean[None], net.cfg.decoder_modes, 0)
        out[:, 0] = net.mode_medians
        return out
    out = _candidates(prior_mean, prior_var, n, seed)
    out[:, 0] = net.mode_medians[net.mode_of(out)]
    return out


def _mode_weights(net: "NumpyNet", candidates_nl: np.ndarray, loglik: np.ndarray, prior_mean: np.ndarray,
                  prior_var: np.ndarray) -> tuple[np.ndarray, int]:
    """(weights (C,), best) of the candidates of :func:`mode_candidates`: one per mode, the weight ∝ π_k times
    the exact likelihood (the posterior of the mode); points of the prior, ∝ the likelihood (importance
    sampling from the prior). The best: in the mode of the largest posterior weight, the candidate of the
    highest posterior density of z_nl's other coordinates (the first within rounding, TIE_TOLERANCE)."""
    mode = net.mode_of(candidates_nl)
    exact = candidates_nl.shape[0] == net.cfg.decoder_modes and np.array_equal(mode, np.arange(mode.size))
    log_w = loglik + (net.mode_log_shares if exact else 0.0)
    weights = np.exp(log_w - log_w.max())
    weights /= weights.sum()
    top_mode = int(np.argmax(np.bincount(mode, weights=weights, minlength=net.cfg.decoder_modes)))
    log_post = loglik - 0.5 * ((candidates_nl[:, 1:] - prior_mean[1:]) ** 2 / prior_var[1:]).sum(1)
    log_post = np.where(mode == top_mode, log_post, -np.inf)
    top = log_post.max()
    best = int(np.flatnonzero(log_post >= top - TIE_TOLERANCE * max(1.0, abs(top)))[0])
    return weights, best


def moved_prior_means(net: "NumpyNet", context_mean: np.ndarray, context_var: np.ndarray) -> np.ndarray | None:
    """The prior of z_lin for each mode of the decoder, (K, k_l): the encodings' aggregation q_c (``context_mean``,
    ``context_var``, (k,)) moved to the mode; None where no move applies (one mode, an MLP residual, or no
    encoding informs z_lin: every variance 1).

    The decoder reads z_nl through the mode alone, whose step passes the encoders no gradient: the training
    decodes each draw of the aggregation with the mode the draw chooses, so the encodings of the contexts and
    images give z_lin relative to the modes' mean over those draws. For mode k, whose decoder adds Φ m_k, the
    prior of z_lin is theirs moved by that mode's offset from the mean in z_lin (u_k − ū,
    :meth:`NumpyNet.mode_latent_offsets`, ū under q_c's distribution of the mode's coordinate) as far as they
    inform it: m − (1 − σ²)(u_k − ū) per coordinate, the aggregation of the prior N(0, I) with the moved
    encodings."""
    k_l = net.k_lin
    if not net.has_modes or net.mlp_active or not np.any(context_var[:k_l] < 1.0):
        return None
    u = net.mode_latent_offsets()
    u = u - net.mode_probabilities(context_mean[k_l], context_var[k_l]) @ u
    return context_mean[:k_l] - (1.0 - context_var[:k_l]) * u


def condition_split(net: "NumpyNet", context_mean: np.ndarray, context_var: np.ndarray, all_mean: np.ndarray,
                    all_var: np.ndarray, x: np.ndarray, y: np.ndarray, w: np.ndarray, mask: np.ndarray,
                    noise: float, n_candidates: int = 32, seed: int = 0,
                    candidates_nl: np.ndarray | None = None,
                    context_rows: tuple[np.ndarray, np.ndarray] | None = None,
                    smooth_noise: float | None = None, weight_noise: float | None = None,
                    fixed_weights: np.ndarray | None = None, move_prior: bool = True) -> LatentGaussian:
    """q(z) of a split latent: z_lin exactly conditioned on the via-points for each z_nl candidate.

    Parameters
    ----------
    net : NumpyNet of a model with ``latent_linear`` k_l > 0
    context_mean, context_var : array, shape (k,)
        q_c(z), the aggregation of contexts and images only; its z_lin block is the prior of z_lin (with
        several modes and ``move_prior``, moved to each candidate's mode).
    all_mean, all_var : array, shape (k,)
        The aggregation of everything (via-points included); its z_nl block proposes the candidates (with
        ``decoder_modes`` the prior does: :func:`mode_candidates`).
    x : array, shape (n,); y : array, shape (n, d) joint units
    w : array, shape (n,), ω >= 0, or None (every ω = 1)
    mask : array of bool, shape (n, d), or None (every joint of every via-point)
        The rows: the observed joints of the via-points of weight ω > 0 (none of a via-point of weight 0).
    noise : float
        ν, the via-point standard deviation in normalized joint units (ω scales the precision).
    n_candidates : int
        Quasi-random points of q(z_nl) besides its mean (none when the decoder does not read z_nl: k_l = k, or
        residual_scale 0 without modes; one per mode with modes and residual_scale 0).
    seed : int
        Of the points' random shift (the same request gives the same latent).
    candidates_nl : array, shape (C, k − k_l), optional
        Candidates to use instead of drawing them (refinement re-conditions with the same ones).
    context_rows : (G (M', k_l), e (M',) or (K, M') per mode of the decoder), optional
        Further observations of z_lin, e − G z_lin ~ N(0, I): the low-dimensional contexts modelled
        linearly (:meth:`deepprompt_ros.primitive.linear_context.LinearContext.rows`), conditioned on
        together with the via-points (which may then be none: x of shape (0,)).
    smooth_noise : float, optional
        A noise ν_s > ``noise``: each candidate's z_lin mean is then the posterior mean at ν_s (which
        smooths the via-points' own noise as the cross-validated via_noise does) moved by the smallest
        change of the trajectory that meets the via-points (:func:`smallest_change`), instead of the
        posterior mean at ``noise``, which interpolates them. The covariance and the candidates' weights
        stay those at ``noise``. Not used when there are more rows than k_l (the via-points cannot all
        be met) or no via-point. When the best candidate's change would exceed
        :data:`~deepprompt_ros.primitive.latent.PLANNER_CHANGE_BOUND` times its largest miss, no
        candidate is moved: the means stay at ν_s and miss the via-points (``via_error`` says by how much).

    weight_noise : float, optional
        With several modes of the decoder: the via-point noise the modes' weights are computed at instead of
        ``noise`` (``ModelConfig.mode_noise``; the context rows keep theirs).
    fixed_weights : array, shape (C,), optional
        With several modes and no MLP residual: the candidates' weights to keep instead of computing them
        (:func:`refine_split` conditions again at smaller noises, and the evidence for the modes stays that of
        the first conditioning).
    move_prior : bool
        With several modes and no MLP residual: whether the z_lin of ``context_mean``, ``context_var`` (the
        encodings' aggregation) is moved to each candidate's mode (:func:`moved_prior_means`; False: taken as
        it is).

    Returns
    -------
    LatentGaussian with ``linear`` set; ``mean`` = the candidate of the highest posterior density — with
    several modes and no MLP residual, the modes' z_lin means weighted by their posterior probabilities,
    which ``mode_weights`` holds (the posterior mean of the trajectory).
    """
    k_l = net.k_lin
    m, s = context_mean[:k_l], np.sqrt(context_var[:k_l])
    # the prior of z_nl, q_c; with several modes its first coordinate, which chooses the mode, N(0, 1) whatever
    # the encodings say (the modes are told apart by the exact likelihoods alone; mode_candidates)
    prior_mean, prior_var = context_mean[k_l:], context_var[k_l:]
    modes = net.has_modes
    if modes:
        prior_mean, prior_var = prior_mean.copy(), prior_var.copy()
        prior_mean[0], prior_var[0] = 0.0, 1.0
    if candidates_nl is None:
        if not net.decoder_reads_z_nl:
            candidates_nl = all_mean[None, k_l:]
        elif modes:
            candidates_nl = mode_candidates(net, prior_mean, prior_var, n_candidates, seed)
        else:
            candidates_nl = _candidates(all_mean[k_l:], all_var[k_l:], n_candidates, seed)
    per_mode = moved_prior_means(net, context_mean, context_var) if move_prior else None
    moved = per_mode is not None
    if moved:
        m = per_mode[net.mode_of(candidates_nl)]  # (C, k_l)
    if x.shape[0] == 0:  # no via-point: the context rows alone
        h, g = np.zeros((0, k_l)), np.zeros((0, k_l))
        r, d = np.zeros((candidates_nl.shape[0], 0)), np.zeros((candidates_nl.shape[0], 0))
    elif mask is None or mask.all():  # every joint of every via-point: rows in (via-point, joint) order
        lin_b, lin_a = net.linear_design(x)  # (n, d), (n, d, k_l)
        off = net.decode_nonlinear(candidates_nl, x)  # (C, n, d)
        off += lin_b
        sigma = noise * net.y_std if w is None else noise * net.y_std / np.sqrt(w)[:, None]  # (d,) or (n, d)
        h = lin_a.reshape(-1, k_l)  # (M, k_l)
        g = (lin_a * (s / sigma[..., None])).reshape(h.shape)  # whitened design
        r = np.subtract(y, off, out=off)  # (C, n, d)
        d = r - (lin_a @ m if m.ndim == 1 else np.einsum("ndk,ck->cnd", lin_a, m))
        d /= sigma  # whitened residuals of the candidates
        r, d = r.reshape(r.shape[0], -1), d.reshape(r.shape[0], -1)  # (C, M)
    else:
        rows = mask.any(1)
        lin_b, lin_a = net.linear_design(x[rows])
        off = net.decode_nonlinear(candidates_nl, x[rows]) + lin_b
        sel = mask[rows]
        h = lin_a[sel]
        w_rows = np.ones(sel.shape[0]) if w is None else w[rows]
        sigma = (noise * net.y_std / np.sqrt(w_rows)[:, None])[sel]
        r = (y[rows][None] - off)[:, sel]
        g = h * (s / sigma[:, None])  # whitened design
        d = r - m @ h.T
        d /= sigma  # whitened residuals of the candidates
    if context_rows is not None and context_rows[0].shape[0]:
        g_c, e_c = context_rows
        g = np.concatenate([g, g_c * s], 0)
        if e_c.ndim == 2:  # one row per mode of the decoder: each candidate's, by the mode its z_nl chooses
            e_c = e_c[net.mode_of(candidates_nl)]
        d = np.concatenate([d, np.broadcast_to(e_c - m @ g_c.T, (d.shape[0], g_c.shape[0]))], 1)
    single = candidates_nl.shape[0] == 1
    n_via = h.shape[0]
    smooth = smooth_noise is not None and smooth_noise > noise and 0 < n_via <= k_l
    if smooth:  # H M⁻¹ (rows as h) for smallest_change
        hm = (net.metric_design(x).reshape(-1, k_l) if mask is None or mask.all() else
              net.metric_design(x[mask.any(1)])[mask[mask.any(1)]])
    gram = g @ g.T if smooth else None
    try:
        if smooth and single and g.shape[0] <= k_l:  # the mean needs no factor: the block factors when read
            form, chol, u, loglik = "observation", None, None, None
        else:
            form, chol, u, loglik = whitened_posterior(g, d, with_loglik=not single, gram=gram,
                                                       with_mean=not smooth)
    except np.linalg.LinAlgError as exc:  # I + GGᵀ is positive definite unless rounding or an overflow breaks it
        if not np.isfinite(g.sum() + d.sum()):
            return _overflow(net.cfg.latent_dim, context_mean, context_var)
        raise ValueError(f"the exact conditioning of the linear latent block failed ({exc}) with via-point noise "
                         f"{noise:g}: " + FACTORABLE_INPUTS) from None
    # an overflow in G or d ends here (or in the factorization; the planner's path without one: in the mean)
    if u is not None and not math.isfinite(u.sum() + (0.0 if single else loglik.sum())):
        return _overflow(net.cfg.latent_dim, context_mean, context_var)
    if single:
        weights, best = np.ones(1), 0
    elif modes and fixed_weights is not None and not net.mlp_active:
        weights = np.asarray(fixed_weights, dtype=np.float64)
        best = int(np.argmax(weights))
    elif modes:
        weight_noise = None if weight_noise is None or weight_noise == noise or not n_via else float(weight_noise)
        if weight_noise is not None:  # the via rows whitened at weight_noise: rows and residuals times ν / ν_w
            rows = np.ones(g.shape[0])
            rows[:n_via] = noise / weight_noise
            try:
                at_weight_noise = whitened_posterior(g * rows[:, None], d * rows, with_mean=False)[3]
            except np.linalg.LinAlgError:  # (a weight noise far below the request's): the weights at ``noise``
                at_weight_noise = None
            if at_weight_noise is not None and math.isfinite(at_weight_noise.sum()):
                loglik = at_weight_noise
            else:  # the weights at ``noise``, and the latent records that noise (a refinement conditions again at it)
                weight_noise = None
        weights, best = _mode_weights(net, candidates_nl, loglik, prior_mean, prior_var)
    else:
        # the posterior ∝ p(via-points | z_nl) q_c(z_nl): the executed mean is the candidate of the highest
        # posterior density (the first within rounding of it, TIE_TOLERANCE: the same choice on every
        # machine); the weights are its self-normalized importance weights under the proposal q_all(z_nl),
        # so the via-points count once, through their exact likelihood, not again through their encodings
        log_post = loglik - 0.5 * ((candidates_nl - prior_mean) ** 2 / prior_var).sum(1)
        top = log_post.max()
        best = int(np.flatnonzero(log_post >= top - TIE_TOLERANCE * max(1.0, abs(top)))[0])
        log_w = log_post + 0.5 * ((candidates_nl - all_mean[k_l:]) ** 2 / all_var[k_l:]).sum(1)
        weights = np.exp(log_w - log_w.max())
        weights /= weights.sum()
    if not smooth:
        z_lin = m + u * s  # (C, k_l)
    else:
        # the via rows' whitening at ν_s: rows and residuals scale by f = ν / ν_s (the context rows stay)
        f = noise / smooth_noise
        if g.shape[0] == n_via:  # via rows only: one factor
            scale, gram_s = f, gram * (f * f)
        else:
            scale = np.ones(g.shape[0])
            scale[:n_via] = f
            gram_s = gram * scale * scale[:, None]
        z_s = m + _posterior_mean(g, d * scale, gram_s, scale) * s
        miss = r - z_s @ h.T
        change = smallest_change(net, h, miss, hm)
        # a correction that would move the trajectory by more than PLANNER_CHANGE_BOUND times the smoothed
        # mean's largest miss is not made: the mean stays the smoothed one, which misses the via-points.
        # ‖L Δ‖∞ <= ‖L Δ‖₂ <= sqrt(Δᵀ M Δ): within the bound without forming L Δ when the last one is
        bound = PLANNER_CHANGE_BOUND * float(np.abs(miss[best]).max())
        if change is not None and (math.sqrt(max(change[1][best], 0.0)) <= bound or
                                   float(np.abs(net.trajectory_rows() @ change[0][best]).max()) <= bound):
            z_lin, after = z_s + change[0], change[2]
        else:
            z_lin, after = z_s, miss
        if not math.isfinite(z_lin.sum() + (0.0 if single else loglik.sum())):
            return _overflow(net.cfg.latent_dim, context_mean, context_var)
    cands = np.concatenate([z_lin, candidates_nl], 1)  # (C, k)
    mean, mode_weights = cands[best].copy(), None
    if modes and not net.mlp_active:
        # the decoder reads z_nl through the mode alone: the executed mean is the posterior mean of the
        # trajectory, Σ_k P(k | via-points, contexts) (Φ m_k + Φ(b + A z̄_k)), the modes' offsets and z_lin
        # means weighted alike (one mode when the evidence tells them apart, between them when it does not:
        # the least-squares prediction); the latent keeps the most probable mode's z_nl
        mode_weights = np.bincount(net.mode_of(candidates_nl), weights=weights, minlength=net.cfg.decoder_modes)
        mean[:k_l] = weights @ z_lin
    # the executed mean at the observed joints of the via-points: offset + H z_lin (joint units), per candidate
    # and weighted as the mean is
    if not h.shape[0]:
        via_error = 0.0
    elif mode_weights is None and smooth:
        via_error = float(np.abs(after[best]).max())
    elif mode_weights is None:
        via_error = float(np.abs(r[best] - h @ cands[best, :k_l]).max())
    else:
        via_error = float(np.abs(weights @ (r - z_lin @ h.T)).max())
    nl_var = all_var[k_l:]
    if modes:  # the prior's, the mode's coordinate narrow: a latent perturbed by its spread keeps its mode
        nl_var = prior_var.copy()
        nl_var[0] = MODE_GATE_VAR
    block = LinearBlock(scale=s, candidates=cands, weights=weights, factor=chol,
                        design=g if form == "observation" else None, form=form, noise=float(noise),
                        via_error=via_error, nl_var=nl_var, weight_noise=weight_noise if modes else None,
                        move_prior=moved, prior=(context_mean, context_var), context_rows=context_rows)
    # (the variance: from the block when it is read)
    return LatentGaussian(mean, linear=block, context_mean=context_mean, context_var=context_var,
                          mode_weights=mode_weights)


#: :func:`smallest_change`: the largest miss of a row by the change solved for, relative to the largest
#: residual (at least 1 rad), for the change to count as meeting the rows.
CHANGE_MET_TOLERANCE = 1e-6


def smallest_change(net: "NumpyNet", h: np.ndarray, residual: np.ndarray,
                    hm: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The changes Δ of z_lin that meet the via-point rows exactly with the smallest change of the
    linear part's trajectory: argmin Δᵀ M Δ subject to H Δ = r, i.e. Δ = M⁻¹ Hᵀ (H M⁻¹ Hᵀ)⁻¹ r, with M
    the trajectory metric (:meth:`NumpyNet.trajectory_metric_inverse`: squared change over the phases,
    joint units, every joint).

    A least-squares estimate of a trajectory from noisy points that must then pass them exactly pays
    the least in squared error for the least change: the correction stays near the via-points, where
    the exact posterior mean would interpolate the points' noise into the whole trajectory along the
    demonstrations' correlations.

    h : array, shape (M, k_l), the rows (joint units); residual : array, shape (C, M), per candidate;
    hm : array, shape (M, k_l), optional, H M⁻¹ when the caller has it (:meth:`NumpyNet.metric_design`)
    Returns (Δ (C, k_l), Δᵀ M Δ (C,) = rᵀ (H M⁻¹ Hᵀ)⁻¹ r, r − H Δ (C, M): the rows' misses after the change,
    rounding), or None when the rows cannot all be met:
    H M⁻¹ Hᵀ singular, or the Δ solved for misses a row by more than :data:`CHANGE_MET_TOLERANCE` (relative
    to the largest residual, at least 1 rad) -- dependent rows whose Gram matrix is singular in exact
    arithmetic can be solved to finite, useless values by rounding, depending on the BLAS kernel."""
    if hm is None:
        hm = h @ net.trajectory_metric_inverse()  # (M, k_l)
    lam = _general_solve(hm @ h.T, residual.T).T  # (C, M); a singular H M⁻¹ Hᵀ gives inf / NaN: refused
    out = lam @ hm
    if not math.isfinite(out.sum()):
        return None
    after = residual - out @ h.T
    if residual.size:
        worst = float(np.abs(after).max())  # (the residual's size is needed only beyond the 1 rad floor)
        if worst > CHANGE_MET_TOLERANCE and worst > CHANGE_MET_TOLERANCE * float(np.abs(residual).max()):
            return None
    return out, (lam * residual).sum(1), after


def _posterior_mean(g: np.ndarray, d: np.ndarray, gram: np.ndarray, rows: np.ndarray | float) -> np.ndarray:
    """(C, k) the posterior means G'ᵀ (I + G' G'ᵀ)⁻¹ d_c of :func:`whitened_posterior` alone for the
    design G' = diag(rows) G (``rows`` (M,) or one factor), from ``gram`` = G' G'ᵀ (M × M, modified),
    by one solve and no factor kept."""
    gram.flat[::gram.shape[0] + 1] += 1.0
    return (_general_solve(gram, d.T).T * rows) @ g


def _overflow(k: int, context_mean: np.ndarray, context_var: np.ndarray) -> LatentGaussian:
    """The latent of a conditioning that overflowed (NaN mean and variance: no distribution to give)."""
    nan = np.full(k, np.nan)
    return LatentGaussian(nan, nan, context_mean=context_mean, context_var=context_var)


def linear_block_variance(block: LinearBlock, jac: np.ndarray) -> np.ndarray:
    """diag(J Σ Jᵀ) for the posterior covariance Σ of z_lin and rows J (n, k_l), without forming Σ:
    with a = J diag(scale), aᵀQa = ‖a‖² − ‖L⁻¹ G aᵀ‖² (observation form) or ‖L⁻¹ aᵀ‖² (information
    form), per row; shape (n,), >= 0."""
    a = jac * block.scale
    if block.form == "information":
        b = _lower_solve(block.chol, a.T)
        return np.einsum("kn,kn->n", b, b)
    out = np.einsum("nk,nk->n", a, a)
    if block.design.shape[0]:
        b = _lower_solve(block.chol, block.design @ a.T)  # W aᵀ, W = L⁻¹G
        out -= np.einsum("mn,mn->n", b, b)
    return np.maximum(out, 0.0)


@dataclasses.dataclass(frozen=True)
class SplitRefinement:
    """Outcome of :func:`refine_split`: the best split latent, its max via-point error (joint units)
    under ``tol``'s test, the iterations used (one per noise reduction), the max error before and
    after each, and why it stopped."""

    latent: LatentGaussian
    max_error: float
    tol: float
    iterations: int
    history: list
    reason: str


def refine_split(net: "NumpyNet", latent: LatentGaussian, x: np.ndarray, y: np.ndarray, mask: np.ndarray,
                 tol: float, max_iterations: int, factor: float = 10.0, min_noise: float = 1e-12,
                 deadline: float = math.inf) -> SplitRefinement:
    """Meet via-points with a split latent's mean by exact conditioning of z_lin alone.

    0 iterations when the mean meets them (|error| <= ``tol`` on every constrained joint) already.
    Else z_lin is conditioned again on these via-points (weight 1 each, constrained joints only),
    from the prior and the contexts' rows the block records (as the first conditioning: moved to the
    modes where it was) and with the latent's z_nl candidates, with the noise divided by
    ``factor`` per iteration (the error of a via-point the linear block can reach falls as the
    noise squared once the noise is below the scale of the block's weakest direction the via-points
    need: it can stay level over several reductions first) until the mean meets them, the noise falls
    below ``min_noise`` (more constraints than the block can meet), the factorization fails or
    overflows, ``max_iterations``, or ``deadline`` (a :func:`time.perf_counter` time) has passed
    before an iteration. The best latent found is returned, with the covariance of ``latent``
    (:func:`moved_mean`); a latent replaces the best one only if its error is lower by more than 10 %.

    Parameters
    ----------
    net : NumpyNet; latent : LatentGaussian with ``linear`` and ``context_mean`` set
    x : array, shape (n,); y : array, shape (n, d) joint units; mask : array of bool, shape (n, d)
    """
    k_l = net.cfg.latent_linear

    def error(lat):
        return float(np.abs((y - net.decode_weighted(lat.mean, x, lat.mode_weights))[mask]).max())

    best, best_err = latent, error(latent)
    history = [best_err]
    block = latent.linear
    noise, it, reason = block.noise, 0, "met by the exact conditioning"
    cands = block.candidates[:, k_l:]
    # the prior the block was conditioned from (a block built by hand: the latent's recorded q_c)
    prior_mean, prior_var = block.prior if block.prior is not None else (latent.context_mean, latent.context_var)
    # q_all of z_nl, all condition_split reads of it: the candidates' proposal (the first candidate is its mean
    # where the candidates are its points; otherwise the mean is not read)
    all_mean = np.concatenate([prior_mean[:k_l], cands[0]])
    all_var = np.concatenate([prior_var[:k_l], block.nl_var])
    while best_err > tol:
        if it >= max_iterations:
            reason = "budget"
            break
        if time.perf_counter() >= deadline:
            reason = "time budget"
            break
        noise /= factor
        if noise < min_noise:
            reason = (f"via-point noise below {min_noise:g} without meeting the via-points: the linear block cannot "
                      "meet them")
            break
        it += 1
        try:
            with np.errstate(all="ignore"):
                lat = condition_split(net, prior_mean, prior_var, all_mean, all_var, x, y, None, mask, noise,
                                      candidates_nl=cands, context_rows=block.context_rows,
                                      weight_noise=block.weight_noise or block.noise,
                                      fixed_weights=None if latent.mode_weights is None else block.weights,
                                      move_prior=block.move_prior)
            err = error(lat)
        except ValueError:  # the factorization failed at this noise
            reason = "the conditioning's factorization failed at a smaller noise"
            history.append(best_err)
            break
        if not np.isfinite(err):
            reason = "the conditioning overflowed at a smaller noise"
            history.append(best_err)
            break
        if err < 0.9 * best_err:  # (a latent barely better than the last is not taken: it is no nearer)
            best, best_err = lat, err
        history.append(best_err)
        if best_err <= tol:
            reason = f"met by exact conditioning of the linear block at via-point noise {noise:.3g}"
    if best is not latent:
        best = moved_mean(best, latent)
    return SplitRefinement(best, best_err, tol, it, history, reason)


def moved_mean(moved: LatentGaussian, original: LatentGaussian) -> LatentGaussian:
    """The split latent with the candidates (z_lin means and weights) of ``moved`` and the covariance
    of ``original``: the refinement moves the mean onto the via-points while the spread stays the one
    of the noise the via-points were asked with. For the linear block this is the optimum of the
    paper's Eq. 5 objective, whose sample-mean term does not depend on the spread and whose
    ‖σ* − σ̃‖² is zero at the original σ*; a covariance of the smaller refinement noise would
    understate the uncertainty away from the via-points."""
    o, m = original.linear, moved.linear
    var = original.var  # (first: a factor it computes is kept for the new block too)
    block = dataclasses.replace(m, scale=o.scale, factor=o.factor, design=o.design, form=o.form, noise=o.noise,
                                nl_var=o.nl_var)
    return LatentGaussian(moved.mean, var, linear=block, context_mean=original.context_mean,
                          context_var=original.context_var, mode_weights=moved.mode_weights)
