"""The model selection of ``TrainConfig.auto_select``, made from the training demonstrations alone:

1. :func:`select_linear_part` — the linear part Φ(x)(b + A z_lin) of the decoder (n_b, k_l, the PPCA
   regularizer and its units) and the model's own via-point noise, together, by cross-validation on the
   demos the network is trained on, each scored by the mean the server executes for a planner (the
   posterior mean at that noise moved onto the via-points by the smallest change of the trajectory;
   every phase as via-points: the least-squares fit at the planner's noise;
   :func:`deepprompt_ros.training.basis.cv_basis_hyperparameters` with ``meet`` and ``whole_noise``),
   and the modes of the demos' basis weights in that basis (``linear_modes``,
   :func:`deepprompt_ros.training.basis.weight_modes`), where the same cross-validation finds the
   executed means of a mixture of them no worse than one Gaussian's
   (:func:`deepprompt_ros.training.basis.cv_modes`): with K > 1 modes the PPCA is taken within the
   modes and the decoder holds the offsets between them (``ModelConfig.decoder_modes``);
2. :func:`judge_residual` — after training, the MLP residual kept or dropped (``residual_scale`` 0)
   by comparing the model with and without it on the validation demos of the training split (or,
   with ``residual_folds``, on the held-out demos of a cross-validation of the whole training):
   the energy score (:func:`energy_score`, a strictly proper scoring rule) of samples of the
   distribution the primitive's own conditioning path gives
   (:meth:`deepprompt_ros.primitive.deep_promp.DeepProMP.condition` and ``sample``), with the
   one-standard-error rule (:func:`keep_residual`); with K > 1 modes, :func:`compare_modes` — the
   modes served only where they beat the training of one mode by the same rule;
3. :func:`choose_context_paths` — per low-dimensional context modality, conditioning z_lin on it
   through its linear Gaussian model (ProMP's joint Gaussian of trajectory and context, in the latent)
   or through the learned encoder alone, by the validation demos' reconstruction from the context.

Held-out (test) demonstrations are never passed to either.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.model.checkpoint import Normalization
from deepprompt_ros.model.network import DeepProMPNet
from deepprompt_ros.model.phase import phase_basis
from deepprompt_ros.primitive.deep_promp import DeepProMP
from deepprompt_ros.primitive.latent import PLANNER_VIA_NOISE
from deepprompt_ros.primitive.linear_context import fit_linear_context
from deepprompt_ros.training.basis import (CV_VIA_NOISES, MODE_NOISES, basis_weights, cv_basis_hyperparameters,
                                          cv_modes, fold_assignment, weight_modes)
from deepprompt_ros.training.config import TrainConfig
from deepprompt_ros.training.tensors import fit_normalization, to_tensors

__all__ = ["select_linear_part", "nonlinear_dims", "judge_residual", "choose_mode_noise", "compare_modes",
           "choose_context_paths", "with_via_noise",
           "energy_score", "keep_residual", "without_residual",
           "FALLBACK_LINEAR_PART", "RESIDUAL_VIA_POINTS", "RESIDUAL_DRAWS", "RESIDUAL_SAMPLES"]

#: The linear part used when the training split has fewer than 3 demonstrations (nothing to
#: cross-validate): 20 basis functions per joint (fewer on a short grid), the whole weight space as
#: linear latent (a ProMP) and ProMP's default regularizer in rad.
FALLBACK_LINEAR_PART = {"decoder_basis": 20, "basis_cov_reg": 0.05, "basis_cov_reg_units": "raw", "via_noise": 1e-3}
#: The residual's validation: ``RESIDUAL_DRAWS`` sets of ``RESIDUAL_VIA_POINTS`` random via-points per demo,
#: each conditioning scored on ``RESIDUAL_SAMPLES`` samples.
RESIDUAL_VIA_POINTS = 5
RESIDUAL_DRAWS = 4
RESIDUAL_SAMPLES = 32
_CHOSEN = ("decoder_basis", "latent_linear", "basis_cov_reg", "basis_cov_reg_units", "via_noise")


def select_linear_part(train_ds: DemoDataset, cfg: TrainConfig, n_joints: int) -> tuple[TrainConfig, dict]:
    """The configuration ``cfg`` with the linear part chosen on ``train_ds`` (``cfg.cv_folds``-fold
    cross-validation, seed ``cfg.seed``; :data:`FALLBACK_LINEAR_PART` below 3 demos), the linear part
    initialized as the PPCA and kept fixed (``basis_init`` pca, ``basis_lr_scale`` 0), ``linear_modes``
    K the modes of the training demos' basis weights (normalized units, the chosen basis;
    :func:`~deepprompt_ros.training.basis.weight_modes`, seed ``cfg.seed``; 1 below 3 demos) where the
    same cross-validation admits their executed means (:func:`~deepprompt_ros.training.basis.cv_modes`),
    else 1, and
    ``latent_dim`` = ``latent_linear`` + :func:`nonlinear_dims`. Returns (that configuration, the record
    of the choice: the values, the cross-validation's result or the reason for the fallback, and the
    modes' criterion)."""
    if len(train_ds) >= 3:
        cv = cv_basis_hyperparameters(train_ds, cfg.n_points, basis_width=cfg.basis_width, folds=cfg.cv_folds,
                                      meet=True, whole_noise=PLANNER_VIA_NOISE, seed=cfg.seed)
        choice = {k: cv[k] for k in _CHOSEN}
        # the weights the training's PCA initialization will see (training.basis.init_basis_pca)
        data = to_tensors(train_ds, fit_normalization(train_ds, cfg.n_points), cfg.n_points)
        phi = phase_basis(data.x.double(), cv["decoder_basis"], cfg.basis_width,
                          train_ds.phase_type == "rhythmic").numpy()
        modes = weight_modes(basis_weights(phi, data.y.double().numpy()), cfg.seed)
        mode_record = dict(modes.record)
        if modes.n_modes > 1:  # the modes' means, cross-validated against one Gaussian's
            mode_record["cross_validation"] = cv_modes(train_ds, cfg.n_points, cv, modes.n_modes, cfg.basis_width,
                                                       folds=cfg.cv_folds, seed=cfg.seed)
        admitted = modes.n_modes > 1 and mode_record["cross_validation"]["admitted"]
        choice["linear_modes"] = modes.n_modes if admitted else 1
        record = {"method": f"{cv['folds']}-fold cross-validation on the {cv['n_demos']} training demonstrations",
                  "cross_validation": cv, "modes": mode_record}
    else:
        nb = min(FALLBACK_LINEAR_PART["decoder_basis"], max(2, cfg.n_points // 2))
        choice = {**FALLBACK_LINEAR_PART, "decoder_basis": nb, "latent_linear": nb * n_joints, "linear_modes": 1}
        record = {"method": f"fallback: {len(train_ds)} training demonstrations are too few to cross-validate"}
    out = dataclasses.replace(cfg, **choice, basis_init="pca", basis_lr_scale=0.0,
                              latent_dim=choice["latent_linear"] + nonlinear_dims(cfg, choice["linear_modes"]))
    return out, {**record, **choice, "latent_dim": out.latent_dim}


def nonlinear_dims(cfg: TrainConfig, n_modes: int) -> int:
    """The dimensions of the latent block z_nl: ``cfg.latent_nonlinear``, which the MLP reads; with
    K > 1 modes the first of them also chooses the mode (``ModelConfig.decoder_modes``)."""
    del n_modes  # the same block for every number of modes
    return cfg.latent_nonlinear


def judge_residual(net: DeepProMPNet, norm: Normalization, joint_names, val_ds: DemoDataset, cfg: TrainConfig,
                   train_ds: DemoDataset | None = None,
                   refit: Callable[[DemoDataset], tuple[DeepProMPNet, Normalization]] | None = None
                   ) -> tuple[DeepProMPNet, dict]:
    """Keep or drop the trained MLP residual of ``net`` by the energy score (:func:`energy_score`) of
    the conditioned distribution's samples with and without it (``residual_scale`` 0), on

    - the validation demos ``val_ds`` by ``net`` (``cfg.residual_folds`` 0), or
    - the held-out demos of a ``cfg.residual_folds``-fold cross-validation on ``train_ds``, by the
      networks ``refit`` trains on the other folds exactly as ``net`` was (its linear part as chosen);
      the demos that judge the residual are then never those that chose its checkpoint.

    The score is that of :data:`RESIDUAL_SAMPLES` samples of the whole trajectory (``cfg.n_points``
    phases, each joint divided by its normalization std) drawn by
    :meth:`~deepprompt_ros.primitive.deep_promp.DeepProMP.sample` from the latent
    :meth:`~deepprompt_ros.primitive.deep_promp.DeepProMP.condition` returns, against the demo. A
    strictly proper score of samples sees what an error of the conditioned mean cannot: a residual
    that holds several modes (the mean of two modes is closer to either than a confident wrong
    one) and one that moves the samples away from the demos. Conditionings: the start point alone,
    ``RESIDUAL_DRAWS`` sets of ``RESIDUAL_VIA_POINTS`` random via-points (seeded, averaged into one)
    and — when the data has them — the start point with every context and the images. Each
    conditioning's scores are divided by its mean score without the residual (so each weighs the
    same), and :func:`keep_residual` decides on the per-demo mean of those relative differences. A
    residual the score keeps is still dropped when the executed mean at the random via-point sets
    is worse with it by more than one standard error (per-demo MSE differences relative to the
    mean MSE without it): a sample score can prefer a wider spread while the trajectory the
    robot executes gets worse.

    Returns (the network to keep: ``net``, or a copy with ``residual_scale`` 0; the record of the
    decision: kept, the score that decided, the mean relative difference and its standard error,
    the energy scores per conditioning and, for information, the conditioned means' MSEs (rad²))."""
    if not net.cfg.decoder_basis or net.cfg.residual_scale == 0:
        return net, {"kept": False, "reason": "no residual to judge (residual_scale 0 or no linear basis)"}
    folds = cfg.residual_folds
    extras = bool(val_ds.context_dims) or val_ds.image_shape is not None
    if folds >= 2:
        if train_ds is None or refit is None:
            raise ValueError("residual_folds >= 2 needs the training demos and a refit function")
        if not 2 <= folds <= len(train_ds) // 2:
            raise ValueError(f"residual_folds = {folds}: expected 2 <= residual_folds <= {len(train_ds) // 2} for "
                             f"{len(train_ds)} training demonstrations (or 0: judge on the validation demos)")
        fold_of = fold_assignment(len(train_ds), folds, cfg.seed)
        parts = []
        for k in range(folds):
            held = DemoDataset(tuple(d for d, f in zip(train_ds.demos, fold_of) if f == k), f"{train_ds.source}:held{k}")
            fit_on = DemoDataset(tuple(d for d, f in zip(train_ds.demos, fold_of) if f != k), f"{train_ds.source}:fold{k}")
            parts.append(_residual_scores(*refit(fit_on), joint_names, held, cfg, extras))
        es, mse = (np.concatenate([p[m] for p in parts], 2) for m in (0, 1))
        judged = f"held-out demos of a {folds}-fold cross-validation on the training demos"
    else:
        es, mse = _residual_scores(net, norm, joint_names, val_ds, cfg, extras)
        judged = "validation demos"
    keep, diff, se, via_diff, via_se, mean_ok = _prefer_first(es, mse)
    labels = ["start", f"{RESIDUAL_VIA_POINTS} via-points"] + (["start + contexts"] if extras else [])
    record = {"kept": keep, "score": f"energy score of {RESIDUAL_SAMPLES} samples (whole trajectory, "
                                     "normalized joint units)",
              "relative_difference": diff, "standard_error": se, "n_val": int(es.shape[2]), "judged_on": judged,
              "via_mean_relative_difference": via_diff, "via_mean_standard_error": via_se,
              "via_mean_ok": bool(mean_ok),
              "energy_score_with": dict(zip(labels, es[0].mean(1).tolist())),
              "energy_score_without": dict(zip(labels, es[1].mean(1).tolist())),
              "mse_with": dict(zip(labels, mse[0].mean(1).tolist())),
              "mse_without": dict(zip(labels, mse[1].mean(1).tolist()))}
    if record["kept"]:
        return net, record
    return without_residual(net), record


def _relative_mse(mse: np.ndarray, c: int) -> tuple[float, float]:
    """Conditioning ``c``'s per-demo MSE differences of the first model from the second (:func:`_pair_scores`)
    relative to the second's mean: (mean, standard error)."""
    rel = (mse[0, c] - mse[1, c]) / max(float(mse[1, c].mean()), 1e-300)
    return float(rel.mean()), float(rel.std(ddof=1) / np.sqrt(rel.size)) if rel.size >= 2 else 0.0


def _prefer_first(es: np.ndarray, mse: np.ndarray, every_mean: bool = False
                  ) -> tuple[bool, float, float, float, float, bool]:
    """The rule of :func:`judge_residual` between two models from their scores (:func:`_pair_scores`:
    index 0 the richer model, 1 the simpler): each conditioning's energy scores divided by the simpler
    model's mean, :func:`keep_residual` on them, and the executed mean at the random via-point sets not
    worse by more than one standard error (per-demo MSE differences relative to the simpler model's mean).
    With ``every_mean`` (the modes against one Gaussian, :func:`compare_modes`) two standard errors for both:
    the energy scores lower by more than two, and the mean at every conditioning not worse by more than two
    (several tests at once: about 7 % false alarms over three where one standard error each would give
    about 40 %). Returns (prefer the first, mean relative difference,
    its standard error, the via-point means' relative difference, its standard error, whether the means
    pass)."""
    scale = np.maximum(es[1].mean(1, keepdims=True), 1e-300)
    better, diff, se = keep_residual(es[0] / scale, es[1] / scale)
    via_diff, via_se = _relative_mse(mse, 1)
    if every_mean:
        better = diff + 2.0 * se < 0.0
        mean_ok = all(d - 2.0 * e <= 0.0 for d, e in (_relative_mse(mse, c) for c in range(mse.shape[1])))
    else:
        mean_ok = via_diff - via_se <= 0.0
    return better and mean_ok, diff, se, via_diff, via_se, mean_ok


def energy_score(samples: np.ndarray, y: np.ndarray) -> float:
    """The energy score ES(P, y) = E‖X − y‖ − ½ E‖X − X′‖ of a distribution P given by samples, X, X′
    independent draws of P (Gneiting & Raftery, "Strictly proper scoring rules, prediction, and
    estimation", JASA 102(477), 2007, Eq. 22 with β = 1): strictly proper, lower is better, in the
    units of y. The second expectation is estimated without the pairs of a sample with itself
    (unbiased for K >= 2 samples).

    samples : array, shape (K, ...); y : array, the shape of one sample."""
    s = np.asarray(samples, dtype=np.float64).reshape(len(samples), -1)
    k = s.shape[0]
    if k < 2:
        raise ValueError(f"energy_score needs >= 2 samples, got {k}")
    to_y = np.linalg.norm(s - np.asarray(y, dtype=np.float64).reshape(-1), axis=1).mean()
    gram = s @ s.T
    sq = np.diag(gram)
    pair = np.sqrt(np.maximum(sq[:, None] + sq[None, :] - 2.0 * gram, 0.0))
    return float(to_y - pair.sum() / (2.0 * k * (k - 1)))


def _residual_scores(net: DeepProMPNet, norm: Normalization, joint_names, demos: DemoDataset, cfg: TrainConfig,
                     extras: bool) -> tuple[np.ndarray, np.ndarray]:
    """(energy scores, MSEs): each (2 = with / without the residual, conditionings, n_demos), of
    ``demos`` conditioned as in :func:`judge_residual`. The energy score is per phase and joint scale
    (the norm of a whole trajectory in normalized units divided by sqrt(T d)); both models draw their
    samples with the same seeds."""
    on = DeepProMP(net, norm, joint_names)
    return _pair_scores(on, on.with_residual_scale(0.0), demos, cfg, extras)


def _pair_scores(on: DeepProMP, off: DeepProMP | None, demos: DemoDataset, cfg: TrainConfig,
                 extras: bool, samples: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_residual_scores` of two primitives ``on`` and ``off`` (index 0 and 1), in the units of
    ``on``'s normalization; ``off`` None scores ``on`` alone (index 0; index 1 stays 0), ``samples``
    False the means alone (the energy scores stay 0)."""
    norm = on.norm
    x = np.linspace(0.0, 1.0, cfg.n_points)
    std = np.asarray(norm.y_std, dtype=np.float64)
    root = np.sqrt(cfg.n_points * len(std))
    n_sets = 1 + RESIDUAL_DRAWS + int(extras)
    es, mse = np.zeros((2, n_sets, len(demos))), np.zeros((2, n_sets, len(demos)))
    n_via = min(RESIDUAL_VIA_POINTS, cfg.n_points)
    for i, demo in enumerate(demos.demos):
        y = demo.resampled(cfg.n_points)
        sets = [np.array([0])] + [np.sort(np.random.default_rng([cfg.seed, 7, i, r]).choice(cfg.n_points, n_via,
                                                                                           replace=False))
                                  for r in range(RESIDUAL_DRAWS)]
        conds = [dict(via_x=x[sel], via_y=y[sel]) for sel in sets]
        if extras:
            conds.append(dict(via_x=x[:1], via_y=y[:1], contexts=demo.contexts or None, images=demo.images))
        for m, prim in enumerate((on, off) if off is not None else (on,)):
            for c, kw in enumerate(conds):
                lat = prim.condition(**kw)
                mse[m, c, i] = float(((prim.mean_trajectory(lat, x) - y) ** 2).mean())
                if samples:
                    s = prim.sample(lat, x, RESIDUAL_SAMPLES, np.random.default_rng([cfg.seed, 11, i, c]))
                    es[m, c, i] = energy_score(s / std, y / std) / root
    # the random via-point sets count as one conditioning: their mean
    per = lambda e: np.concatenate([e[:, :1], e[:, 1:1 + RESIDUAL_DRAWS].mean(1, keepdims=True),  # noqa: E731
                                    e[:, 1 + RESIDUAL_DRAWS:]], 1)
    return per(es), per(mse)


def compare_modes(several: tuple[DeepProMPNet, Normalization], one: tuple[DeepProMPNet, Normalization], joint_names,
                  val_ds: DemoDataset, cfg: TrainConfig, several_context: dict | None = None,
                  one_context: dict | None = None) -> tuple[bool, dict]:
    """After a training of K > 1 modes (which the decoder holds): keep it over the training of one mode
    (``linear_modes`` 1, its residual judged) only when the validation demos' conditioned samples have a
    lower energy score by more than two standard errors (modes change the executed mean of every
    conditioning, and the evidence they are worth it must be strong: demonstrations spread over a continuum
    also split into modes of the basis weights, whose executed means are then worse) and the
    executed mean is worse by more than two standard errors at no conditioning (the start, the random
    via-point sets, the start with the contexts; :func:`_prefer_first`): the
    modes' mean weighs them by their posterior probabilities, which where the inputs cannot tell them apart
    is only as good as a single Gaussian's mean, and the samples of spurious modes are no better. ``several_context``,
    ``one_context``: each model's record of :func:`choose_context_paths` (its path of the low-dimensional
    contexts), None for the encoders. Returns (keep the modes, the record)."""
    extras = bool(val_ds.context_dims) or val_ds.image_shape is not None

    def primitive(fitted, context):
        return DeepProMP(*fitted, joint_names, metadata={"selection": {"context": context}} if context else None)
    es, mse = _pair_scores(primitive(several, several_context), primitive(one, one_context), val_ds, cfg, extras)
    keep, diff, se, via_diff, via_se, means_ok = _prefer_first(es, mse, every_mean=True)
    return keep, {"kept_modes": bool(keep), "judged_on": "validation demos", "relative_difference": diff,
                  "standard_error": se, "via_mean_relative_difference": via_diff, "via_mean_standard_error": via_se,
                  "means_not_worse": bool(means_ok),
                  "means_relative_difference_and_standard_error": [list(_relative_mse(mse, c))
                                                                   for c in range(mse.shape[1])],
                  "mse_modes": mse[0].mean(1).tolist(),
                  "mse_one_mode": mse[1].mean(1).tolist()}


def choose_mode_noise(net: DeepProMPNet, norm: Normalization, joint_names, val_ds: DemoDataset,
                      cfg: TrainConfig) -> tuple[DeepProMPNet, dict]:
    """With K > 1 modes, before :func:`compare_modes`: the via-point noises of the model of the modes, whose
    linear part — the PPCA within the modes — is not the one :func:`select_linear_part` cross-validated the
    noise for. ``ModelConfig.via_noise``: among :data:`~deepprompt_ros.training.basis.CV_VIA_NOISES`, the one
    whose means at the random via-point sets of :func:`judge_residual` have the lowest MSE on the validation
    demos. ``ModelConfig.mode_noise``, the noise of the modes' posterior probabilities: among
    :data:`MODE_NOISES` from that via_noise up, the one whose means from the start point and at the random
    via-point sets have the lowest sum of the two MSEs, each relative to its value at via_noise (the first of
    equal sums). Where the modes meet, their offsets differ by their estimation error alone, and a via-point
    there weighs them by that difference at a small noise. Returns (a copy of ``net`` with both, the
    record)."""
    mse = {}
    for noise in CV_VIA_NOISES:
        prim = DeepProMP(with_via_noise(net, noise), norm, joint_names)
        mse[noise] = float(_pair_scores(prim, None, val_ds, cfg, False, samples=False)[1][0, 1].mean())
    best = min(mse, key=lambda v: mse[v])
    per_demo, base = {}, None
    for noise in (v for v in MODE_NOISES if v >= best):
        prim = DeepProMP(with_via_noise(net, best, noise), norm, joint_names)
        m = _pair_scores(prim, None, val_ds, cfg, False, samples=False)[1][0]  # (start, random sets) x demos
        base = m.mean(1, keepdims=True) if base is None else base
        per_demo[noise] = (m / np.maximum(base, 1e-300)).sum(0)
    mode_noise = min(per_demo, key=lambda v: per_demo[v].mean())
    return with_via_noise(net, best, mode_noise), {
        "via_noise": best, "mode_noise": mode_noise, "judged_on": "validation demos",
        "mse_random_via_points": {f"{k:g}": v for k, v in mse.items()},
        "mode_noise_relative_mse_start_plus_random": {f"{k:g}": float(v.mean()) for k, v in per_demo.items()},
        "mode_noise_rule": "the lowest sum of the start's and the random via-point sets' MSE, each relative to "
                           "its value at via_noise"}


def with_via_noise(net: DeepProMPNet, noise: float, mode_noise: float | None = None) -> DeepProMPNet:
    """A copy of ``net`` whose conditioning's via-point noise (``ModelConfig.via_noise``) is ``noise`` (and
    ``ModelConfig.mode_noise`` ``mode_noise`` when given)."""
    changes = {"via_noise": float(noise)} if mode_noise is None else {"via_noise": float(noise),
                                                                       "mode_noise": float(mode_noise)}
    out = DeepProMPNet(dataclasses.replace(net.cfg, **changes))
    out.load_state_dict(net.state_dict())
    return out.eval()


def without_residual(net: DeepProMPNet) -> DeepProMPNet:
    """A copy of ``net`` whose residual scale is 0 (its decoder is the linear part alone)."""
    out = DeepProMPNet(dataclasses.replace(net.cfg, residual_scale=0.0))
    out.load_state_dict(net.state_dict())
    return out.eval()


def keep_residual(with_residual: np.ndarray, without: np.ndarray) -> tuple[bool, float, float]:
    """The one-standard-error rule (Hastie, Tibshirani & Friedman, *The Elements of Statistical
    Learning*, 2nd ed., §7.10): keep the MLP residual only if its validation error is lower than the
    simpler model's (residual off) by more than one standard error of the difference.

    ``with_residual``, ``without`` : (sets, n_demos) validation errors of the same conditionings. The
    standard error is over demos (their mean over the sets; the sets of one demo are not independent),
    over the sets when there is a single demo. Returns (keep, mean difference, its standard error)."""
    a = np.atleast_2d(np.asarray(with_residual, dtype=np.float64))
    b = np.atleast_2d(np.asarray(without, dtype=np.float64))
    if a.shape != b.shape or a.size == 0:
        raise ValueError(f"keep_residual needs two equal, non-empty (sets, demos) arrays, got {a.shape} and {b.shape}")
    diff = (a - b).mean(0) if a.shape[1] >= 2 else (a - b)[:, 0]
    if diff.size < 2:
        return False, float(diff.mean()), float("inf")
    se = float(diff.std(ddof=1) / np.sqrt(diff.size))
    return bool(diff.mean() + se < 0.0), float(diff.mean()), se


def choose_context_paths(net: DeepProMPNet, norm: Normalization, joint_names, cfg: TrainConfig,
                         train_ds: DemoDataset, val_ds: DemoDataset) -> dict:
    """``auto_select`` after the residual's judgement: whether the primitive conditions z_lin on the
    low-dimensional contexts through their joint linear Gaussian model
    (:mod:`deepprompt_ros.primitive.linear_context`, fitted on the training demos' z_lin — each demo's
    posterior mean under the trained model given all its points — and their contexts) or through the
    learned encoders alone, and with the linear model and images whether the images' encodings still
    inform z_lin. The candidates are scored on the validation demos reconstructed from their first point
    and every context (``low_dim``, the server's default path) and, with images, from those and the
    images (``image+low``): per demo, the mean over those conditionings of the MSE relative to the
    encoders' mean. The linear model (the best of its candidates) is the default — ProMP's joint Gaussian
    of trajectory and context, in the latent —; the encoders replace it only when their mean is lower by
    more than one standard error of the paired per-demo difference (the rule of :func:`keep_residual`).

    Returns the record ``selection["context"]``: ``linear`` (the model's JSON when kept, else None) and
    ``images_inform_z_lin`` — what :class:`~deepprompt_ros.primitive.deep_promp.DeepProMP` reads —,
    ``validation`` {candidate: {conditioning: MSE rad²}} and ``method``; without a linear block, low-dim
    contexts, 3 training demos or a validation demo, ``linear`` is None and ``reason`` says why."""
    names = sorted(train_ds.context_dims)
    if not cfg.latent_linear or not names or len(train_ds) < 3 or not len(val_ds):
        why = ("no linear latent block" if not cfg.latent_linear else "no low-dimensional context" if not names
               else "fewer than 3 training or no validation demonstrations")
        return {"linear": None, "reason": why}
    base = DeepProMP(net, norm, joint_names, name="selection")
    x = np.linspace(0.0, 1.0, cfg.n_points)
    # each demo's z_lin given all its points (with several modes: of the candidate, and so the mode, of the
    # largest weight, not the modes' weighted mean the robot executes)
    k_l, k_m = cfg.latent_linear, net.cfg.decoder_modes

    def top_candidate(lat):
        return lat.mean if lat.linear is None else lat.linear.candidates[int(np.argmax(lat.linear.weights))]
    latents = np.stack([top_candidate(base.condition(x, d.resampled(cfg.n_points), n_candidates=32 if k_m else 0))
                        for d in train_ds.demos])
    labels = base.mode_of(latents) if k_m else None
    model = fit_linear_context({n: np.stack([d.contexts[n].mean(0) for d in train_ds.demos]) for n in names},
                               latents[:, :k_l], labels, k_m)
    images = val_ds.image_shape is not None and net.cfg.image_shape is not None
    conds = ("low_dim", "image+low") if images else ("low_dim",)
    candidates = {"encoders": {"linear": None}, "linear model": {"linear": model.to_json()}}
    if images:
        candidates["linear model"]["images_inform_z_lin"] = True
        candidates["linear model, images on z_nl"] = {"linear": model.to_json(), "images_inform_z_lin": False}

    def val_mse(record) -> np.ndarray:
        """(conditionings, validation demos) MSE, rad²."""
        prim = DeepProMP(net, norm, joint_names, name="selection", metadata={"selection": {"context": record}})
        out = np.zeros((len(conds), len(val_ds)))
        for j, c in enumerate(conds):
            for i, d in enumerate(val_ds.demos):
                y = d.resampled(cfg.n_points)
                lat = prim.condition_planner(x[:1], y[:1], contexts=dict(d.contexts),
                                             images=d.images if c == "image+low" else None).latent
                out[j, i] = float(((prim.decode_mean(lat, x) - y) ** 2).mean())
        return out

    per_demo = {k: val_mse(rec) for k, rec in candidates.items()}
    scale = np.maximum(per_demo["encoders"].mean(1, keepdims=True), 1e-300)
    rel_demo = {k: (v / scale).mean(0) for k, v in per_demo.items()}  # (val demos,) relative to the encoders' mean
    rel = {k: float(v.mean()) for k, v in rel_demo.items()}
    best_linear = min((k for k in rel if k != "encoders"), key=lambda k: rel[k])
    # the contexts' linear model (ProMP's joint Gaussian of trajectory and context, in the latent) unless the
    # encoders reconstruct the validation demos better by more than one standard error of the paired difference
    better, diff, se = keep_residual(rel_demo["encoders"][None], rel_demo[best_linear][None])
    best = "encoders" if better else best_linear
    table = {k: {c: float(v[j].mean()) for j, c in enumerate(conds)} for k, v in per_demo.items()}
    return {**candidates[best], "chosen": best, "validation": table, "relative": rel,
            "encoders_vs_linear": {"difference": diff, "standard_error": se},
            "method": f"joint linear Gaussian model of the contexts {list(names)} on z_lin of the {len(train_ds)} "
                      f"training demonstrations against the encoders: per-demo MSE relative to the encoders' mean "
                      f"over {' and '.join(conds)} of the {len(val_ds)} validation demonstrations; the best linear "
                      f"candidate unless the encoders' is lower by more than one standard error of the paired "
                      f"difference"}
