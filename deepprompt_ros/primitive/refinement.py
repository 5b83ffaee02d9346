"""Deployment-time refinement of a conditioned latent so that the executed trajectory meets the
via-points (paper Eq. 5 and appendix), two algorithms:

* :func:`refine_exact` — meet the via-points exactly (to ``tol``): Levenberg–Marquardt on the mean
  μ̃ with the decoder's exact Jacobian, continuation through smooth surrogates of the ReLU decoder
  and seeded restarts (stage 1, :class:`_MeanFit`), then σ̃ fitted to the paper's Monte-Carlo
  objective with fixed samples (stage 2, :func:`_fit_std`).
* :func:`refine_map` — the MAP latent of a regularized least-squares problem: staying where the
  model has seen demonstrations instead of meeting the via-points exactly.

A :class:`~deepprompt_ros.primitive.deep_promp.DeepProMP` offers them as ``refine`` and ``refine_map``.
Units: phases in [0, 1], joint positions in joint units (rad), μ̃ in units of the prior's std.
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import TYPE_CHECKING, Sequence

import numpy as np

from deepprompt_ros.primitive.latent import LatentGaussian
from deepprompt_ros.primitive.linear_conditioning import (MODE_GATE_VAR, SplitRefinement, condition_split,
                                                          moved_prior_means, refine_split)

if TYPE_CHECKING:
    from deepprompt_ros.primitive.deep_promp import DeepProMP

__all__ = ["RefinementResult", "refinement_inputs", "refine_exact", "refine_map"]


@dataclasses.dataclass(frozen=True)
class RefinementResult:
    """Outcome of :func:`refine_exact` (:meth:`DeepProMP.refine`) and :func:`refine_map`
    (:meth:`DeepProMP.refine_map`).

    Attributes
    ----------
    latent : LatentGaussian
        Refined (μ̃, σ̃²). The executed trajectory is the decoder at z = μ̃ (with the decoder's modes
        weighted by the latent's ``mode_weights`` when it has them:
        :meth:`~deepprompt_ros.primitive.deep_promp.DeepProMP.mean_trajectory`).
    max_error : float
        max_i,j |y_ij − μ_y(μ̃, x_i)_j| over the constrained joints (rad): what the robot will miss by.
    errors : array, shape (n, d)
        Signed residuals y − μ_y(μ̃, x) per via-point and joint (0 on unconstrained joints).
    sample_mean_error : float
        Same, for the mean over the K fixed Monte-Carlo samples (the paper's objective).
    iterations : int
    reachable : bool
        True when max_error <= tol. False means the solver reached a stationary point (or its
        budget) with a residual above tol: the via-points cannot all be met by this primitive; the
        best fit found is returned, never a silent miss.
    reason : str
    out_of_time : bool
        True when the time budget (``time_budget`` of :func:`refine_exact`) ended the refinement
        before it met tol (``reachable`` is then False): a larger budget may meet the via-points.
    error_history : array, shape (iterations + 1,)
        Max via-point error of the exact decoder at the best μ̃ found so far: before the first
        iteration, then after each one (all stages: LM, continuation, restarts). Non-increasing;
        its last value is ``max_error``.
    """

    latent: LatentGaussian
    max_error: float
    errors: np.ndarray
    sample_mean_error: float
    iterations: int
    reachable: bool
    reason: str
    error_history: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    out_of_time: bool = False


def refinement_inputs(prim: "DeepProMP", via_x, via_y, joint_mask, max_iterations: int, tol: float):
    """Validated (x (n,), y (n, d), mask (n, d) bool) of a refinement; ``ValueError`` otherwise."""
    x = prim.check_phases(via_x, "via-point phase")
    if x.size == 0:
        raise ValueError("refinement needs at least one via-point")
    y = prim.check_positions(via_y, x.shape[0])
    mask = prim.check_mask(joint_mask, x.shape[0])
    if not mask.any():
        raise ValueError("joint mask selects no joint; expected at least one constrained joint")
    if max_iterations < 1 or not tol > 0:
        raise ValueError("max_iterations must be >= 1 and tol > 0")
    return x, y, mask


# ---------------------------------------------------------------------------------------- MAP
def refine_map(prim: "DeepProMP", latent: LatentGaussian, via_x, via_y, joint_mask=None, prior: str = "posterior",
               noise_std=None, max_iterations: int = 50, tol: float = 1e-6,
               latent_bound: float = 5.0) -> RefinementResult:
    """MAP refinement: μ̃ = argmin_z Σ_ij m_ij (y_ij − μ_y(z, x_i)_j)² / s_j² + (z − m)ᵀ P (z − m).

    A regularized least-squares step instead of meeting the via-points exactly. ``prior``:
    ``"posterior"`` — m, P = the mean and precision diag(1/σ²) of what ``latent`` knows from the
    inputs other than the via-points: q_c, the aggregation of its contexts and images, which
    :meth:`DeepProMP.condition` records in the latent (``context_mean``, ``context_var``), for plain
    and split latents alike; the via-points enter through the likelihood alone, never twice. A latent
    that records no q_c (built by hand) is the prior itself: it must not hold the via-points'
    evidence. With several modes of the decoder (``mode_weights``): the MAP latent of the most probable
    mode, whose posterior prior is the one that conditioning gave the mode (the encodings moved to it, the
    contexts' rows; :func:`_mode_prior`). ``"standard"`` — the model's prior N(0, I). For a decoder that is linear
    in z (``decoder_basis`` > 0 with ``residual_scale`` 0) and the standard prior this is exactly
    Gaussian conditioning of the latent linear-Gaussian model — ProMP conditioning in the latent.
    Solved by Levenberg–Marquardt with the decoder's exact Jacobian (one step when it is linear).

    Parameters
    ----------
    prim : DeepProMP
    latent : LatentGaussian, the initialization (its mean; with ``mode_weights``, moved to the most probable
        mode) and (``prior="posterior"``) the prior (its recorded q_c, else itself; with ``mode_weights``,
        :func:`_mode_prior`)
    via_x : array, shape (n,); via_y : array, shape (n, d)
    joint_mask : array of bool, shape (n, d) or (d,), optional; joints to meet (default all)
    noise_std : float or array (d,), optional
        s_j, the via-point standard deviation in joint units; default σ_y · the joint's
        normalization std (the decoder's own noise level).
    latent_bound : float
        μ̃ stays in the box |μ̃_i| ≤ latent_bound.

    Returns
    -------
    RefinementResult with latent N(μ̃, diag of the Laplace covariance (JᵀJ/s² + P)⁻¹);
    ``max_error`` / ``reachable`` as in :func:`refine_exact` (a MAP fit usually does not meet
    tol: it is not meant to), ``sample_mean_error`` = ``max_error``.
    """
    x, y, mask = refinement_inputs(prim, via_x, via_y, joint_mask, max_iterations, tol)
    start = np.asarray(latent.mean, dtype=np.float64)
    if latent.mode_weights is not None:  # several modes: the MAP latent of the most probable one
        mode = int(np.argmax(latent.mode_weights))
        start = _one_mode(prim, latent, mode).mean if latent.linear is None else _in_mode(prim, start, mode)
    if prior == "posterior":
        known = latent if latent.context_mean is None else LatentGaussian(latent.context_mean, latent.context_var)
        if latent.mode_weights is not None:
            known = _mode_prior(prim, latent, start)
        m, prec = np.asarray(known.mean, dtype=np.float64), 1.0 / np.asarray(known.var, dtype=np.float64)
    elif prior == "standard":
        m, prec = np.zeros(prim.latent_dim), np.ones(prim.latent_dim)
        if latent.mode_weights is not None:  # (the mode held, as _mode_prior holds it)
            k_l = prim.cfg.latent_linear
            m[k_l], prec[k_l] = start[k_l], 1.0 / MODE_GATE_VAR
    else:
        raise ValueError(f"MAP prior '{prior}' unknown; expected 'posterior' or 'standard'")
    y_std = np.asarray(prim.norm.y_std, dtype=np.float64)
    s = prim.cfg.sigma_y * y_std if noise_std is None else np.broadcast_to(
        np.asarray(noise_std, dtype=np.float64), (prim.n_joints,))
    if not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise ValueError(f"noise_std must be > 0 (joint units), got {noise_std}")
    wgt = mask.astype(np.float64) / s[None, :]  # residual weights m_ij / s_j

    def terms(z):
        y_hat, jac = prim.decoder_jacobian(z, x)
        r = ((y - y_hat) * wgt).reshape(-1)
        J = (jac * wgt[:, :, None]).reshape(-1, prim.latent_dim)
        dz = z - m
        return r, J, float(r @ r + dz @ (prec * dz)), y_hat

    z = np.clip(start, -latent_bound, latent_bound)
    r, J, cost, y_hat = terms(z)
    history = [float(np.abs((y - y_hat) * mask).max())]
    lam, it, reason = 0.0, 0, "budget"
    while it < max_iterations:
        it += 1
        H = J.T @ J + np.diag(prec)
        g = J.T @ r - prec * (z - m)  # −½ ∇cost
        step = np.clip(z + np.linalg.solve(H + lam * np.diag(np.diag(H)), g), -latent_bound, latent_bound) - z
        r2, J2, c2, y2 = terms(z + step)
        if c2 <= cost:
            converged = cost - c2 <= 1e-12 * max(1.0, cost) or np.abs(step).max() < 1e-10
            z, r, J, cost, y_hat = z + step, r2, J2, c2, y2
            lam = lam / 3.0
            history.append(float(np.abs((y - y_hat) * mask).max()))
            if converged:
                reason = "converged (MAP)"
                break
        else:
            lam = max(lam * 4.0, 1e-6)
            history.append(history[-1])
            if lam > 1e8:
                reason = "converged (MAP, no descent step)"
                break
    cov = np.linalg.inv(J.T @ J + np.diag(prec))
    err = (y - y_hat) * mask
    max_err = float(np.abs(err).max())
    return RefinementResult(latent=LatentGaussian(z, np.diag(cov).copy()), max_error=max_err, errors=err,
                            sample_mean_error=max_err, iterations=it, reachable=max_err <= tol, reason=reason,
                            error_history=np.minimum.accumulate(np.array(history)))


def _in_mode(prim: "DeepProMP", z: np.ndarray, mode: int) -> np.ndarray:
    """``z`` (k,) with the coordinate that chooses the decoder's mode at ``mode``'s median unless it is in that
    mode's interval already."""
    net, k_l = prim._np, prim.cfg.latent_linear
    if int(net.mode_of(z[k_l:])) == mode:
        return z
    z = z.copy()
    z[k_l] = net.mode_medians[mode]
    return z


def _one_mode(prim: "DeepProMP", latent: LatentGaussian, mode: int) -> LatentGaussian:
    """An aggregation's latent with several modes of the decoder (``mode_weights``) as the latent of one of
    them: z_nl's mode coordinate at the mode's median with the variance a conditioned latent records for it
    (``MODE_GATE_VAR``), z_lin moved to the mode as the encodings are
    (:func:`~deepprompt_ros.primitive.linear_conditioning.moved_prior_means`)."""
    k_l = prim.cfg.latent_linear
    mean, var = _in_mode(prim, np.asarray(latent.mean, dtype=np.float64), mode), latent.var.copy()
    per_mode = moved_prior_means(prim._np, latent.mean, latent.var)
    if per_mode is not None:
        mean = mean.copy()
        mean[:k_l] = per_mode[mode]
    var[k_l] = MODE_GATE_VAR
    return LatentGaussian(mean, var, context_mean=latent.context_mean, context_var=latent.context_var)


def _mode_prior(prim: "DeepProMP", latent: LatentGaussian, z: np.ndarray) -> LatentGaussian:
    """What ``latent`` (with several modes of the decoder) knows besides the via-points, for the mode ``z``
    chooses: the prior its conditioning started from (its block's record, else its q_c: a latent of the
    aggregation alone) with z_lin moved to that mode and conditioned on the contexts' rows, as that
    conditioning did for its candidate of the mode; z_nl as recorded (q_c) but for the coordinate that chooses
    the mode: at ``z``'s, with the variance a conditioned latent records for it (``MODE_GATE_VAR``), so the MAP
    latent stays in the mode."""
    block = latent.linear
    if block is not None and block.prior is not None:
        pm, pv = block.prior
    elif latent.context_mean is not None:
        pm, pv = latent.context_mean, latent.context_var
    else:
        pm, pv = latent.mean, latent.var
    k_l = prim.cfg.latent_linear
    given = condition_split(prim._np, pm, pv, pm, pv, np.zeros(0), np.zeros((0, prim.n_joints)), None, None, 1.0, 0,
                            candidates_nl=z[None, k_l:], context_rows=None if block is None else block.context_rows,
                            move_prior=True if block is None else block.move_prior)
    qm, qv = (pm, pv) if latent.context_mean is None else (latent.context_mean, latent.context_var)
    mean, var = np.concatenate([given.mean[:k_l], qm[k_l:]]), np.concatenate([given.var[:k_l], qv[k_l:]])
    mean[k_l], var[k_l] = z[k_l], MODE_GATE_VAR
    return LatentGaussian(mean, var)


# ---------------------------------------------------------------------------------------- exact
def _result_as_is(prim: "DeepProMP", latent: LatentGaussian, x, y, mask, n_samples: int, seed: int, *,
                  tol: float, iterations: int, reason: str, history=None, out_of_time: bool = False,
                  errors: np.ndarray | None = None) -> RefinementResult:
    """The :class:`RefinementResult` of ``latent`` as it is, without fitting it further: its executed
    mean's residuals (``errors`` when the caller has them) and the sample mean error of ``n_samples``
    draws (:meth:`DeepProMP.sample`); ``history`` the errors of the iterations that led to it (None: its
    own error alone)."""
    mf = mask.astype(np.float64)
    r = (y - prim.decode_mean(latent, x)) * mf if errors is None else errors
    y_bar = prim.sample(latent, x, n_samples, seed).mean(0)
    max_err = float(np.abs(r).max())
    return RefinementResult(latent=latent, max_error=max_err, errors=r,
                            sample_mean_error=float(np.abs((y - y_bar) * mf).max()), iterations=iterations,
                            reachable=max_err <= tol, reason=reason,
                            error_history=np.minimum.accumulate(np.asarray(
                                [max_err] if history is None else history, dtype=np.float64)),
                            out_of_time=out_of_time and max_err > tol)


def _split_result(prim: "DeepProMP", split: SplitRefinement, x, y, mask, n_samples: int,
                  seed: int, out_of_time: bool = False) -> RefinementResult:
    """The :class:`RefinementResult` of a split latent refined in its linear block alone; the sample
    mean error is that of ``n_samples`` draws of the latent (candidates by weight, z_lin exact)."""
    return _result_as_is(prim, split.latent, x, y, mask, n_samples, seed, tol=split.tol,
                         iterations=split.iterations, reason=split.reason, history=split.history,
                         out_of_time=out_of_time)


class _MeanFit:
    """Stage 1 of :func:`refine_exact`: μ̃ such that μ_y(μ̃, x) meets the via-points, with the best
    iterate of every run and the non-increasing error history. No iteration starts after
    ``deadline`` (a :func:`time.perf_counter` time); ``out_of_time`` then says so."""

    def __init__(self, prim: "DeepProMP", x: np.ndarray, y: np.ndarray, mask: np.ndarray, tol: float,
                 latent_bound: float, deadline: float = math.inf, time_budget: float | None = None):
        self.prim, self.x, self.y, self.tol, self.latent_bound = prim, x, y, tol, latent_bound
        self.deadline, self.time_budget, self.out_of_time = deadline, time_budget, False
        self.eval_seconds = 0.0  # longest wall time of one residual and Jacobian evaluation
        self.mf = mask.astype(np.float64)
        self.smoothing: float | None = None  # β of the decoder's softplus surrogate, None = exact
        self.eye = np.eye(prim.latent_dim)
        self.history: list[float] = []  # exact-decoder max error at the best μ̃ so far, one entry per iteration
        self.best_mu: np.ndarray | None = None  # the iterate with the smallest exact error seen in any stage
        self.best_err = math.inf

    def residual(self, z):
        t0 = time.perf_counter()
        y_hat, jac = self.prim.decoder_jacobian(z, self.x, self.smoothing)
        r = (self.y - y_hat) * self.mf
        self.eval_seconds = max(self.eval_seconds, time.perf_counter() - t0)
        return r, jac * self.mf[:, :, None]

    def record(self, mu, r):
        # r is exact when no smoothing is active; on a smooth surrogate, decode exactly once more
        err = (float(np.abs(r).max()) if self.smoothing is None
               else float(np.abs((self.y - self.prim.decode(mu, self.x)) * self.mf).max()))
        if err < self.best_err:
            self.best_mu, self.best_err = mu.copy(), err
        self.history.append(self.best_err)

    def levenberg_marquardt(self, mu, budget):
        """Levenberg–Marquardt with Nielsen's damping update (Madsen, Nielsen & Tingleff 2004,
        "Methods for non-linear least squares problems", Alg. 3.16); returns (mu, r, its, reason).

        δ = (JᵀJ + λI)⁻¹ Jᵀ r; the step is accepted when the squared error decreases, and λ
        follows the gain ratio ρ between actual and predicted decrease (λ ← λ·max(1/3, 1−(2ρ−1)³)
        on success, λ ← λν, ν ← 2ν on failure)."""
        k, tol, bound = self.prim.latent_dim, self.tol, self.latent_bound
        r, jac = self.residual(mu)
        if not self.history:
            self.record(mu, r)
        cost = float((r ** 2).sum())
        J = jac.reshape(-1, k)
        A, g = J.T @ J, J.T @ r.reshape(-1)
        lam, nu, it = 1e-3 * max(float(np.diag(A).max()), 1e-12), 2.0, 0
        while it < budget:
            if np.abs(r).max() <= 0.1 * tol:
                return mu, r, it, "converged"
            if np.abs(g).max() < 1e-15 * max(1.0, cost):
                return mu, r, it, "stationary (zero gradient)"
            if time.perf_counter() >= self.deadline:
                self.out_of_time = True
                return mu, r, it, f"time budget of {self.time_budget:g} s used up"
            it += 1
            step = np.clip(mu + np.linalg.solve(A + lam * self.eye, g), -bound, bound) - mu
            r_new, jac_new = self.residual(mu + step)
            c_new = float((r_new ** 2).sum())
            predicted = float(step @ (lam * step + g))  # = cost − ‖r − Jδ‖² (> 0)
            rho = min((cost - c_new) / max(predicted, 1e-300), 1.0)  # > 1 only lowers λ by the cap
            if c_new < cost:
                mu, r, cost = mu + step, r_new, c_new
                J = jac_new.reshape(-1, k)
                A, g = J.T @ J, J.T @ r.reshape(-1)
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
            else:
                lam *= nu
                nu *= 2.0
                if lam > 1e8 * max(float(np.diag(A).max()), 1e-12):
                    self.record(mu, r)
                    return mu, r, it, "stationary (no descent step)"
            self.record(mu, r)
        return mu, r, it, "budget"

    def solve_from(self, mu0, budget, smoothing_schedule: Sequence[float]):
        """1) LM on the exact decoder from mu0 (enough when mu0 lies in the basin).
        2) Otherwise continuation in the decoder's smoothness: the exact decoder is piecewise
           linear (ReLU), so the squared error has kinks where LM stalls far from a solution.
           LM runs on smooth surrogates (softplus of increasing sharpness β), then polishes on
           the exact decoder — the trajectory that is executed. The better fit is kept."""
        mu, r, it, reason = self.levenberg_marquardt(mu0, max(1, budget // 4))
        if (np.abs(r).max() > self.tol and budget - it > len(smoothing_schedule) and smoothing_schedule
                and not self.out_of_time):
            mu2 = mu0
            for beta in smoothing_schedule:
                self.smoothing = beta
                mu2, _, used, _ = self.levenberg_marquardt(mu2, max(1, (budget // 4) // len(smoothing_schedule)))
                it += used
            self.smoothing = None
            mu2, r2, used, reason2 = self.levenberg_marquardt(mu2, budget - it)
            it += used
            if np.abs(r2).max() < np.abs(r).max():
                mu, r, reason = mu2, r2, reason2
        return mu, r, it, reason

    def run(self, latent: LatentGaussian, max_iterations: int, max_restarts: int,
            smoothing_schedule: Sequence[float], seed: int):
        """:meth:`solve_from` the clipped posterior mean, then restarts (exact LM only) from small
        seeded perturbations of the best point while the shared iteration budget lasts; the best
        fit over all runs is kept. Returns (μ̃, residuals (n, d), iterations, reason)."""
        rng = np.random.default_rng(seed)
        mu, r, it, reason = self.solve_from(
            np.clip(latent.mean, -self.latent_bound, self.latent_bound).astype(np.float64), max_iterations,
            smoothing_schedule)
        restarts = 0
        while (np.abs(r).max() > self.tol and it < max_iterations and restarts < max_restarts
               and not self.out_of_time):
            restarts += 1
            start = mu + rng.standard_normal(self.prim.latent_dim) * 0.05 * np.sqrt(latent.var)
            mu2, r2, it2, reason2 = self.levenberg_marquardt(start, max_iterations - it)
            it += it2
            if np.abs(r2).max() < np.abs(r).max():
                mu, r, reason = mu2, r2, reason2
        if self.best_err < float(np.abs(r).max()):  # an intermediate iterate (e.g. of the continuation) fit better
            mu = self.best_mu
            r = self.residual(mu)[0]
        max_err = float(np.abs(r).max())
        if self.history and max_err < self.history[-1]:  # a restart that started (and stopped) on a better point
            self.history[-1] = max_err
        if max_err <= self.tol:
            reason = "converged"
        elif restarts:
            reason += f" after {restarts} restarts"
        return mu, r, it, reason


def _fit_std(prim: "DeepProMP", mu: np.ndarray, x: np.ndarray, y: np.ndarray, mf: np.ndarray, eps: np.ndarray,
             s_target: np.ndarray, sigma_iterations: int, deadline: float = math.inf,
             eval_seconds: float = 0.0) -> tuple[np.ndarray, bool]:
    """Stage 2 of :func:`refine_exact`: σ̃ minimizing the paper's objective
    Σ_i ||y_i − 1/K Σ_k μ_y(μ̃ + ε_k σ̃, x_i)||² + ||σ* − σ̃||² at the refined mean, with the K
    fixed samples ``eps`` (K, k), by damped Gauss–Newton (``sigma_iterations`` steps, σ̃ ≥ 1e-6).

    An evaluation (K decoder Jacobians, estimated as K x ``eval_seconds``, the longest one of
    stage 1) starts only if it ends before ``deadline``. Returns (σ̃, True when that cut it short)."""
    s = s_target.copy()

    def in_time():
        return time.perf_counter() + eps.shape[0] * eval_seconds < deadline

    def s_residual(s):
        # residual [y − ȳ(σ̃); σ* − σ̃] and the Jacobian of the model part [∂ȳ/∂σ̃; I]
        ys, js = prim.decoder_jacobian(mu[None] + eps * s[None], x)  # (K, n, d), (K, n, d, k)
        r_y = ((y - ys.mean(0)) * mf).reshape(-1)
        j_y = (js * eps[:, None, None, :]).mean(0) * mf[:, :, None]
        return (np.concatenate([r_y, s_target - s]),
                np.concatenate([j_y.reshape(-1, s.size), np.eye(s.size)]))

    if sigma_iterations > 0:
        if not in_time():
            return s, True
        rs, jm = s_residual(s)
        c = float(rs @ rs)
        lam_s = 1e-3
        for _ in range(sigma_iterations):
            if not in_time():
                return s, True
            step = np.linalg.solve(jm.T @ jm + lam_s * np.eye(s.size), jm.T @ rs)
            s_new = np.maximum(s + step, 1e-6)
            rs_new, jm_new = s_residual(s_new)
            c_new = float(rs_new @ rs_new)
            if c_new < c:
                s, rs, jm, c, lam_s = s_new, rs_new, jm_new, c_new, lam_s / 5
            else:
                lam_s *= 4
                if lam_s > 1e8:
                    break
    return s, False


def refine_exact(prim: "DeepProMP", latent: LatentGaussian, via_x, via_y, joint_mask=None,
                 max_iterations: int = 200, tol: float = 1e-6, n_samples: int = 16, seed: int = 0,
                 sigma_target: np.ndarray | None = None, sigma_iterations: int = 5, max_restarts: int = 5,
                 smoothing_schedule: Sequence[float] = (3.0, 10.0, 30.0, 100.0),
                 latent_bound: float = 5.0, time_budget: float | None = None) -> RefinementResult:
    """Refinement that meets the via-points exactly (paper Eq. 5 and appendix).

    Stage 1 moves μ̃ — starting at the given (posterior) mean, or for an aggregation with several modes
    (below) at its most probable mode — so that the trajectory the robot
    executes, μ_y(μ̃, x), passes through the via-points: damped Gauss–Newton
    (Levenberg–Marquardt) in float64 with the decoder's exact Jacobian. Stage 2 keeps μ̃ and fits
    σ̃ to the paper's objective Σ_i ||y_i − 1/K Σ_k μ_y(μ̃ + ε_k σ̃, x_i)||² + ||σ* − σ̃||² with
    K FIXED samples ε_k (common random numbers: fresh samples at every step leave Monte-Carlo
    noise of ~1e-2 that no optimizer removes).

    A split latent (``latent_linear`` > 0, from :meth:`DeepProMP.condition`) is refined in the linear
    block first (:func:`~deepprompt_ros.primitive.linear_conditioning.refine_split`): nothing to do
    (0 iterations, the latent returned as it is) when its mean meets the via-points already, else
    z_lin is conditioned exactly again on these via-points with the noise divided by 10 per
    iteration, keeping the z_nl candidates; the result stays a split latent, its mean moved onto the
    via-points and its covariance the one of the given latent (the Eq. 5 optimum for a linear
    block: σ̃ = σ*), so its samples pass the via-points within the noise they were asked with. Only
    if that cannot meet them (more constraints than the linear block can satisfy) do the stages below
    continue from its best fit, with a plain latent.

    An aggregation with several modes of the decoder and no linear block (``mode_weights``: the prior,
    or contexts through their encoders) whose executed mean meets the via-points already is returned as
    it is; else the stages fit the most probable mode, starting from the encodings moved to it, and the
    reason names the mode.

    Unreachable via-points: stage 1 stops at a stationary point when no damped step (damping up
    to 1e6) decreases the squared error or the gradient Jᵀr vanishes; it then restarts from
    small seeded perturbations (``max_restarts``) while iterations remain (all runs share the
    ``max_iterations`` budget). If the best fit still misses by more than ``tol``, the result
    says ``reachable=False`` and carries that best fit and its residuals — never a silent miss.

    Parameters
    ----------
    prim : DeepProMP
    latent : LatentGaussian, the initialization (normally the posterior from :meth:`DeepProMP.condition`)
    via_x : array, shape (n,)
    via_y : array, shape (n, d)
    joint_mask : array of bool, shape (n, d) or (d,), optional; joints to meet (default all)
    n_samples : int, K; seed : int, of the restarts and of the K samples
    sigma_target : array, shape (k,), σ*; default the initial std
    smoothing_schedule : sequence of float, the β of the continuation's softplus surrogates
    latent_bound : float
        μ̃ stays in the box |μ̃_i| ≤ latent_bound (units of the prior's std). The ReLU decoder
        extrapolates linearly, so almost any target is "reachable" with a huge z — far outside
        what was demonstrated. Via-points that need more are reported unreachable.
    time_budget : float, optional
        Wall time (s) after which no iteration of either stage starts (None: no limit); stage 2
        starts an evaluation only if it is expected to end within the budget. The best fit found
        by then is returned; unmet, it says ``reachable=False`` and ``out_of_time=True``. The time
        used exceeds the budget by about one iteration and the decoding of the result.
    """
    x, y, mask = refinement_inputs(prim, via_x, via_y, joint_mask, max_iterations, tol)
    if time_budget is not None and not (time_budget > 0 and math.isfinite(time_budget)):
        raise ValueError(f"time_budget must be a finite number of seconds > 0 (or None: no limit); got {time_budget}")
    deadline = math.inf if time_budget is None else time.perf_counter() + time_budget
    in_mode = ""
    if latent.linear is None and latent.mode_weights is not None:
        # an aggregation with several modes of the decoder and no via-point in it: its executed mean weighs the
        # modes, the decoder that μ̃ is fitted with has one
        r = (y - prim.decode_mean(latent, x)) * mask
        if float(np.abs(r).max()) <= tol:  # (the samples are drawn only for a result returned)
            return _result_as_is(prim, latent, x, y, mask, n_samples, seed, tol=tol, iterations=0,
                                 reason="met by the executed mean already", errors=r)
        mode = int(np.argmax(latent.mode_weights))
        in_mode = f" (in mode {mode}, the aggregation's most probable: {float(latent.mode_weights[mode]):.3g})"
        latent = _one_mode(prim, latent, mode)
    split = None
    if latent.linear is not None and latent.context_mean is not None:
        split = refine_split(prim._np, latent, x, y, mask, tol, max_iterations, deadline=deadline)
        if split.max_error <= tol or split.iterations >= max_iterations or time.perf_counter() >= deadline:
            # unmet with iterations left: the time budget ended it (in refine_split or before stage 1)
            res = _split_result(prim, split, x, y, mask, n_samples, seed, split.iterations < max_iterations)
            return dataclasses.replace(res, reason=f"{res.reason} (time budget of {time_budget:g} s)"
                                       if res.out_of_time else res.reason)
        latent = split.latent
    fit = _MeanFit(prim, x, y, mask, tol, latent_bound, deadline, time_budget)
    budget = max_iterations - (split.iterations if split else 0)
    mu, r, it, reason = fit.run(latent, budget, max_restarts, smoothing_schedule, seed)
    max_err = float(np.abs(r).max())
    if split is not None:
        it += split.iterations
        if split.max_error <= max_err:  # the box |μ̃| <= latent_bound kept the fit from the split latent's mean
            return dataclasses.replace(_split_result(prim, split, x, y, mask, n_samples, seed, fit.out_of_time),
                                       iterations=it, reason=f"{split.reason}; then {reason} without a better fit")
        fit.history[:0] = split.history[:-1]

    # Stage 2: σ̃ with fixed ε (paper objective in σ̃ at the refined mean).
    eps = np.random.default_rng(seed).standard_normal((n_samples, prim.latent_dim))
    s_target = np.sqrt(latent.var) if sigma_target is None else np.asarray(sigma_target, dtype=np.float64)
    s, cut = _fit_std(prim, mu, x, y, fit.mf, eps, s_target, sigma_iterations, deadline, fit.eval_seconds)
    out_of_time = fit.out_of_time and max_err > tol
    if out_of_time and "time budget" not in reason:  # the best fit came from a run that ended otherwise
        reason += f"; then the time budget of {time_budget:g} s was used up"
    if cut and not fit.out_of_time:
        reason += f"; σ̃ fit cut short by the time budget of {time_budget:g} s"
    y_bar = prim.decode(mu[None] + eps * s[None], x).mean(0)
    reason += in_mode
    return RefinementResult(
        latent=LatentGaussian(mu, s ** 2), max_error=max_err, errors=r, iterations=it,
        sample_mean_error=float(np.abs((y - y_bar) * fit.mf).max()), reachable=max_err <= tol, reason=reason,
        error_history=np.minimum.accumulate(np.array(fit.history)), out_of_time=out_of_time)
