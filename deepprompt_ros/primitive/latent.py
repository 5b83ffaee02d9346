"""The conditioned latent distribution q(z) of a primitive (torch-free: the server's handle store
imports it before loading torch).

A plain :class:`LatentGaussian` is the diagonal Gaussian of the Bayesian aggregation (paper Eq. 1
and 3). A model whose latent is split into a linear and a nonlinear block
(``ModelConfig.latent_linear`` k_l > 0) conditions z_lin exactly on the via-points; its latent also
carries a :class:`LinearBlock`: the candidates of z_nl with their importance weights, each with the
posterior mean of z_lin, and the full posterior covariance of z_lin, shared by every candidate.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

__all__ = ["LatentGaussian", "LinearBlock", "PLANNER_VIA_NOISE", "PLANNER_TOLERANCE", "PLANNER_CHANGE_BOUND"]

#: The standard deviation of a planner's via-point in the exact conditioning of a split latent
#: (normalized joint units: rad / the joint's normalization std). A via-point a planner asks for is a
#: hard constraint: at this noise the conditioning alone meets the reachable ones to about 1e-6 rad
#: (:meth:`deepprompt_ros.primitive.deep_promp.DeepProMP.refine_linear` conditions again with a
#: smaller noise when it does not). The primitive server's default (parameter ``via_noise``).
PLANNER_VIA_NOISE = 1e-7

#: The via-point tolerance (rad) a planner's via-points are met to by
#: :meth:`deepprompt_ros.primitive.deep_promp.DeepProMP.condition_planner`: the primitive server's
#: default (parameter ``refine_tolerance``).
PLANNER_TOLERANCE = 1e-6

#: How far (max over phases and joints) meeting a planner's via-points may move the trajectory from
#: the posterior mean at the model's own via-point noise, in multiples of that mean's largest miss at
#: the via-points. Via-points that would need more — a basis made to interpolate many close, noisy
#: points oscillates between them — are not met: the planner gets that posterior and its error
#: (:meth:`deepprompt_ros.primitive.deep_promp.DeepProMP.condition_planner`).
PLANNER_CHANGE_BOUND = 100.0
#: What a conditioning whose I + G Gᵀ rounding breaks expects instead (the end of its refusal).
FACTORABLE_INPUTS = ("expected via-points of the size of the training data and a noise of at least about 1e-10 "
                     "(normalized joint units)")


def _solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a⁻¹ b for a square (triangular) factor a, by LAPACK's solver (no inverse is formed)."""
    return np.linalg.solve(a, b) if a.shape[0] else np.zeros_like(b)


def _all_finite(*arrays: np.ndarray) -> bool:
    """Whether the arrays hold no NaN or inf (their sum is finite unless one does, or an overflow of
    values near the float64 limit, which is refused alike)."""
    return math.isfinite(sum(float(np.add.reduce(a, axis=None)) for a in arrays))


@dataclasses.dataclass(frozen=True)
class LinearBlock:
    """Posterior of the linear block z_lin (k_l) under exact Gaussian conditioning on via-points, for
    each of C candidates of the nonlinear block z_nl.

    z_lin | z_nl = candidate c  ~  N(candidates[c, :k_l], diag(scale) Q diag(scale)),

    Q the posterior covariance of the whitened u = (z_lin − m) / scale (m, scale² the prior: the
    context aggregation, its m moved to each candidate's mode with ``move_prior``), the same for every
    candidate, stored in one of two factored forms:

    * ``form="observation"`` (M <= k_l rows): ``design`` G (M, k_l), the whitened design (rows of the
      via-points' observed joints divided by their noise, columns times ``scale``), and ``chol`` the
      lower Cholesky factor of I_M + G Gᵀ; Q = I − Gᵀ (I + G Gᵀ)⁻¹ G. A conditioning whose mean needs
      no factor leaves ``factor`` None: ``chol`` factors I + G Gᵀ when it is first read.
    * ``form="information"`` (M > k_l rows): ``chol`` the lower Cholesky factor of the whitened
      precision I + Gᵀ G; Q = (I + GᵀG)⁻¹. ``design`` is None.

    Attributes
    ----------
    scale : array, shape (k_l,)
        Prior standard deviations of z_lin.
    candidates : array, shape (C, k)
        Full latents [posterior mean of z_lin given the candidate, the candidate of z_nl].
    weights : array, shape (C,)
        Importance weights of the candidates (closed-form marginal likelihood of the via-points times
        q_c(z_nl) / q_all(z_nl)), sum 1.
    factor : array, shape (M, M) or (k_l, k_l), or None
        ``chol`` as computed by the conditioning (None: not yet, observation form only).
    design : array, shape (M, k_l), or None
    form : {"observation", "information"}
    noise : float
        The via-point standard deviation used (normalized joint units, before the importance weights).
    via_error : float
        Max |mean − via-point| (joint units) of the ``mean`` latent over the observed joints of the
        via-points it was conditioned on (of weight > 0).
    nl_var : array, shape (k − k_l,)
        The variance of q(z_nl), the candidates' proposal (with ``decoder_modes``: the prior's, and
        ``MODE_GATE_VAR`` for the coordinate that chooses the mode).
    weight_noise : float or None
        The via-point noise the candidates' weights were computed at when it is not ``noise``
        (``ModelConfig.mode_noise``); a re-conditioning at a smaller noise keeps it.
    move_prior : bool
        Whether the conditioning moved the prior's z_lin to each candidate's mode
        (:func:`~deepprompt_ros.primitive.linear_conditioning.condition_split`).
    prior : (array (k,), array (k,)), or None
        The mean and variance the block was conditioned from (q_c, the aggregation of the contexts' and
        images' encodings; None for a block built by hand).
    context_rows : (array (M', k_l), array (M',) or (K, M')), or None
        The rows of the contexts' linear model the block was conditioned on besides the via-points. A
        re-conditioning (:func:`~deepprompt_ros.primitive.linear_conditioning.refine_split`) starts again
        from ``prior`` and these rows, as this conditioning did.
    """

    scale: np.ndarray
    candidates: np.ndarray
    weights: np.ndarray
    factor: np.ndarray | None
    design: np.ndarray | None
    form: str
    noise: float
    via_error: float
    nl_var: np.ndarray
    weight_noise: float | None = None
    move_prior: bool = False
    prior: tuple[np.ndarray, np.ndarray] | None = None
    context_rows: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def k_lin(self) -> int:
        return int(self.scale.shape[0])

    @property
    def chol(self) -> np.ndarray:
        """The lower Cholesky factor of the form: ``factor``, or in the observation form that of
        I + G Gᵀ computed now (once; two threads may both compute it: equal arrays, either kept)."""
        c = self.factor
        if c is None:
            assert self.form == "observation", "the information form is factored by its conditioning"
            s = self.design @ self.design.T
            s.flat[::s.shape[0] + 1] += 1.0
            try:
                c = np.linalg.cholesky(s)
            except np.linalg.LinAlgError:  # I + GGᵀ is positive definite unless rounding or an overflow breaks it
                raise ValueError(
                    f"the covariance of the exact conditioning of the linear latent block cannot be factored with "
                    f"via-point noise {self.noise:g} (I + G Gᵀ is not positive definite in floating point): "
                    + FACTORABLE_INPUTS) from None
            object.__setattr__(self, "factor", c)
        return c

    def whitened_var(self) -> np.ndarray:
        """diag Q, shape (k_l,)."""
        if self.form == "observation":
            if self.design.shape[0] == 0:
                return np.ones(self.k_lin)
            w = np.linalg.inv(self.chol) @ self.design  # (M, k_l) W = L⁻¹G: Q = I − Wᵀ W
            return np.clip(1.0 - np.einsum("mk,mk->k", w, w), 0.0, 1.0)
        li = _solve(self.chol, np.eye(self.k_lin))  # L⁻¹: Q = L⁻ᵀ L⁻¹
        return (li * li).sum(0)

    def variance(self) -> np.ndarray:
        """The diagonal of the latent's covariance, shape (k,): scale² diag Q, then ``nl_var``."""
        return np.concatenate([self.scale ** 2 * self.whitened_var(), self.nl_var])

    def is_finite(self) -> bool:
        """Whether the factors the covariance is computed from hold no NaN or inf."""
        return _all_finite(self.scale, self.nl_var, *(a for a in (self.factor, self.design) if a is not None))

    def cov(self) -> np.ndarray:
        """The full posterior covariance of z_lin, diag(scale) Q diag(scale), shape (k_l, k_l)."""
        if self.form == "observation":
            w = _solve(self.chol, self.design)
            q = np.eye(self.k_lin) - w.T @ w
        else:
            li = _solve(self.chol, np.eye(self.k_lin))
            q = li.T @ li
        return q * self.scale[:, None] * self.scale[None, :]

    def draw_lin(self, eps: np.ndarray, eps_obs: np.ndarray | None = None) -> np.ndarray:
        """Zero-mean draws of z_lin from N(0, diag(scale) Q diag(scale)): eps (n, k_l) standard normal
        (and, in the observation form, eps_obs (n, M) standard normal) → (n, k_l).

        Observation form by pathwise conditioning: u = ε − Gᵀ (I + GGᵀ)⁻¹ (G ε + ε_obs) has covariance
        Q exactly; information form u = L⁻ᵀ ε."""
        if self.form == "observation":
            if self.design.shape[0] == 0:
                u = eps
            else:
                v = self.design @ eps.T + eps_obs.T  # (M, n)
                a = _solve(self.chol.T, _solve(self.chol, v))  # (I + GGᵀ)⁻¹ v
                u = eps - (self.design.T @ a).T
        else:
            u = _solve(self.chol.T, eps.T).T
        return u * self.scale

    def draw(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """n latents: a candidate drawn by weight, then z_lin from its conditional posterior; (n, k)."""
        idx = rng.choice(self.candidates.shape[0], size=n, p=self.weights)
        z = self.candidates[idx].copy()
        eps = rng.standard_normal((n, self.k_lin))
        eps_obs = (rng.standard_normal((n, self.design.shape[0])) if self.form == "observation" else None)
        z[:, :self.k_lin] += self.draw_lin(eps, eps_obs)
        return z


class LatentGaussian:
    """q(z) = N(mean, diag(var)), the conditioned latent distribution of a primitive (immutable).

    ``mean`` is the latent the robot executes and ``var`` the diagonal summary that blending (paper
    Eq. 4) and the server's handles use. With ``linear`` set (a split latent), ``mean`` is the
    candidate of the highest posterior density with its z_lin posterior mean (with ``mode_weights``: the
    modes' z_lin means weighted by them), ``var`` the diagonal of the z_lin
    posterior covariance and the variance of q(z_nl) (the candidates' proposal); sampling and the
    full covariance come from ``linear``. A split latent made without ``var`` computes it from
    ``linear`` when it is first read (executing the mean needs only ``mean``).

    Attributes
    ----------
    mean, var : array, shape (k,)
    linear : LinearBlock or None
        The exact posterior of the linear block (split latents only).
    context_mean, context_var : array, shape (k,), or None
        q_c(z), the aggregation of the contexts and images alone (without the via-points): the
        prior of MAP refinement, whose likelihood holds the via-points. None: not recorded.
    mode_weights : array, shape (K,), or None
        A decoder of several modes (``decoder_modes`` K): the weight of each mode's offset in the
        executed mean (:meth:`deepprompt_ros.primitive.deep_promp.DeepProMP.mean_trajectory`). A split
        latent: the posterior probabilities of the modes, with ``mean``'s z_lin the same weighting of the
        modes' z_lin means — the posterior mean of the trajectory. An aggregation alone (no ``linear``):
        the probabilities of the modes' intervals under N(mean, var) of the mode's coordinate, where its
        samples fall. None: the mode ``mean``'s z_nl chooses.
    """

    __slots__ = ("mean", "_var", "linear", "context_mean", "context_var", "mode_weights")

    def __init__(self, mean: np.ndarray, var: np.ndarray | None = None, linear: LinearBlock | None = None,
                 context_mean: np.ndarray | None = None, context_var: np.ndarray | None = None,
                 mode_weights: np.ndarray | None = None):
        if var is None and linear is None:
            raise ValueError("a latent distribution needs its variance var, or a linear block to compute it from")
        for name, value in (("mean", mean), ("_var", var), ("linear", linear), ("context_mean", context_mean),
                            ("context_var", context_var), ("mode_weights", mode_weights)):
            object.__setattr__(self, name, value)

    def __setattr__(self, name, value):
        raise AttributeError(f"LatentGaussian is immutable: cannot set '{name}'")

    def __reduce__(self):
        return LatentGaussian, (self.mean, self._var, self.linear, self.context_mean, self.context_var,
                                self.mode_weights)

    def __repr__(self) -> str:
        return (f"LatentGaussian(mean={self.mean!r}, var={self.var!r}, linear={self.linear!r}, "
                f"context_mean={self.context_mean!r}, context_var={self.context_var!r}, "
                f"mode_weights={self.mode_weights!r})")

    @property
    def var(self) -> np.ndarray:
        v = self._var
        if v is None:  # (two threads may both compute it: equal arrays, either kept)
            v = self.linear.variance()
            object.__setattr__(self, "_var", v)
        return v

    def with_context(self, context_mean: np.ndarray | None, context_var: np.ndarray | None) -> "LatentGaussian":
        """The same distribution recording another q_c(z) (``context_mean``, ``context_var``)."""
        return LatentGaussian(self.mean, self._var, self.linear, context_mean, context_var, self.mode_weights)

    def is_finite(self) -> bool:
        """Whether mean and variance hold no NaN or inf (a variance not yet computed: its factors)."""
        if not _all_finite(self.mean):
            return False
        if self._var is None:
            return self.linear.is_finite()
        return _all_finite(self._var)

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(self.var)
