"""Probabilistic Movement Primitives (ProMP), the linear-Gaussian model the paper builds on and
compares against (Paraschos et al., "Probabilistic Movement Primitives", NeurIPS 2013, and
"Using probabilistic movement primitives in robotics", Autonomous Robots 2018).

Model, for d joints and n basis functions per joint, phase x in [0, 1]::

    y(x) = Ψ(x) w + ε,   Ψ(x) = I_d ⊗ φ(x)^T  (d × dn),   ε ~ N(0, diag(σ²_y))
    w ~ N(μ_w, Σ_w)

w is ordered joint-major: w[j·n:(j+1)·n] are joint j's weights. φ(x) are normalized Gaussian
RBFs (discrete primitives) or normalized von Mises functions (rhythmic primitives, periodic in
x with period 1, i.e. a function of [sin 2πx, cos 2πx] like the deep model's rhythmic phase).

Optional low-dimensional context c: the demonstrations' (w, c) are modelled jointly Gaussian,
so :meth:`ProMP.condition_context` is Gaussian conditioning of that joint distribution (a
linear regression of w on c). Internally the model keeps ONE Gaussian over the stacked vector
[w; c]; via-point conditioning updates the context part too.

All operations (``condition``, ``condition_context``, ``blend``) return new objects.

One concept in one module (past ~400 lines on purpose): the class is the ProMP, and its basis,
fit, trajectory distribution, conditioning, blending, file format and input checks all read and
write one internal representation — the Gaussian over [w; c] with its covariance kept as a matrix
minus a pending low-rank factor (``_cov_mat - _cov_qᵀ _cov_q``) and cached per-joint blocks.
Splitting them would spread that invariant over several files.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Callable, NamedTuple, Sequence

import numpy as np

from deepprompt_ros.common.joints import joint_list_text

__all__ = ["ProMP", "TrajectoryDistribution"]

_FORMAT = "deepprompt_ros.promp"
_FORMAT_VERSION = 1


class TrajectoryDistribution(NamedTuple):
    """Per-time-step Gaussian over joint positions (e.g. the result of :meth:`ProMP.blend`).

    Attributes
    ----------
    x : array, shape (T,)
        Phases.
    mean : array, shape (T, d)
    cov : array, shape (T, d, d)
        Covariance of y at each phase (joints coupled, time steps independent).
    """

    x: np.ndarray
    mean: np.ndarray
    cov: np.ndarray

    @property
    def std(self) -> np.ndarray:
        """Per-joint standard deviation, shape (T, d)."""
        return np.sqrt(np.maximum(np.diagonal(self.cov, axis1=1, axis2=2), 0.0))


class ProMP:
    """Probabilistic movement primitive with RBF (or periodic von Mises) basis.

    Parameters
    ----------
    n_joints : int
        d.
    n_basis : int
        n, basis functions per joint.
    rhythmic : bool
        Periodic von Mises basis (y(0) = y(1), all derivatives too) instead of RBFs.
    width : float
        Basis width relative to the centre spacing Δ: RBF standard deviation h = width·Δ with
        centres linspace(0, 1, n) (Δ = 1/(n-1)); von Mises concentration κ = 1/(2π·width·Δ)²
        with centres j/n (Δ = 1/n), which matches the RBF's curvature at its centre.
    ridge : float
        Ridge regularizer of the per-demonstration weight regression, relative to the mean
        diagonal of ΦᵀΦ (scale-free with respect to the number of samples).
    cov_reg : float or None
        λ added to the diagonal of the weight covariance (see :meth:`fit`); None chooses it.
    cov_reg_scale : float or None
        Instead of ``cov_reg``: λ relative to the demonstrations' weight variance,
        λ = cov_reg_scale · max(mean(diag(cov_i w_i)), (0.01 · y_range)²) (see :meth:`fit`); the scale
        :func:`deepprompt_ros.baselines.promp_selection.select_promp` chooses by cross-validation.
    joint_names : sequence of str, optional
        Used in error messages (default joint_1..joint_d).
    """

    def __init__(self, n_joints: int, n_basis: int = 20, *, rhythmic: bool = False,
                 width: float = 1.0, ridge: float = 1e-8, cov_reg: float | None = None,
                 cov_reg_scale: float | None = None, joint_names: Sequence[str] | None = None):
        if int(n_joints) != n_joints or n_joints < 1:
            raise ValueError(f"n_joints must be an integer >= 1; got {n_joints}")
        if int(n_basis) != n_basis or n_basis < 2:
            raise ValueError(f"n_basis must be an integer >= 2; got {n_basis}")
        if not (math.isfinite(width) and width > 0):
            raise ValueError(f"width must be > 0 (relative to the centre spacing); got {width}")
        if not (math.isfinite(ridge) and ridge >= 0):
            raise ValueError(f"ridge must be >= 0; got {ridge}")
        if cov_reg is not None and not (math.isfinite(cov_reg) and cov_reg >= 0):
            raise ValueError(f"cov_reg must be >= 0 or None (automatic); got {cov_reg}")
        if cov_reg_scale is not None and not (math.isfinite(cov_reg_scale) and cov_reg_scale >= 0):
            raise ValueError(f"cov_reg_scale must be >= 0 or None; got {cov_reg_scale}")
        if cov_reg is not None and cov_reg_scale is not None:
            raise ValueError(f"give cov_reg (absolute λ, {cov_reg}) or cov_reg_scale (λ relative to the weight "
                             f"variance, {cov_reg_scale}), not both")
        self.n_joints = int(n_joints)
        self.n_basis = int(n_basis)
        self.rhythmic = bool(rhythmic)
        self.width = float(width)
        self.ridge = float(ridge)
        self.cov_reg = cov_reg if cov_reg is None else float(cov_reg)
        self.cov_reg_scale = cov_reg_scale if cov_reg_scale is None else float(cov_reg_scale)
        names = tuple(joint_names) if joint_names is not None else tuple(
            f"joint_{i + 1}" for i in range(self.n_joints))
        if len(names) != self.n_joints:
            raise ValueError(f"joint_names has {len(names)} names; expected {self.n_joints}")
        self.joint_names = names
        n = self.n_basis
        if self.rhythmic:
            self._centers = np.arange(n) / n
            self._kappa = 1.0 / (2.0 * math.pi * self.width / n) ** 2
        else:
            self._centers = np.linspace(0.0, 1.0, n)
            self._h = self.width / (n - 1)
        # fitted state: Gaussian over [w; c] (D = d·n weights, C context dims)
        self._mean: np.ndarray | None = None
        # covariance of [w; c] = _cov_mat - _cov_q.T @ _cov_q; the low-rank factor of a
        # conditioning step is applied lazily (the std of the mean needs only its diagonal
        # blocks, the full matrix costs a (D x R) @ (R x D) product)
        self._cov_mat: np.ndarray | None = None
        self._cov_q: np.ndarray | None = None
        self._obs_var: np.ndarray | None = None
        self.context_dim = 0
        self.n_demos = 0
        self.cov_reg_used = float("nan")
        self._blocks: np.ndarray | None = None  # cached per-joint diagonal blocks of Σ_w

    # ---------------------------------------------------------------------------------
    # basis
    # ---------------------------------------------------------------------------------
    @property
    def n_weights(self) -> int:
        """D = d·n."""
        return self.n_joints * self.n_basis

    def basis(self, x, deriv: int = 0) -> np.ndarray:
        """Normalized basis φ(x) or its derivative d^k φ / dx^k.

        Parameters
        ----------
        x : array, shape (T,)
            Phases in [0, 1].
        deriv : {0, 1, 2}

        Returns
        -------
        array, shape (T, n)
        """
        x = self._check_phase(x, "x")
        if deriv not in (0, 1, 2):
            raise ValueError(f"deriv must be 0, 1 or 2; got {deriv}")
        return self._basis(x, deriv).copy()

    def _basis(self, x: np.ndarray, deriv: int = 0) -> np.ndarray:
        """φ(x) (or a derivative); the last few phase grids are cached (read-only arrays), as
        the same grid is typically evaluated again and again (mean, std, every condition)."""
        key = (deriv, x.tobytes())
        cache = self.__dict__.setdefault("_basis_cache", {})
        hit = cache.get(key)
        if hit is not None:
            return hit
        phi = self._basis_eval(x, deriv)
        phi.setflags(write=False)
        if len(cache) >= 8:
            cache.pop(next(iter(cache)))
        cache[key] = phi
        return phi

    def _basis_eval(self, x: np.ndarray, deriv: int) -> np.ndarray:
        u = x[:, None] - self._centers[None, :]
        if self.rhythmic:
            w = 2.0 * math.pi
            e = self._kappa * (np.cos(w * u) - 1.0)
        else:
            e = -0.5 * (u / self._h) ** 2
        b = np.exp(e - e.max(axis=1, keepdims=True))  # scale cancels in the normalization
        s = b.sum(axis=1, keepdims=True)
        phi = b / s
        if deriv == 0:
            return phi
        if self.rhythmic:
            g1 = -w * self._kappa * np.sin(w * u)            # b'/b
            g2 = g1 * g1 - w * w * self._kappa * np.cos(w * u)  # b''/b
        else:
            g1 = -u / self._h ** 2
            g2 = g1 * g1 - 1.0 / self._h ** 2
        r1 = (phi * g1).sum(axis=1, keepdims=True)  # S'/S
        if deriv == 1:
            return phi * (g1 - r1)
        if deriv == 2:
            r2 = (phi * g2).sum(axis=1, keepdims=True)  # S''/S
            # (b/S)'' = b''/S - 2 b'S'/S² - b S''/S² + 2 b S'²/S³
            return phi * (g2 - 2.0 * g1 * r1 - r2 + 2.0 * r1 * r1)
        raise ValueError(f"deriv must be 0, 1 or 2; got {deriv}")

    # ---------------------------------------------------------------------------------
    # fitting
    # ---------------------------------------------------------------------------------
    def fit(self, Y, x, contexts=None) -> "ProMP":
        """Fit the weight distribution (and the joint distribution with contexts) to demos.

        Per demonstration i, ridge regression W_i = (ΦᵀΦ + r·I)^-1 ΦᵀY_i (the usual ProMP
        weight estimate; r = ``ridge`` · mean diag(ΦᵀΦ)); then μ_w = mean_i w_i and
        Σ_w = cov_i w_i + λI. σ²_y per joint is the mean squared residual of the regressions.

        Why λ, and its value: with N demonstrations the sample covariance has rank <= N - 1
        (e.g. 3 demos, 7·20 = 140 weights: rank 2). Conditioning such a Σ_w can only move the
        mean inside the span of the demos' deviations, so a via-point outside it is met by
        amplifying those few directions (large oscillations) or not at all. λI gives every
        weight a small independent prior variance, so conditioning adds a local correction of
        the basis functions near the via-point instead. ``cov_reg=None`` chooses
        λ = 0.05 · mean(diag(cov_i w_i)) + (0.01 · y_range)², y_range the largest peak-to-peak
        range of a joint in Y: 5 % of the average weight variance plus a floor (a standard
        deviation of 1 % of the motion's range) for a single or identical demonstrations.
        Measured on 7-joint sine families (3 and 30 demos, 5 via-points off the demos' span,
        noise 1e-6): 1 % left 2.6e-3..2e-2 rad via-point errors, 5 % 5.6e-4..5e-3 rad, while
        the prior std grew by ~1 %; no overshoot of the data range either way. Smaller noise
        meets via-points more tightly. ``cov_reg_scale`` s instead: λ = s · max(mean(diag(cov_i w_i)),
        (0.01 · y_range)²), the same two terms as a scale and a floor (the floor only for
        identical demonstrations). The value used is ``cov_reg_used``.

        Contexts: (w_i, c_i) are modelled jointly Gaussian; the context block gets a ridge of
        1e-6 · mean(diag(cov_i c_i)) + 1e-12 so it can be conditioned on with few demos.

        Parameters
        ----------
        Y : array, shape (N, T, d), or sequence of N arrays of shape (T_i, d)
            Demonstrated joint positions.
        x : array, shape (T,) or (N, T), or sequence of N arrays of shape (T_i,)
            Phases of the samples, in [0, 1].
        contexts : array, shape (N, C), optional
            One low-dimensional context vector per demonstration.

        Returns
        -------
        self
        """
        demos, phases = self._check_demos(Y, x)
        N, d, n = len(demos), self.n_joints, self.n_basis
        W = np.empty((N, d * n))
        sq_res = np.zeros(d)
        count = 0
        y_min = np.full(d, np.inf)
        y_max = np.full(d, -np.inf)
        for i, (Yi, xi) in enumerate(zip(demos, phases)):
            Phi = self._basis(xi)                                  # (T_i, n)
            A = Phi.T @ Phi
            A[np.diag_indices(n)] += self.ridge * np.trace(A) / n
            Wi = np.linalg.solve(A, Phi.T @ Yi)                    # (n, d)
            W[i] = Wi.T.reshape(-1)                                # joint-major
            sq_res += ((Yi - Phi @ Wi) ** 2).sum(axis=0)
            count += Yi.shape[0]
            y_min = np.minimum(y_min, Yi.min(axis=0))
            y_max = np.maximum(y_max, Yi.max(axis=0))
        obs_var = np.maximum(sq_res / count, 1e-12)

        C = 0
        if contexts is not None:
            c = np.asarray(contexts, dtype=float)
            if c.ndim == 1:
                c = c[:, None]
            if c.ndim != 2 or c.shape[0] != N or c.shape[1] == 0:
                raise ValueError(f"contexts must have shape ({N}, C >= 1), one vector per "
                                 f"demonstration; got {c.shape}")
            if not np.all(np.isfinite(c)):
                raise ValueError("contexts contain NaN or inf; expected finite numbers")
            C = c.shape[1]
            Z = np.hstack([W, c])
        else:
            Z = W
        mean = Z.mean(axis=0)
        cov = np.cov(Z, rowvar=False, ddof=1) if N > 1 else np.zeros((Z.shape[1], Z.shape[1]))
        cov = np.atleast_2d(cov)
        D = d * n
        y_range = float(np.max(y_max - y_min))
        if self.cov_reg is not None:
            lam = self.cov_reg
        elif self.cov_reg_scale is not None:
            lam = self.cov_reg_scale * max(float(np.mean(np.diag(cov)[:D])), (0.01 * max(y_range, 1e-9)) ** 2)
        else:
            lam = 0.05 * float(np.mean(np.diag(cov)[:D])) + (0.01 * max(y_range, 1e-9)) ** 2
        cov[np.arange(D), np.arange(D)] += lam
        if C:
            lam_c = 1e-6 * float(np.mean(np.diag(cov)[D:])) + 1e-12
            cov[np.arange(D, D + C), np.arange(D, D + C)] += lam_c
        self._mean, self._obs_var = mean, obs_var
        self._cov_mat, self._cov_q = 0.5 * (cov + cov.T), None
        self.context_dim = C
        self.n_demos = N
        self.cov_reg_used = lam
        self._blocks = None
        return self

    # ---------------------------------------------------------------------------------
    # accessors
    # ---------------------------------------------------------------------------------
    @property
    def fitted(self) -> bool:
        return self._mean is not None

    @property
    def mean_w(self) -> np.ndarray:
        """μ_w, shape (d·n,) (joint-major)."""
        self._require_fitted()
        return self._mean[: self.n_weights].copy()

    @property
    def cov_w(self) -> np.ndarray:
        """Σ_w, shape (d·n, d·n)."""
        self._require_fitted()
        D = self.n_weights
        return self._cov[:D, :D].copy()

    @property
    def obs_var(self) -> np.ndarray:
        """σ²_y per joint, shape (d,)."""
        self._require_fitted()
        return self._obs_var.copy()

    @property
    def _cov(self) -> np.ndarray:
        """Full covariance of [w; c] (materializes a pending low-rank update)."""
        if self._cov_q is not None:
            Q = self._cov_q
            cov = self._cov_mat - Q.T @ Q
            self._cov_mat, self._cov_q = 0.5 * (cov + cov.T), None
        return self._cov_mat

    def _require_fitted(self):
        if self._mean is None:
            raise ValueError("this ProMP is not fitted: call fit(Y, x) with demonstrations first")

    def _new(self, mean: np.ndarray, cov: np.ndarray, context_dim: int,
             cov_q: np.ndarray | None = None) -> "ProMP":
        """New primitive with the same basis; covariance cov - cov_qᵀ cov_q."""
        out = ProMP.__new__(ProMP)
        out.__dict__.update(self.__dict__)
        out._mean, out._cov_mat, out._cov_q = mean, cov, cov_q
        out.context_dim = context_dim
        out._blocks = None
        return out

    # ---------------------------------------------------------------------------------
    # trajectories
    # ---------------------------------------------------------------------------------
    def mean_trajectory(self, x, deriv: int = 0) -> np.ndarray:
        """Mean E[y(x)] = Ψ(x) μ_w, or its derivative with respect to the phase.

        Parameters
        ----------
        x : array, shape (T,)
        deriv : {0, 1, 2}
            d^k/dx^k of the mean (for velocities: multiply by dx/dt).

        Returns
        -------
        array, shape (T, d)
        """
        self._require_fitted()
        x = self._check_phase(x, "x")
        M = self._mean[: self.n_weights].reshape(self.n_joints, self.n_basis)
        return self._basis(x, deriv) @ M.T

    def std_trajectory(self, x, include_obs_noise: bool = False) -> np.ndarray:
        """Per-joint standard deviation of y(x): sqrt(φ(x)ᵀ Σ_jj φ(x)) (+ σ²_y,j if asked).

        Parameters
        ----------
        x : array, shape (T,)
        include_obs_noise : bool
            Add the observation noise σ²_y (the spread of demonstrations around their basis
            fit) to the uncertainty of the mean function.

        Returns
        -------
        array, shape (T, d)
        """
        self._require_fitted()
        x = self._check_phase(x, "x")
        Phi = self._basis(x)
        var = np.einsum("jtn,tn->tj", Phi[None] @ self._diag_blocks(), Phi)
        if include_obs_noise:
            var = var + self._obs_var
        return np.sqrt(np.maximum(var, 0.0))

    def _diag_blocks(self) -> np.ndarray:
        """Σ_jj, shape (d, n, n)."""
        if self._blocks is None:
            d, n = self.n_joints, self.n_basis
            S = self._cov_mat[: d * n, : d * n].reshape(d, n, d, n)
            blocks = S[np.arange(d), :, np.arange(d), :]
            if self._cov_q is not None:
                Qj = self._cov_q[:, : d * n].reshape(-1, d, n).transpose(1, 0, 2)  # (d, R, n)
                blocks = blocks - np.swapaxes(Qj, 1, 2) @ Qj
            self._blocks = np.ascontiguousarray(blocks)
        return self._blocks

    def cov_trajectory(self, x, include_obs_noise: bool = True) -> np.ndarray:
        """Joint covariance of y at each phase, Ψ(x) Σ_w Ψ(x)ᵀ (+ diag σ²_y).

        Returns
        -------
        array, shape (T, d, d)
        """
        self._require_fitted()
        x = self._check_phase(x, "x")
        return self._cov_traj(self._basis(x), include_obs_noise)

    def _cov_traj(self, Phi: np.ndarray, include_obs_noise: bool) -> np.ndarray:
        d, n = self.n_joints, self.n_basis
        S = self._cov[: d * n, : d * n].reshape(d, n, d, n)
        cov = np.einsum("tn,jnkm,tm->tjk", Phi, S, Phi, optimize=True)
        if include_obs_noise:
            cov[:, np.arange(d), np.arange(d)] += self._obs_var
        return cov

    def distribution(self, x, include_obs_noise: bool = True) -> TrajectoryDistribution:
        """Mean and per-time covariance of y(x) as a :class:`TrajectoryDistribution`."""
        self._require_fitted()
        x = self._check_phase(x, "x")
        Phi = self._basis(x)
        M = self._mean[: self.n_weights].reshape(self.n_joints, self.n_basis)
        return TrajectoryDistribution(x, Phi @ M.T, self._cov_traj(Phi, include_obs_noise))

    def sample(self, x, n: int, rng: np.random.Generator | int | None = None, *,
               include_obs_noise: bool = False) -> np.ndarray:
        """Sample trajectories y = Ψ(x) w, w ~ N(μ_w, Σ_w) (plus ε ~ N(0, σ²_y) if asked).

        Parameters
        ----------
        x : array, shape (T,)
        n : int
            Number of samples.
        rng : numpy Generator or seed

        Returns
        -------
        array, shape (n, T, d)
        """
        self._require_fitted()
        x = self._check_phase(x, "x")
        if int(n) != n or n < 1:
            raise ValueError(f"number of samples n must be an integer >= 1; got {n}")
        rng = np.random.default_rng(rng)
        D, d, nb = self.n_weights, self.n_joints, self.n_basis
        L = _psd_sqrt(self._cov[:D, :D])
        w = self._mean[:D] + rng.standard_normal((int(n), D)) @ L.T     # (n, D)
        Phi = self._basis(x)
        y = np.einsum("tk,sjk->stj", Phi, w.reshape(int(n), d, nb))
        if include_obs_noise:
            y = y + rng.standard_normal(y.shape) * np.sqrt(self._obs_var)
        return y

    # ---------------------------------------------------------------------------------
    # operations
    # ---------------------------------------------------------------------------------
    def condition(self, x_via, y_via, noise_var=1e-6, joint_mask=None) -> "ProMP":
        """Condition on via-points (closed-form Gaussian conditioning, Paraschos et al. 2013,
        Sec. 2.2).

        With H stacking the rows of Ψ(x_i) of the observed joints and R = diag(noise_var)::

            K  = Σ Hᵀ (R + H Σ Hᵀ)^-1
            μ' = μ + K (y - H μ)
            Σ' = Σ - K H Σ

        computed from the Cholesky factor L L^T = R + H Σ Hᵀ (no inverse):
        [q, Q] = L^-1 [y - Hμ, H Σ], μ' = μ + Qᵀ q, Σ' = Σ - Qᵀ Q; the update of Σ is kept as
        the factor Q until the full matrix is needed (std needs only its diagonal blocks).
        Σ is the covariance of the stacked [w; c], so a context distribution is updated
        consistently.

        Parameters
        ----------
        x_via : array, shape (V,)
            Phases of the via-points, in [0, 1].
        y_via : array, shape (V, d)
            Desired joint positions; entries of unobserved joints (joint_mask False) are
            ignored and may be NaN.
        noise_var : float or array broadcastable to (V, d)
            Variance of each via-point value (>= 0): how strictly it must be met.
        joint_mask : array of bool, shape (d,) or (V, d), optional
            Which joints each via-point constrains (default: all).

        Returns
        -------
        ProMP
            A new, conditioned primitive.
        """
        self._require_fitted()
        x_via, y_via, mask = self._check_via(x_via, y_via, joint_mask)
        V, d, n = y_via.shape[0], self.n_joints, self.n_basis
        nv = np.broadcast_to(np.asarray(noise_var, dtype=float), (V, d)) if np.ndim(noise_var) \
            else np.full((V, d), float(noise_var))
        if nv.shape != (V, d):
            raise ValueError(f"noise_var must be a scalar or broadcastable to ({V}, {d}); got "
                             f"shape {np.shape(noise_var)}")
        if not np.all(np.isfinite(nv)) or np.any(nv < 0):
            raise ValueError("noise_var must be finite and >= 0")
        D = d * n
        Phi_v = self._basis(x_via)                                   # (V, n)
        if self._cov_q is not None and self._cov_q.shape[0] > self._cov_mat.shape[0] // 2:
            _ = self._cov  # long chains of conditioning: fold the factor into the matrix
        Sigma0, Q0 = self._cov_mat, self._cov_q   # Σ = Σ0 - Q0ᵀ Q0

        def times_Ht(S):  # S Hᵀ for all (via-point, joint) pairs: column (v, j) = S[:, block j] φ(x_v)
            rows = S.shape[0]
            Sw = S if S.shape[1] == D else np.ascontiguousarray(S[:, :D])
            return (Sw.reshape(rows * d, n) @ Phi_v.T).reshape(rows, d, V).transpose(0, 2, 1).reshape(rows, V * d)

        SH = times_Ht(Sigma0)
        if Q0 is not None:
            SH = SH - Q0.T @ times_Ht(Q0)
        sel = mask.reshape(-1)
        if not sel.all():
            SH = SH[:, sel]
        # H Σ Hᵀ: row (v, j) of H applied to Σ Hᵀ
        HSH = np.einsum("vn,jnr->vjr", Phi_v, SH[:D].reshape(d, n, -1)).reshape(V * d, -1)[sel]
        M = self._mean[:D].reshape(d, n)
        innovation = (y_via - Phi_v @ M.T).reshape(-1)[sel]           # y - Hμ
        Ssys = HSH + np.diag(nv.reshape(-1)[sel])
        Ssys = 0.5 * (Ssys + Ssys.T)
        jitter = 1e-12 * max(float(np.mean(np.diag(Ssys))), 1e-300)
        Ssys[np.diag_indices_from(Ssys)] += jitter
        # Ssys = L Lᵀ;  [q, Q] = L^-1 [y - Hμ, H Σ]:  μ' = μ + Qᵀ q,  Σ' = Σ - Qᵀ Q
        try:
            L = np.linalg.cholesky(Ssys)
        except np.linalg.LinAlgError:
            raise ValueError("the via-points cannot all be met exactly (e.g. the same phase twice "
                             "with different values, or noise_var = 0 on a primitive that is "
                             "already pinned there); use noise_var > 0") from None
        X = np.linalg.solve(L, np.column_stack([innovation, SH.T]))     # (R, 1 + Dz)
        mean = self._mean + X[:, 1:].T @ X[:, 0]
        Q = X[:, 1:] if Q0 is None else np.vstack([Q0, X[:, 1:]])
        return self._new(mean, Sigma0, self.context_dim, Q)

    def condition_context(self, c, noise_var: float = 0.0) -> "ProMP":
        """Condition the weights on a context vector: p(w | c) from the joint Gaussian of
        (w, c) fitted on the demonstrations::

            μ_w|c = μ_w + Σ_wc (Σ_cc + s I)^-1 (c - μ_c),   Σ_w|c = Σ_ww - Σ_wc (Σ_cc + s I)^-1 Σ_cw

        Parameters
        ----------
        c : array, shape (C,)
        noise_var : float
            s, variance of the observed context (>= 0).

        Returns
        -------
        ProMP
            A new primitive without context dimensions.
        """
        self._require_fitted()
        C = self.context_dim
        if C == 0:
            raise ValueError("this ProMP was fitted without contexts; fit(Y, x, contexts=...) "
                             "to condition on a context")
        c = np.asarray(c, dtype=float).reshape(-1)
        if c.shape != (C,):
            raise ValueError(f"context has {c.shape[0]} values; this ProMP's context has {C}")
        if not np.all(np.isfinite(c)):
            raise ValueError(f"context {c.tolist()} contains NaN or inf; expected finite numbers")
        if not (math.isfinite(noise_var) and noise_var >= 0):
            raise ValueError(f"noise_var must be >= 0; got {noise_var}")
        D = self._cov.shape[0] - C
        S_wc = self._cov[:D, D:]
        S_cc = self._cov[D:, D:] + noise_var * np.eye(C)
        G = np.linalg.solve(S_cc, np.column_stack([c - self._mean[D:], S_wc.T]))
        mean = self._mean[:D] + S_wc @ G[:, 0]
        cov = self._cov[:D, :D] - S_wc @ G[:, 1:]
        return self._new(mean, 0.5 * (cov + cov.T), 0)

    def blend(self, other: "ProMP", omega_fn: Callable[[np.ndarray], np.ndarray] | np.ndarray,
              x) -> TrajectoryDistribution:
        """ProMP blending (Paraschos et al. 2013, Sec. 2.2; the DeepProMP paper, Sec. III-C,
        applies the same exponent weighting to q(z)): per phase, the product of the two
        Gaussians of y raised to ω(x) and 1 - ω(x)::

            Σ_b^-1 = ω Σ_1^-1 + (1 - ω) Σ_2^-1,   μ_b = Σ_b (ω Σ_1^-1 μ_1 + (1 - ω) Σ_2^-1 μ_2)

        evaluated without inverses as Σ_b = Σ_1 M^-1 Σ_2 and
        μ_b = ω Σ_2 M^-1 μ_1 + (1 - ω) Σ_1 M^-1 μ_2 with M = ω Σ_2 + (1 - ω) Σ_1. The
        covariances include the observation noise σ²_y (so they are invertible).
        ω = 1 gives exactly the first primitive, ω = 0 the second.

        Parameters
        ----------
        other : ProMP
            Same number of joints.
        omega_fn : callable x -> ω, or array of shape (T,)
            Activation of ``self`` in [0, 1].
        x : array, shape (T,)

        Returns
        -------
        TrajectoryDistribution
        """
        self._require_fitted()
        if not isinstance(other, ProMP):
            raise ValueError("blend needs another ProMP")
        other._require_fitted()
        if other.n_joints != self.n_joints:
            raise ValueError(f"cannot blend a {self.n_joints}-joint ProMP with a "
                             f"{other.n_joints}-joint one")
        x = self._check_phase(x, "x")
        omega = np.asarray(omega_fn(x) if callable(omega_fn) else omega_fn, dtype=float)
        omega = np.broadcast_to(omega, x.shape) if omega.ndim == 0 else omega
        if omega.shape != x.shape:
            raise ValueError(f"ω must have one value per phase, shape {x.shape}; got {omega.shape}")
        if not np.all(np.isfinite(omega)) or np.any(omega < 0) or np.any(omega > 1):
            raise ValueError("ω(x) must lie in [0, 1]")
        d1, d2 = self.distribution(x), other.distribution(x)
        A, B = d1.cov, d2.cov
        w = omega[:, None, None]
        Mx = w * B + (1.0 - w) * A
        rhs = np.concatenate([d1.mean[:, :, None], d2.mean[:, :, None], B], axis=2)
        X = np.linalg.solve(Mx, rhs)                                   # (T, d, 2 + d)
        mean = (omega[:, None] * np.einsum("tij,tj->ti", B, X[:, :, 0])
                + (1.0 - omega)[:, None] * np.einsum("tij,tj->ti", A, X[:, :, 1]))
        cov = A @ X[:, :, 2:]
        cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
        return TrajectoryDistribution(x, mean, cov)

    # ---------------------------------------------------------------------------------
    # persistence (npz with a JSON header; loads without pickle)
    # ---------------------------------------------------------------------------------
    def save(self, path) -> None:
        """Write the primitive to ``path`` (.npz: arrays + a JSON metadata string)."""
        self._require_fitted()
        meta = {
            "format": _FORMAT, "format_version": _FORMAT_VERSION,
            "n_joints": self.n_joints, "n_basis": self.n_basis, "rhythmic": self.rhythmic,
            "width": self.width, "ridge": self.ridge, "cov_reg": self.cov_reg, "cov_reg_scale": self.cov_reg_scale,
            "cov_reg_used": self.cov_reg_used, "context_dim": self.context_dim,
            "n_demos": self.n_demos, "joint_names": list(self.joint_names),
        }
        path = Path(path)
        with open(path, "wb") as f:
            np.savez(f, mean=self._mean, cov=self._cov, obs_var=self._obs_var,
                     meta=np.array(json.dumps(meta)))

    @classmethod
    def load(cls, path) -> "ProMP":
        """Read a primitive written by :meth:`save` (no pickle); ``ValueError`` naming ``path`` when
        it is not one."""
        try:
            z = np.load(Path(path), allow_pickle=False)
        except EOFError as exc:  # an empty file
            raise ValueError(f"{path} is not a ProMP file: {exc}") from exc
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise ValueError(f"{path} is not a ProMP file: a single array, not an .npz archive")
        with z:
            for key in ("mean", "cov", "obs_var", "meta"):
                if key not in z.files:
                    raise ValueError(f"{path} is not a ProMP file: missing '{key}'")
            meta, mean, cov, obs_var = str(z["meta"]), z["mean"], z["cov"], z["obs_var"]
        return cls.from_arrays(mean, cov, obs_var, meta, str(path))

    @classmethod
    def from_arrays(cls, mean, cov, obs_var, meta: str, source: str) -> "ProMP":
        """The primitive whose arrays and JSON metadata string :meth:`save` writes: mean ((n_w + c,)),
        cov ((n_w + c, n_w + c)), obs_var ((d,)); ``ValueError`` naming ``source`` (where they were
        read) when the metadata is not valid, the format or version differs, the shapes do not match
        the metadata or an array holds NaN or inf."""
        try:
            meta = json.loads(meta)
        except ValueError as exc:
            raise ValueError(f"{source}: ProMP metadata is not valid JSON ({exc})") from exc
        if not isinstance(meta, dict):
            raise ValueError(f"{source}: ProMP metadata must be a JSON object; got {type(meta).__name__}")
        if meta.get("format") != _FORMAT or meta.get("format_version") != _FORMAT_VERSION:
            raise ValueError(f"{source}: format {meta.get('format')!r} version "
                             f"{meta.get('format_version')!r}; expected {_FORMAT!r} version "
                             f"{_FORMAT_VERSION}")
        try:
            out = cls(meta["n_joints"], meta["n_basis"], rhythmic=meta["rhythmic"],
                      width=meta["width"], ridge=meta["ridge"], cov_reg=meta["cov_reg"],
                      cov_reg_scale=meta.get("cov_reg_scale"),
                      joint_names=meta["joint_names"])
            context_dim, n_demos, cov_reg_used = int(meta["context_dim"]), meta["n_demos"], meta["cov_reg_used"]
        except KeyError as exc:
            raise ValueError(f"{source}: ProMP metadata lacks {exc}") from exc
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{source}: invalid ProMP metadata: {exc}") from exc
        mean, cov, obs_var = (np.asarray(a) for a in (mean, cov, obs_var))
        Dz = out.n_weights + context_dim
        if mean.shape != (Dz,) or cov.shape != (Dz, Dz) or obs_var.shape != (out.n_joints,):
            raise ValueError(f"{source}: array shapes {mean.shape}, {cov.shape}, {obs_var.shape} "
                             f"do not match the metadata (expected ({Dz},), ({Dz}, {Dz}), "
                             f"({out.n_joints},))")
        for name, a in (("mean", mean), ("cov", cov), ("obs_var", obs_var)):
            if a.dtype.kind != "f" or not np.all(np.isfinite(a)):
                raise ValueError(f"{source}: ProMP array '{name}' must hold finite floats; got dtype {a.dtype}"
                                 f"{'' if a.dtype.kind != 'f' else ' with NaN or inf'}")
        out._mean, out._cov_mat, out._cov_q, out._obs_var = mean, cov, None, obs_var
        out.context_dim = context_dim
        out.n_demos = n_demos
        out.cov_reg_used = cov_reg_used
        return out

    # ---------------------------------------------------------------------------------
    # validation
    # ---------------------------------------------------------------------------------
    def _check_phase(self, x, name: str) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        if x.ndim == 0:
            x = x.reshape(1)
        if x.ndim != 1:
            raise ValueError(f"phases {name} must be a 1-D array; got shape {x.shape}")
        if x.shape[0] == 0:
            raise ValueError(f"phases {name} are empty; expected at least one phase in [0, 1]")
        bad = ~np.isfinite(x) | (x < 0.0) | (x > 1.0)
        if bad.any():
            i = int(np.argmax(bad))
            raise ValueError(f"phase {name}[{i}] = {x[i]} is outside [0, 1]; phases are "
                             f"normalized time")
        return x

    def _check_via(self, x_via, y_via, joint_mask):
        d = self.n_joints
        x_via = self._check_phase(x_via, "x_via")
        V = x_via.shape[0]
        y = np.asarray(y_via, dtype=float)
        if y.ndim == 1 and V == 1:
            y = y[None, :]
        if y.ndim != 2 or y.shape[0] != V:
            raise ValueError(f"y_via must have shape ({V}, {d}): one row per via-point phase; "
                             f"got {y.shape}")
        if y.shape[1] != d:
            raise ValueError(f"via-points have {y.shape[1]} joint values; this ProMP has {d} "
                             f"joints: {joint_list_text(self.joint_names)}")
        if joint_mask is None:
            mask = np.ones((V, d), dtype=bool)
        else:
            m = np.asarray(joint_mask, dtype=bool)
            if m.shape == (d,):
                mask = np.broadcast_to(m, (V, d)).copy()
            elif m.shape == (V, d):
                mask = m.copy()
            else:
                raise ValueError(f"joint_mask must have shape ({d},) or ({V}, {d}); got {m.shape}")
            if not mask.any():
                raise ValueError("joint_mask selects no joint: nothing to condition on")
        bad = mask & ~np.isfinite(y)
        if bad.any():
            v, j = np.argwhere(bad)[0]
            raise ValueError(f"via-point {v} has value {y[v, j]} for {self.joint_names[j]}; "
                             f"expected a finite number (or mask the joint out)")
        return x_via, np.where(mask, y, 0.0), mask

    def _check_demos(self, Y, x):
        d = self.n_joints
        if isinstance(Y, np.ndarray) or (not isinstance(Y, (list, tuple))):
            Y = np.asarray(Y, dtype=float)
            if Y.ndim != 3:
                raise ValueError(f"Y must have shape (n_demos, T, {d}) or be a list of (T_i, {d}) "
                                 f"arrays; got shape {Y.shape}")
            demos = list(Y)
            xa = np.asarray(x, dtype=float)
            if xa.ndim == 1:
                phases = [xa] * len(demos)
            elif xa.ndim == 2 and xa.shape[0] == len(demos):
                phases = list(xa)
            else:
                raise ValueError(f"x must have shape (T,) or ({len(demos)}, T); got {xa.shape}")
        else:
            demos = [np.asarray(Yi, dtype=float) for Yi in Y]
            if isinstance(x, np.ndarray) and x.ndim == 1:
                raise ValueError("with a list of demonstrations, x must be a list of per-demo "
                                 "phase arrays")
            phases = [np.asarray(xi, dtype=float) for xi in x]
            if len(phases) != len(demos):
                raise ValueError(f"{len(demos)} demonstrations but {len(phases)} phase arrays")
        if len(demos) == 0:
            raise ValueError(f"no demonstrations: expected Y of shape (n_demos >= 1, T, {d})")
        for i, (Yi, xi) in enumerate(zip(demos, phases)):
            if Yi.ndim != 2 or Yi.shape[0] == 0:
                raise ValueError(f"demonstration {i} has shape {Yi.shape}; expected (T >= 1, {d})")
            if Yi.shape[1] != d:
                raise ValueError(f"demonstration {i} has {Yi.shape[1]} joints; this ProMP has {d}: "
                                 f"{joint_list_text(self.joint_names)}")
            if not np.all(np.isfinite(Yi)):
                t, j = np.argwhere(~np.isfinite(Yi))[0]
                raise ValueError(f"demonstration {i} has value {Yi[t, j]} at sample {t} for "
                                 f"{self.joint_names[j]}; expected finite numbers")
            if xi.shape != (Yi.shape[0],):
                raise ValueError(f"demonstration {i} has {Yi.shape[0]} samples but its phases have "
                                 f"shape {xi.shape}")
            self._check_phase(xi, f"of demonstration {i}")
        return demos, phases


def _psd_sqrt(S: np.ndarray) -> np.ndarray:
    """L with L Lᵀ = S for a symmetric positive semi-definite S (Cholesky, or eigen-
    decomposition with negative rounding errors clipped when S is singular)."""
    try:
        return np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        vals, vecs = np.linalg.eigh(0.5 * (S + S.T))
        return vecs * np.sqrt(np.maximum(vals, 0.0))
