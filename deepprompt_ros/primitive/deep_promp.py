"""A trained DeepProMP and the operations of the paper (Sec. III-C and appendix): conditioning
(Eq. 1 and 3; for a split latent also exact Gaussian conditioning of its linear block,
:mod:`deepprompt_ros.primitive.linear_conditioning`), decoding, sampling, blending (Eq. 4) and
refinement (Eq. 5); :meth:`DeepProMP.condition_planner` is the primitive server's default
conditioning of a planner's via-points.

The module is past ~400 lines on purpose: :class:`DeepProMP` is the one object a user or the server
holds, and its methods are mostly input validation and documentation around the computations that
live in the modules named below.

:class:`DeepProMP` validates inputs in the robot's units and evaluates the network through its
float64 numpy twin (:class:`deepprompt_ros.primitive.numpy_net.NumpyNet`); images go through the
torch CNN. Blending is :func:`deepprompt_ros.primitive.blending.blend_gaussians`; the two
refinements of :mod:`deepprompt_ros.primitive.refinement` are two methods, :meth:`DeepProMP.refine`
(meet the via-points exactly) and :meth:`DeepProMP.refine_map` (the MAP latent).

Units: phases x in [0, 1]; joint positions in the robot's units (rad); contexts in their raw
units. Every public method validates its inputs and raises ``ValueError`` saying what is expected.
"""
from __future__ import annotations

import dataclasses
import math
import pathlib
import time
from typing import Callable, Mapping, Sequence

import numpy as np
import torch

from deepprompt_ros.common.joints import joint_list_text
from deepprompt_ros.model.aggregation import bayesian_aggregate
from deepprompt_ros.model.checkpoint import Checkpoint, Normalization, load_checkpoint
from deepprompt_ros.model.network import DeepProMPNet
from deepprompt_ros.primitive.blending import blend_gaussians, blend_mode_weights
from deepprompt_ros.primitive.inputs import check_images, check_phases, check_weights
from deepprompt_ros.primitive.latent import (PLANNER_CHANGE_BOUND, PLANNER_TOLERANCE, PLANNER_VIA_NOISE,
                                            LatentGaussian)
from deepprompt_ros.primitive.linear_context import LinearContext
from deepprompt_ros.primitive.linear_conditioning import (SplitRefinement, condition_split, linear_block_variance,
                                                          refine_split)
from deepprompt_ros.primitive.numpy_net import METRIC_PHASES, NumpyNet
from deepprompt_ros.primitive.refinement import RefinementResult, refine_exact, refine_map

__all__ = ["DeepProMP", "PlannerConditioning"]


def _joined(parts: list) -> np.ndarray:
    """The arrays of ``parts`` concatenated along their first axis (a single one as it is)."""
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


@dataclasses.dataclass(frozen=True)
class PlannerConditioning:
    """Outcome of :meth:`DeepProMP.condition_planner`.

    Attributes
    ----------
    latent : LatentGaussian
        The conditioned latent (for a split latent, the best one re-conditioning found).
    via_error : float
        Max |mean trajectory − via-point| (joint units) over the observed joints of the via-points of
        weight > 0; 0 without such a joint.
    iterations : int
        How many times the linear block was conditioned again with a smaller noise (0: met by the
        first conditioning, or a plain latent).
    reason : str
        How the latent was obtained (why the via-points were not met, when they were not).
    """

    latent: LatentGaussian
    via_error: float
    iterations: int
    reason: str = ""


class DeepProMP:
    """A trained DeepProMP with its joint names and normalization.

    Parameters
    ----------
    net : DeepProMPNet
    normalization : Normalization
    joint_names : sequence of str, length d
    name : str
    metadata : mapping, optional (training provenance)
    """

    def __init__(self, net: DeepProMPNet, normalization: Normalization, joint_names: Sequence[str],
                 name: str = "primitive", metadata: Mapping | None = None):
        self.net = net.eval()
        self.cfg = net.cfg
        self.norm = normalization
        self.joint_names = tuple(joint_names)
        self.name = name
        self.metadata = dict(metadata or {})
        if len(self.joint_names) != self.cfg.n_joints:
            raise ValueError(f"{len(self.joint_names)} joint names for a model with {self.cfg.n_joints} joints")
        self._np = NumpyNet(net, normalization)
        self._split = self.cfg.latent_linear > 0
        self._context_dims = dict(self.cfg.context_dims)
        sel = self.metadata.get("selection")
        record = (sel.get("context") or {}) if isinstance(sel, Mapping) else {}
        self.linear_context = self._read_linear_context(record.get("linear"))
        #: with the contexts' linear model in a request, whether the images' encodings still inform z_lin
        #: (``selection.context.images_inform_z_lin``, default true) or z_nl only
        self.images_inform_z_lin = bool(record.get("images_inform_z_lin", True))

    def _read_linear_context(self, rec) -> LinearContext | None:
        """The joint linear model of the low-dimensional contexts the training chose to condition z_lin on
        (``rec`` = ``metadata["selection"]["context"]["linear"]``,
        :mod:`deepprompt_ros.primitive.linear_context`), or None; ``ValueError`` naming what is wrong for a
        record that does not fit this model."""
        if not rec:
            return None
        if not isinstance(rec, Mapping):
            raise ValueError(f"model '{self.name}': selection.context.linear must be a linear context record, got "
                             f"{type(rec).__name__}")
        lin = LinearContext.from_json(rec)
        if (not self._split or lin.b.shape[1] != self.cfg.latent_linear
                or any(self._context_dims.get(n) != d for n, d in zip(lin.names, lin.dims))):
            raise ValueError(f"model '{self.name}': the linear context model of {dict(zip(lin.names, lin.dims))} "
                             f"(B {lin.b.shape}) does not fit the model (latent_linear {self.cfg.latent_linear}, "
                             f"contexts {dict(self._context_dims)})")
        k_m = 0 if lin.mode_means is None else lin.mode_means.shape[0]
        if k_m != self.cfg.decoder_modes:
            raise ValueError(f"model '{self.name}': the linear context model has a mean for {k_m} modes, the decoder "
                             f"{self.cfg.decoder_modes} modes (decoder_modes); expected one mean per mode of the "
                             "decoder (none for one mode)")
        return lin

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_checkpoint(cls, ck: Checkpoint | str, name: str | None = None) -> "DeepProMP":
        if not isinstance(ck, Checkpoint):
            name = name or pathlib.Path(ck).stem
            ck = load_checkpoint(ck)
        return cls(ck.build(), ck.normalization, ck.joint_names, name or "primitive", ck.metadata)

    def with_residual_scale(self, residual_scale: float) -> "DeepProMP":
        """A copy whose decoder's MLP residual carries the factor ``residual_scale`` instead of the
        trained one (``decoder_basis`` > 0 only; 0 = the linear part Φ(x)(b + A z) alone). The
        weights are shared in value (copied), the encoders are unchanged."""
        if not self.cfg.decoder_basis:
            raise ValueError("with_residual_scale needs a residual decoder (decoder_basis > 0)")
        net = DeepProMPNet(dataclasses.replace(self.cfg, residual_scale=float(residual_scale)))
        net.load_state_dict(self.net.state_dict())
        return DeepProMP(net, self.norm, self.joint_names, self.name, self.metadata)

    # ------------------------------------------------------------------ properties
    @property
    def n_joints(self) -> int:
        return self.cfg.n_joints

    @property
    def latent_dim(self) -> int:
        return self.cfg.latent_dim

    @property
    def phase_type(self) -> str:
        return self.cfg.phase_type

    @property
    def exact_conditioning(self) -> bool:
        """Whether via-points condition a linear latent block exactly (``latent_linear`` > 0): the
        mean then meets reachable via-points by conditioning alone (:meth:`refine_linear` when a
        smaller noise is needed)."""
        return self._split

    @property
    def context_dims(self) -> dict[str, int]:
        return dict(self._context_dims)

    @property
    def image_shape(self):
        return self.cfg.image_shape

    # ------------------------------------------------------------------ validation
    def check_phases(self, x, what: str = "phase") -> np.ndarray:
        return check_phases(x, what, rhythmic=self.phase_type == "rhythmic")

    def check_positions(self, y, n: int | None = None, what: str = "via-point") -> np.ndarray:
        y = np.asarray(y, dtype=np.float64)
        if y.ndim == 1:
            y = y[None, :]
        if y.ndim != 2:
            raise ValueError(f"{what} positions must have shape (n, {self.n_joints}), got {y.shape}")
        if y.shape[1] != self.n_joints:
            raise ValueError(f"{what} has {y.shape[1]} joint values; primitive '{self.name}' has "
                             f"{self.n_joints} joints: {joint_list_text(self.joint_names)}")
        if n is not None and y.shape[0] != n:
            raise ValueError(f"{y.shape[0]} {what} position rows for {n} phases; expected one row per phase")
        if not np.isfinite(y).all():
            i, j = np.argwhere(~np.isfinite(y))[0]
            raise ValueError(f"{what} {i} joint '{self.joint_names[j]}' is NaN or inf; expected finite positions")
        return y

    def check_mask(self, mask, n: int) -> np.ndarray:
        """Joints constrained by each of ``n`` via-points: shape (n, d) or (d,), None = all → (n, d) bool."""
        if mask is None:
            return np.ones((n, self.n_joints), dtype=bool)
        m = np.asarray(mask, dtype=bool)
        if m.ndim == 1:
            m = np.broadcast_to(m, (n, m.shape[0]))
        if m.shape != (n, self.n_joints):
            raise ValueError(f"joint mask must have shape ({n}, {self.n_joints}) or ({self.n_joints},), got {m.shape}")
        return m

    # ------------------------------------------------------------------ encoders
    def encode_via_points(self, x, y):
        """Per-element q(z | a_i): x (n,), y (n, d) rad → μ_i, σ²_i (n, k)."""
        return self._np.encode_via_points(x, y)

    @property
    def mode_noise(self) -> float:
        """The via-point noise the posterior probabilities of the decoder's modes are computed at, whatever
        noise a request states: ``ModelConfig.mode_noise``, else the model's ``via_noise``."""
        return self.cfg.mode_noise or self.cfg.via_noise

    def mode_of(self, z) -> np.ndarray | None:
        """The mode of the decoder each latent z (k,) or (n, k) chooses (``ModelConfig.decoder_modes``:
        its z_nl's first coordinate), an int array of shape () or (n,); None for a decoder of one mode."""
        if not self._np.has_modes:
            return None
        return np.asarray(self._np.mode_of(np.asarray(z, dtype=np.float64)[..., self.cfg.latent_linear:]))

    def encode_context(self, name: str, c):
        """q(z | c_i) for low-dim contexts: c (m, c_dim) raw units → μ_i, σ²_i (m, k)."""
        dim = self._context_dims.get(name)
        if dim is None:
            raise ValueError(f"primitive '{self.name}' takes no context '{name}'; it accepts "
                             f"{sorted(self._context_dims) or 'no low-dimensional contexts'}"
                             f"{' and images' if self.image_shape else ''}")
        c = np.asarray(c, dtype=np.float64)
        if c.ndim == 1:
            c = c[None, :]
        if c.ndim != 2 or c.shape[1] != dim or c.shape[0] < 1:
            raise ValueError(f"context '{name}' must have {dim} values per vector (shape (m, {dim})), got {c.shape}")
        if not np.isfinite(c).all():
            raise ValueError(f"context '{name}' contains NaN or inf; expected finite values")
        return self._np.encode_context(name, c)

    def encode_images(self, images):
        """q(z | images): images (n, H, W, 3) uint8 of one scene, averaged in embedding space → (1, k)."""
        if self.image_shape is None:
            raise ValueError(f"primitive '{self.name}' takes no images")
        im = check_images(images, self.image_shape)
        with torch.inference_mode():
            t = torch.from_numpy(np.ascontiguousarray(im)).permute(0, 3, 1, 2).float().unsqueeze(0) / 255.0
            mu, var = self.net.encode_images(t, torch.ones(1, t.shape[1]))
        return mu[0].double().numpy(), var[0].double().numpy()

    # ------------------------------------------------------------------ conditioning
    def prior(self) -> LatentGaussian:
        """p0(z) = N(0, I); with several modes of the decoder and no MLP residual, the modes weighted by their
        shares (:meth:`_aggregation_latent`)."""
        return self._aggregation_latent(np.zeros(self.latent_dim), np.ones(self.latent_dim))

    def _aggregation_latent(self, mean: np.ndarray, var: np.ndarray, context_mean: np.ndarray | None = None,
                            context_var: np.ndarray | None = None) -> LatentGaussian:
        """The latent of a Bayesian aggregation that no via-point and no linear context model conditions.

        With several modes of the decoder (``decoder_modes``) and no MLP residual the mode is chosen by z_nl's
        first coordinate through a step (:meth:`mode_of`): the training decodes latents drawn from the
        aggregation, each with the mode its draw chooses, and the step passes no gradient to that coordinate's
        encoding. The executed mean is therefore the mean over those draws: each mode's offset weighted by the
        probability of its interval under the aggregation's N(mean, var) of that coordinate (``mode_weights``;
        the shares for the prior), which is where the samples (:meth:`sample`) fall too — not the one mode the
        coordinate's mean falls in."""
        if not self._np.has_modes or self._np.mlp_active:
            return LatentGaussian(mean, var, context_mean=context_mean, context_var=context_var)
        k_l = self.cfg.latent_linear
        return LatentGaussian(mean, var, context_mean=context_mean, context_var=context_var,
                              mode_weights=self._np.mode_probabilities(mean[k_l], var[k_l]))

    def condition(self, via_x=None, via_y=None, via_weights=None, via_mask=None,
                  contexts: Mapping[str, np.ndarray] | None = None,
                  context_weights: Mapping[str, Sequence[float]] | None = None,
                  images=None, image_weight: float = 1.0, via_noise: float | None = None,
                  n_candidates: int = 32, smooth_noise: float | None = None) -> LatentGaussian:
        """q(z | A, C, ω): Bayesian aggregation (paper Eq. 1 and the importance-weighted Eq. 3), and for
        a split latent (``latent_linear`` k_l > 0) exact Gaussian conditioning of z_lin on the via-points.

        Plain latent: the aggregation of every element. Split latent
        (:mod:`deepprompt_ros.primitive.linear_conditioning`): the prior of z_lin is the aggregation
        q_c of the contexts and images alone; z_nl candidates (the mean of the aggregation of
        everything, via-points included, and ``n_candidates`` seeded quasi-random points of it) are
        weighted by the closed-form marginal likelihood of the via-points times q_c(z_nl) / q_all(z_nl)
        (importance weights of the posterior under the prior q_c); z_lin is conditioned exactly on the
        observed joints of each via-point, whose weight ω scales its precision. The mean is the
        candidate of the highest posterior density with its z_lin posterior mean (with several modes of the
        decoder and no MLP residual: the modes' z_lin means weighted by the modes' posterior probabilities
        at ``mode_noise``, the executed mean weighing the modes' offsets alike); :meth:`sample` draws
        candidates by
        weight and z_lin from its posterior, so samples pass the via-points within the noise.
        Without a via-point of weight > 0 both give the aggregation. The latent records q_c
        (``context_mean``, ``context_var``), the prior of :meth:`refine_map`.

        Parameters
        ----------
        via_x : array, shape (n,), phases in [0, 1]
        via_y : array, shape (n, d), joint positions
        via_weights : array, shape (n,), ω ≥ 0 (default 1; 0 removes the via-point exactly)
        via_mask : array of bool, shape (n, d) or (d,), optional
            Joints constrained by each via-point. The encoder needs whole configurations, so the
            unconstrained joints of a partial via-point are filled with the mean trajectory
            conditioned on everything else, and its encoding counts with its weight times the share
            of joints it constrains (a via-point of 2 of 6 joints carries a third of a full one's
            evidence): the free joints stay wider than under a full via-point. A split latent's
            exact conditioning observes the constrained joints only. :meth:`refine` with the same
            mask then meets the constrained joints exactly.
        contexts : mapping modality -> array, shape (m, c) or (c,)
        context_weights : mapping modality -> array, shape (m,)
        images : array, shape (n_img, H, W, 3) uint8, the images of one scene
        image_weight : float
        via_noise : float, optional
            Split latent: the via-points' standard deviation ν (normalized joint units: rad / the
            joint's normalization std); default ``ModelConfig.via_noise``.
        n_candidates : int
            Split latent: quasi-random points of z_nl besides the mean of its aggregation.
        smooth_noise : float, optional
            Split latent, a noise above ν (normalized joint units): the mean's z_lin is the posterior
            mean at this noise moved by the smallest change of the trajectory that meets the via-points
            as the posterior at ν does (:func:`~deepprompt_ros.primitive.linear_conditioning.smallest_change`);
            the covariance and the candidates' weights are those at ν. None (default), or not above
            ν: the posterior mean at ν.
        """
        noise = self.cfg.via_noise if via_noise is None else via_noise
        if isinstance(noise, bool) or not (isinstance(noise, (int, float, np.floating, np.integer))
                                            and math.isfinite(noise) and noise > 0):
            raise ValueError(f"via_noise = {via_noise!r}: expected a finite standard deviation > 0 (normalized joint "
                             "units) or None (the model's own)")
        if isinstance(n_candidates, bool) or not isinstance(n_candidates, (int, np.integer)) or n_candidates < 0:
            raise ValueError(f"n_candidates = {n_candidates!r}: expected an integer >= 0")
        if smooth_noise is not None and (isinstance(smooth_noise, bool) or not (
                isinstance(smooth_noise, (int, float, np.floating, np.integer)) and math.isfinite(smooth_noise)
                and smooth_noise > 0)):
            raise ValueError(f"smooth_noise = {smooth_noise!r}: expected a finite standard deviation > 0 (normalized "
                             "joint units) or None (the posterior mean at via_noise)")
        smooth = None if smooth_noise is None or smooth_noise <= noise else float(smooth_noise)
        with np.errstate(over="ignore", invalid="ignore"):
            out = self._condition(via_x, via_y, via_weights, via_mask, contexts, context_weights, images,
                                  image_weight, float(noise), int(n_candidates), smooth)
            finite = out.is_finite()  # no NaN or inf in the mean or the variance
        if not finite:
            # finite but huge inputs (e.g. 1e308) overflow in the normalization, the aggregation or the
            # exact conditioning: refused with the values that caused it
            vy = np.abs(np.asarray(via_y, dtype=np.float64)) if via_y is not None else np.zeros(1)
            cv = [np.abs(np.asarray(c, dtype=np.float64)).max() for c in (contexts or {}).values()]
            ws = [np.asarray(via_weights if via_weights is not None else 1.0, dtype=np.float64).max(),
                  *(np.asarray(w, dtype=np.float64).max() for w in (context_weights or {}).values()), image_weight]
            raise ValueError(
                f"the via-points and contexts give primitive '{self.name}' a latent distribution with NaN or inf (an "
                f"overflow): largest |via-point position| {float(vy.max()) if vy.size else 0.0:.3g} rad, largest "
                f"|context value| {max(cv, default=0.0):.3g}, largest weight {max(ws):.3g}; expected joint positions "
                "and context values of the size of the training data and weights of moderate size")
        return out

    def condition_planner(self, via_x=None, via_y=None, via_weights=None, via_mask=None,
                          contexts: Mapping[str, np.ndarray] | None = None,
                          context_weights: Mapping[str, Sequence[float]] | None = None,
                          images=None, image_weight: float = 1.0, via_noise: float | None = PLANNER_VIA_NOISE,
                          tol: float = PLANNER_TOLERANCE, max_iterations: int = 200,
                          time_budget: float | None = None, smooth: bool = True) -> PlannerConditioning:
        """Condition on a planner's via-points as the primitive server's default Condition request does
        (no Eq. 5 refinement asked for): :meth:`condition` with the planner's via-point noise, and for a
        split latent whose mean still misses a via-point by more than ``tol``, its linear block
        conditioned again with a smaller noise (:meth:`refine_linear`) until the mean meets them.

        A plain latent is the aggregation of :meth:`condition` as it is (``via_noise`` and the budgets
        unused); its via-point error is measured and reported all the same.

        Parameters
        ----------
        via_x, via_y, via_weights, via_mask, contexts, context_weights, images, image_weight
            As for :meth:`condition`; via-points of weight 0 are not met.
        via_noise : float, optional
            Split latent: the via-points' standard deviation in the first conditioning (normalized
            joint units), default the planner's
            (:data:`~deepprompt_ros.primitive.latent.PLANNER_VIA_NOISE`); None: the model's own
            (``ModelConfig.via_noise``).
        tol : float
            Via-point tolerance (joint units, rad); default
            :data:`~deepprompt_ros.primitive.latent.PLANNER_TOLERANCE`.
        max_iterations : int
            Re-conditionings at most (each with the noise divided by 10).
        time_budget : float, optional
            Wall time (s) after which no further re-conditioning starts (None: no limit).
        smooth : bool
            Split latent: the mean first smooths the via-points as the model's own cross-validated
            noise (``ModelConfig.via_noise``) does, then meets them by the smallest change of the
            trajectory (:meth:`condition`'s ``smooth_noise``); the distribution around it is the one
            at ``via_noise``. A via-point observed with noise is then not interpolated into the
            whole trajectory. False, or when that mean misses a via-point by more than ``tol``: the
            posterior mean at ``via_noise``.

        Split latent, via-points not met by either mean: the linear block conditioned again
        (:meth:`refine_linear`). Whatever meets the via-points (or comes closest) is returned only if
        it stays within :data:`~deepprompt_ros.primitive.latent.PLANNER_CHANGE_BOUND` times the
        largest miss (at least ``tol``) of the posterior at the model's own noise, max over phases and
        joints; else that posterior is returned with its error: many close via-points with noise can be
        met only by a trajectory that oscillates between them.

        Returns
        -------
        PlannerConditioning; ``via_error`` > ``tol`` says the via-points were not met (the linear
        block cannot meet them, cannot meet them without that oscillation, or a budget ended the
        re-conditioning) and ``reason`` says which, never a silent miss.
        """
        self._check_budgets(tol, max_iterations, time_budget)
        if via_x is not None and via_y is not None and np.size(via_x) == 0 == np.size(via_y):
            # no via-point: the aggregation of the rest
            via_x = via_y = via_weights = via_mask = None
        inputs = (via_x, via_y, via_weights, via_mask, contexts, context_weights, images, image_weight)
        own = self.cfg.via_noise
        softer = self._split and via_x is not None and via_noise is not None and own > via_noise
        latent = self.condition(*inputs, via_noise=via_noise, smooth_noise=own if smooth and softer else None)
        if latent.linear is not None and latent.linear.via_error <= tol:
            return PlannerConditioning(latent, latent.linear.via_error, 0, "met by the conditioning")
        if via_x is None:
            return PlannerConditioning(latent, 0.0, 0, "no via-point")
        x = self.check_phases(via_x, "via-point phase")
        y = self.check_positions(via_y, x.shape[0])
        active = check_weights(via_weights, x.shape[0], "via-points") > 0
        x, y, mask = x[active], y[active], self.check_mask(via_mask, x.shape[0])[active]

        def error(lat):
            return float(np.abs((self.decode_mean(lat, x) - y)[mask]).max()) if mask.any() else 0.0

        if latent.linear is None:
            return PlannerConditioning(latent, error(latent), 0, "a plain latent: the aggregation as it is")
        if smooth and softer:  # the smoothed mean missed: the posterior mean at via_noise
            latent = self.condition(*inputs, via_noise=via_noise)
        if latent.linear.via_error <= tol:
            out = PlannerConditioning(latent, latent.linear.via_error, 0, "met by the exact posterior mean")
        else:
            res = self.refine_linear(latent, x, y, mask, tol=tol, max_iterations=max_iterations,
                                     time_budget=time_budget)
            out = PlannerConditioning(res.latent, res.max_error, res.iterations, res.reason)
        if not softer:
            return out
        soft = self.condition(*inputs)  # the posterior at the model's own noise
        soft_error = error(soft)
        grid = np.linspace(0.0, 1.0, METRIC_PHASES)
        change = float(np.abs(self.mean_trajectory(out.latent, grid) - self.mean_trajectory(soft, grid)).max())
        if change <= PLANNER_CHANGE_BOUND * max(soft_error, tol):
            return out
        return PlannerConditioning(
            soft, soft_error, out.iterations,
            f"meeting the via-points ({out.reason}: max error {out.via_error:.3g} rad) moves the trajectory up to "
            f"{change:.3g} rad from the posterior at the model's via-point noise {own:g}, more than "
            f"{PLANNER_CHANGE_BOUND:g} times that posterior's largest miss {soft_error:.3g} rad (a swing such as an "
            "oscillation between close via-points, or via-points far from what the linear block spans); that "
            "posterior is given instead")

    def _condition(self, via_x, via_y, via_weights, via_mask, contexts, context_weights, images, image_weight,
                   noise: float, n_candidates: int, smooth: float | None = None) -> LatentGaussian:
        """:meth:`condition` after its checks of ``via_noise`` and ``n_candidates`` (may overflow)."""
        mus, vars_, ws, context_rows = [], [], [], None
        if contexts:
            lin, checked = self.linear_context, {}
            for name, c in contexts.items():
                mu, var = self.encode_context(name, c)
                checked[name] = check_weights((context_weights or {}).get(name), mu.shape[0], f"context '{name}'")
                if lin is not None and name in lin.names:  # z_lin observes it through the linear model; the
                    k_l = self.cfg.latent_linear             # encoding informs z_nl only
                    mu, var = mu.copy(), var.copy()
                    mu[:, :k_l], var[:, :k_l] = 0.0, np.inf
                mus.append(mu), vars_.append(var), ws.append(checked[name])
            if lin is not None:
                context_rows = lin.rows(contexts, checked)
        if images is not None:
            mu, var = self.encode_images(images)
            if context_rows is not None and not self.images_inform_z_lin:  # the contexts' linear model decides z_lin
                mu, var = mu.copy(), var.copy()
                mu[:, :self.cfg.latent_linear], var[:, :self.cfg.latent_linear] = 0.0, np.inf
            mus.append(mu), vars_.append(var)
            ws.append(check_weights([image_weight], 1, "images"))
        n_c = len(mus)
        q_c = self.aggregate(_joined(mus), _joined(vars_), _joined(ws)) if mus else self.prior()
        via = None
        if via_x is not None or via_y is not None:
            if via_x is None or via_y is None:
                raise ValueError("via-points need both phases via_x (n,) and positions via_y (n, d)")
            x = self.check_phases(via_x, "via-point phase")
            y = self.check_positions(via_y, x.shape[0])
            # None: every weight 1, every joint constrained (nothing to weigh or drop)
            w = None if via_weights is None else check_weights(via_weights, x.shape[0], "via-points")
            mask = None if via_mask is None else self.check_mask(via_mask, x.shape[0])
            via = x, y, w, mask
            if not self._split or self._np.decoder_reads_z_nl:  # (a split latent's z_lin never reads the encodings)
                y_enc, w_enc = y, np.ones(x.shape[0]) if w is None else w
                if mask is not None and not mask.all():
                    full = mask.all(1)
                    base = self._condition(x[full], y[full], w_enc[full], None, contexts, context_weights, images,
                                           image_weight, noise, n_candidates, smooth)
                    y_enc = np.where(mask, y, self.decode_mean(base, x))
                    w_enc = w_enc * mask.sum(1) / self.n_joints
                mu, var = self.encode_via_points(x, y_enc)
                mus.append(mu), vars_.append(var), ws.append(w_enc)
        if not mus and via is None:
            return self.prior()
        # q_all differs from q_c only when via-point encodings were added after the contexts and images
        q_all = self.aggregate(_joined(mus), _joined(vars_), _joined(ws)) if len(mus) > n_c else q_c
        observed = None if via is None else self._observed(*via)
        has_via = via is not None and via[0].shape[0] and (observed is None or observed.any())
        if self._split and has_via and context_rows is None:
            return condition_split(self._np, q_c.mean, q_c.var, q_all.mean, q_all.var, *via[:3], observed, noise,
                                   n_candidates, smooth_noise=smooth,
                                   weight_noise=self.mode_noise)
        if self._split and context_rows is not None:
            # q(z | contexts, images) with the linear contexts' exact posterior of z_lin (its diagonal) is the
            # latent's record of q_c: the prior of MAP refinement of a model with one mode; without a via-point it
            # is the distribution itself. With several modes it is the one of the mode the via-points and contexts
            # chose (the contexts' model has a mean per mode). A re-conditioning starts from the encodings'
            # aggregation and the rows that the linear block records.
            def given_contexts(n, candidates=None):
                return condition_split(self._np, q_c.mean, q_c.var, q_all.mean, q_all.var, np.zeros(0),
                                       np.zeros((0, self.n_joints)), None, None, 1.0, n, candidates_nl=candidates,
                                       context_rows=context_rows)
            k_l = self.cfg.latent_linear
            if not has_via:
                ctx = lat = given_contexts(n_candidates)
            elif self._np.has_modes:
                lat = condition_split(self._np, q_c.mean, q_c.var, q_all.mean, q_all.var, *via[:3], observed, noise,
                                      n_candidates, context_rows=context_rows, smooth_noise=smooth,
                                      weight_noise=self.mode_noise)
                ctx = given_contexts(0, lat.mean[None, k_l:])
            else:
                ctx = given_contexts(0)
                lat = condition_split(self._np, q_c.mean, q_c.var, q_all.mean, q_all.var, *via[:3], observed, noise,
                                      n_candidates, context_rows=context_rows, smooth_noise=smooth,
                                      weight_noise=self.mode_noise)
            # (the latent's q_c records the linear model's posterior of z_lin; its block records the encodings'
            # aggregation and the rows, which a re-conditioning starts from again)
            return LatentGaussian(lat.mean, lat._var, lat.linear,
                                  np.concatenate([ctx.mean[:k_l], q_c.mean[k_l:]]),
                                  np.concatenate([ctx.var[:k_l], q_c.var[k_l:]]), lat.mode_weights)
        # no observed joint of a via-point of weight > 0: the aggregation is the distribution
        return self._aggregation_latent(q_all.mean, q_all.var, q_c.mean, q_c.var)

    @staticmethod
    def _observed(x, y, w, mask) -> np.ndarray | None:
        """The joints the exact conditioning observes: those of the via-points of weight > 0, shape (n, d)
        bool, or None for every joint of every via-point (neither weights nor a mask given)."""
        if mask is None:
            return None if w is None else np.repeat((w > 0)[:, None], y.shape[1], axis=1)
        return mask if w is None else (w > 0)[:, None] & mask

    @staticmethod
    def aggregate(mu: np.ndarray, var: np.ndarray, w: np.ndarray) -> LatentGaussian:
        """σ²_z = (1 + Σ ω_i/σ²_i)^-1, μ_z = σ²_z Σ ω_i μ_i/σ²_i (paper Eq. 1 and 3).

        mu, var : array, shape (n, k); w : array, shape (n,).
        """
        if mu.shape[0] == 1:  # one element (a request's one context): the same sums of one term, fewer steps
            prec = w[0] / var[0]
            var_z = 1.0 / (1.0 + prec)
            return LatentGaussian(var_z * (prec * mu[0]), var_z)
        return LatentGaussian(*bayesian_aggregate(mu, var, w))

    # ------------------------------------------------------------------ decoding
    def decode(self, z, x) -> np.ndarray:
        """μ_y(z, x) in joint units.

        Parameters
        ----------
        z : array, shape (k,) or (n, k)
        x : array, shape (T,)

        Returns
        -------
        array, shape (T, d) or (n, T, d)
        """
        return self._np.decode(z, x)

    def decode_per_phase(self, z_x: np.ndarray, x: np.ndarray, mode_weights: np.ndarray | None = None) -> np.ndarray:
        """Decode a latent that varies with phase (blending): z_x (T, k), x (T,) → (T, d). With
        ``decoder_modes``, ``mode_weights`` (T, K) weighs the modes' offsets at each phase instead of the
        mode each z_x chooses (a blend between two modes; :meth:`mode_weights`)."""
        return self._np.decode_per_phase(z_x, x, mode_weights)

    def mode_weights(self, latent: LatentGaussian) -> np.ndarray | None:
        """The weights (K,) of the decoder's modes in ``latent``'s executed mean: its ``mode_weights`` (the
        modes' posterior probabilities), else one-hot on the mode its mean chooses; None for a decoder of one
        mode. What a blend interpolates (:meth:`blend`)."""
        if latent.mode_weights is not None:
            return np.asarray(latent.mode_weights, dtype=np.float64)
        k = self.mode_of(latent.mean)
        return None if k is None else np.eye(self.cfg.decoder_modes)[int(k)]

    def decode_mean(self, latent: LatentGaussian, x: np.ndarray, eps: np.ndarray | None = None) -> np.ndarray:
        """The trajectory of ``latent``'s mean (+ ``eps`` times its std, eps (k,)) at checked phases x (T,),
        with the modes' offsets weighted by its ``mode_weights`` when it has them, (T, d) joint units."""
        z = latent.mean if eps is None else latent.mean + eps * latent.std
        return self._np.decode_weighted(z, x, latent.mode_weights)

    def decoder_jacobian(self, z: np.ndarray, x: np.ndarray, smoothing: float | None = None):
        """μ_y(z, x_i) and ∂μ_y/∂z at each phase, joint units (see
        :meth:`deepprompt_ros.primitive.numpy_net.NumpyNet.decoder_jacobian`).

        Parameters
        ----------
        z : array, shape (k,) or (K, k)
        x : array, shape (n,)
        smoothing : float, optional
            β of a softplus surrogate of ReLU (refinement's continuation); None = the exact decoder.

        Returns
        -------
        y : array, shape (n, d) or (K, n, d); jac : array, shape (n, d, k) or (K, n, d, k)
        """
        return self._np.decoder_jacobian(z, x, smoothing)

    def mean_trajectory(self, latent: LatentGaussian, x) -> np.ndarray:
        """The trajectory a robot executes for ``latent``: μ_y(μ_z, x), shape (T, d); with several modes of
        the decoder weighted by the latent's ``mode_weights`` (the posterior mean of the trajectory)."""
        return self.decode_mean(latent, self.check_phases(x))

    def sample(self, latent: LatentGaussian, x, n: int, rng: np.random.Generator | int | None = None) -> np.ndarray:
        """n trajectories, each with ONE z ~ q(z) held constant over the trajectory (paper Sec. III-C).
        A split latent's z: a z_nl candidate drawn by weight and z_lin from the full posterior given it.

        Returns
        -------
        array, shape (n, T, d)
        """
        if n < 1:
            raise ValueError(f"number of samples must be >= 1, got {n}")
        rng = np.random.default_rng(rng)
        if latent.linear is not None:  # a candidate of z_nl by weight, z_lin from its exact posterior
            z = latent.linear.draw(rng, n)
        else:
            z = latent.mean + rng.standard_normal((n, self.latent_dim)) * latent.std
        return self.decode(z, self.check_phases(x))

    def linearized_std(self, latent: LatentGaussian, x) -> np.ndarray:
        """Per-point standard deviation of the trajectory without sampling.

        Plain latent: linearized at the mean, sqrt(diag(J diag(var) Jᵀ)), J = ∂μ_y/∂z at (mean, x); with
        ``mode_weights`` (an aggregation with several modes of the decoder) plus the weighted variance of the
        modes' offsets Φ(x) m_k, between which its samples fall.
        Split latent: exact for the mixture :meth:`sample` draws from, as the decoder is linear in
        z_lin: Var = J_lin Σ_lin J_linᵀ (the full z_lin covariance, the same for every candidate,
        J_lin = Φ(x) A) + the weighted variance of the candidates' mean trajectories.

        Parameters
        ----------
        x : array, shape (T,)

        Returns
        -------
        array, shape (T, d)
        """
        x = self.check_phases(x)
        if latent.linear is None:
            _, jac = self.decoder_jacobian(latent.mean, x)  # (T, d, k)
            var = ((jac * latent.std) ** 2).sum(axis=-1)
            if latent.mode_weights is not None:  # and the spread of the modes' offsets the mean weighs
                w = np.asarray(latent.mode_weights, dtype=np.float64)
                offsets = self._np.mode_offsets(x)  # (K, T, d)
                dev = offsets - np.einsum("k,ktd->td", w, offsets)
                var = var + np.einsum("k,ktd->td", w, dev * dev)
            return np.sqrt(var)
        block = latent.linear
        _, j_lin = self._np.linear_design(x)  # (T, d, k_l)
        var = linear_block_variance(block, j_lin.reshape(-1, block.k_lin)).reshape(x.shape[0], -1)
        w = block.weights
        keep = w > 1e-12 * w.max()  # candidates that weigh anything (often one dominates)
        if keep.sum() > 1:
            w = w[keep] / w[keep].sum()
            y = self.decode(block.candidates[keep], x).reshape(w.shape[0], -1)  # (C', T·d)
            dev = y - w @ y
            var += (w @ (dev * dev)).reshape(var.shape)
        return np.sqrt(var)

    def trajectory_std(self, latent: LatentGaussian, x, n_samples: int = 64, seed: int = 0) -> np.ndarray:
        """Per-point standard deviation of the trajectory distribution (Monte Carlo), shape (T, d)."""
        return self.sample(latent, x, n_samples, seed).std(0)

    # ------------------------------------------------------------------ blending
    @staticmethod
    def blend_latent(a: LatentGaussian, b: LatentGaussian, omega) -> tuple[np.ndarray, np.ndarray]:
        """q_b(z | x) ∝ q_a(z)^ω(x) q_b(z)^(1−ω(x)) (paper Eq. 4), per phase.

        Parameters
        ----------
        omega : array, shape (T,), values in [0, 1]

        Returns
        -------
        mean, var : array, shape (T, k)
        """
        w = np.asarray(omega, dtype=np.float64)
        if not np.all(np.isfinite(w)) or w.min() < 0 or w.max() > 1:
            raise ValueError("blending weights ω(x) must be finite and in [0, 1]")
        return blend_gaussians(w, a.mean, a.var, b.mean, b.var)

    def blend(self, a: LatentGaussian, b: LatentGaussian, omega: Callable | np.ndarray, x,
              eps: np.ndarray | None = None) -> np.ndarray:
        """Blended trajectory z(x) = μ_b(x) + ε σ_b(x) with ONE ε per trajectory (smooth in x).

        Parameters
        ----------
        omega : callable x -> ω(x) in [0, 1], or array shape (T,)
        eps : array, shape (k,), optional; None decodes the blended mean (ε = 0)

        Returns
        -------
        array, shape (T, d)
        """
        x = self.check_phases(x)
        w = omega(x) if callable(omega) else np.asarray(omega, dtype=np.float64)
        if np.shape(w) != x.shape:
            raise ValueError(f"ω(x) must give one weight per phase: got shape {np.shape(w)} for {x.shape[0]} phases")
        mean, var = self.blend_latent(a, b, w)
        z = mean if eps is None else mean + np.asarray(eps)[None, :] * np.sqrt(var)
        wa, wb = self.mode_weights(a), self.mode_weights(b)
        modes = None if wa is None else blend_mode_weights(w, wa, wb)
        return self.decode_per_phase(z, x, modes)

    # ------------------------------------------------------------------ refinement
    def refine(self, latent: LatentGaussian, via_x, via_y, joint_mask=None, max_iterations: int = 200,
               tol: float = 1e-6, n_samples: int = 16, seed: int = 0, sigma_target: np.ndarray | None = None,
               sigma_iterations: int = 5, max_restarts: int = 5,
               smoothing_schedule: Sequence[float] = (3.0, 10.0, 30.0, 100.0),
               latent_bound: float = 5.0, time_budget: float | None = None) -> RefinementResult:
        """Deployment-time refinement of (μ̃, σ̃) that meets the via-points to ``tol`` (paper Eq. 5
        and appendix): :func:`deepprompt_ros.primitive.refinement.refine_exact`, where the other
        parameters are described. A split latent whose mean meets them already comes back as it is
        (0 iterations); else its linear block is conditioned again with a smaller noise. So does an
        aggregation with several modes whose executed mean meets them; else its most probable mode is
        fitted.
        :meth:`refine_map` is the regularized (MAP) alternative.

        Parameters
        ----------
        latent : LatentGaussian, the initialization (normally the posterior from :meth:`condition`)
        via_x : array, shape (n,)
        via_y : array, shape (n, d)
        joint_mask : array of bool, shape (n, d) or (d,), optional; joints to meet (default all)
        time_budget : float, optional
            Wall time (s) after which no further iteration starts (None: no limit).

        Returns
        -------
        RefinementResult; ``reachable=False`` with the best fit when the via-points cannot all be
        met (never a silent miss), ``out_of_time=True`` as well when the time budget ended it.
        """
        return refine_exact(self, latent, via_x, via_y, joint_mask, max_iterations=max_iterations, tol=tol,
                            n_samples=n_samples, seed=seed, sigma_target=sigma_target,
                            sigma_iterations=sigma_iterations, max_restarts=max_restarts,
                            smoothing_schedule=smoothing_schedule, latent_bound=latent_bound,
                            time_budget=time_budget)

    def refine_linear(self, latent: LatentGaussian, via_x, via_y, joint_mask=None, tol: float = 1e-6,
                      max_iterations: int = 200, time_budget: float | None = None) -> SplitRefinement:
        """Meet via-points with a split latent's mean by exact conditioning of its linear block alone
        (:func:`deepprompt_ros.primitive.linear_conditioning.refine_split`: 0 iterations when met,
        else z_lin conditioned again with the noise divided by 10 per iteration). Unlike
        :meth:`refine` there is no gradient stage: the result is always a split latent, and
        ``max_error`` > ``tol`` says the linear block cannot meet them (or the time budget ended).

        Parameters
        ----------
        latent : LatentGaussian from :meth:`condition` of this (split) primitive
        via_x : array, shape (n,); via_y : array, shape (n, d); joint_mask : (n, d) or (d,), optional
        time_budget : float, optional, wall time (s) after which no further iteration starts
        """
        if latent.linear is None or latent.context_mean is None:
            raise ValueError("refine_linear needs a latent of a split primitive (latent_linear > 0) from condition() "
                             "with at least one via-point")
        x = self.check_phases(via_x, "via-point phase")
        y = self.check_positions(via_y, x.shape[0])
        mask = self.check_mask(joint_mask, x.shape[0])
        self._check_budgets(tol, max_iterations, time_budget)
        deadline = math.inf if time_budget is None else time.perf_counter() + time_budget
        return refine_split(self._np, latent, x, y, mask, float(tol), int(max_iterations), deadline=deadline)

    @staticmethod
    def _check_budgets(tol, max_iterations, time_budget) -> None:
        """The tolerance and budgets of :meth:`refine_linear` and :meth:`condition_planner`."""
        if not (math.isfinite(tol) and tol > 0):
            raise ValueError(f"tol = {tol!r}: expected a finite tolerance > 0 (rad)")
        if int(max_iterations) != max_iterations or max_iterations < 0:
            raise ValueError(f"max_iterations = {max_iterations!r}: expected an integer >= 0")
        if time_budget is not None and not (math.isfinite(time_budget) and time_budget > 0):
            raise ValueError(f"time_budget = {time_budget!r}: expected seconds > 0 (or None: no limit)")

    def refine_map(self, latent: LatentGaussian, via_x, via_y, joint_mask=None, prior: str = "posterior",
                   noise_std=None, max_iterations: int = 50, tol: float = 1e-6,
                   latent_bound: float = 5.0) -> RefinementResult:
        """MAP refinement (:func:`deepprompt_ros.primitive.refinement.refine_map`): the latent that
        trades meeting the via-points for staying where the model has seen demonstrations.

        Parameters
        ----------
        latent : LatentGaussian, the initialization (its mean; with several modes of the decoder, moved
            to its most probable mode) and (``prior="posterior"``) the prior
        via_x : array, shape (n,); via_y : array, shape (n, d)
        joint_mask : array of bool, shape (n, d) or (d,), optional; joints to meet (default all)
        prior : {"posterior", "standard"}
            What ``latent`` knows besides the via-points — q_c, the aggregation of its contexts and
            images, recorded by :meth:`condition` (a latent without that record is taken as the
            prior itself; with several modes, what its conditioning gave the most probable mode) — so
            the via-points count once, in the likelihood; or the model's N(0, I).
        noise_std : float or array, shape (d,), optional
            Via-point standard deviation in joint units (default σ_y · each joint's normalization std).
        """
        return refine_map(self, latent, via_x, via_y, joint_mask, prior=prior, noise_std=noise_std,
                          max_iterations=max_iterations, tol=tol, latent_bound=latent_bound)
