"""ProMP's two hyper-parameters chosen by cross-validation on its training demonstrations alone: the
covariance regularizer (``cov_reg_scale`` of :class:`deepprompt_ros.baselines.promp.ProMP`, λ
relative to the demonstrations' weight variance) and the via-point noise (a standard deviation in
normalized joint units: joint j's noise is ``via_noise`` · std_j, std_j the joint's spread over the
training demos as in :func:`deepprompt_ros.training.tensors.fit_normalization` — the units of
DeepProMP's ``via_noise``).

K-fold over the training demonstrations: per fold, a ProMP is fitted to the other folds for every
regularizer of the grid, and each demonstration of the fold is reconstructed from the via-point sets
of :func:`deepprompt_ros.training.basis.cv_via_sets` (start only, start + end, random sets of
``n_via``) with every noise of the grid; the score of a grid point is the held-out whole-trajectory
MSE (:func:`deepprompt_ros.training.basis.cv_score`: the geometric mean over the three
conditionings), and the lowest wins. DeepProMP's linear part is chosen on the same folds and sets
(:func:`deepprompt_ros.training.basis.cv_basis_hyperparameters`), each scored by the mean the server
executes (the via-points met), with the whole trajectory as a fourth conditioning, and ProMP's form
left only where no conditioning gets worse.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from deepprompt_ros.baselines.promp import ProMP
from deepprompt_ros.training.basis import AUTO_COV_REGS, CV_VIA_NOISES, cv_score, cv_via_sets, fold_assignment

__all__ = ["ProMPSelection", "select_promp", "COV_REG_SCALES", "VIA_NOISES", "joint_spread"]

#: Grid of ``cov_reg_scale``: the grid of DeepProMP's linear part (``AUTO_COV_REGS``), from a little
#: (every direction of the weight space keeps some variance: via-points off the demos' span stay
#: reachable) to λ equal to the mean weight variance (few demos, far from spanning the weight space).
COV_REG_SCALES = AUTO_COV_REGS
#: Grid of the via-point noise (normalized joint units), DeepProMP's: from a point met all but exactly
#: to one a tenth of the joint's spread away.
VIA_NOISES = CV_VIA_NOISES


@dataclasses.dataclass(frozen=True)
class ProMPSelection:
    """The chosen ``cov_reg_scale`` and ``via_noise`` with their cross-validation error ``cv_mse``
    (rad², :func:`deepprompt_ros.training.basis.cv_score`), the number of folds and of training demos,
    and the whole grid ``table``: rows (cov_reg_scale, via_noise, cv_mse, then the MSE of each of the
    first three conditionings of :data:`deepprompt_ros.training.basis.CV_CONDITIONINGS`)."""

    cov_reg_scale: float
    via_noise: float
    cv_mse: float
    folds: int
    n_demos: int
    table: tuple[tuple[float, ...], ...]

    def to_json(self) -> dict:
        return {**dataclasses.asdict(self), "table": [list(r) for r in self.table]}


def joint_spread(Y: np.ndarray) -> np.ndarray:
    """(d,) each joint's standard deviation over all samples of the demos Y (N, T, d), at least 1e-3:
    the normalization's ``y_std`` (:func:`deepprompt_ros.training.tensors.fit_normalization`)."""
    return np.maximum(Y.reshape(-1, Y.shape[-1]).std(0), 1e-3)


def select_promp(Y, x, *, n_basis: int = 20, width: float = 1.0, rhythmic: bool = False, ridge: float = 1e-8,
                 cov_reg_scales=COV_REG_SCALES, via_noises=VIA_NOISES, folds: int = 5, n_via: int = 5,
                 draws: int = 2, seed: int = 0) -> ProMPSelection:
    """Choose ProMP's ``cov_reg_scale`` and via-point noise by ``folds``-fold cross-validation (at most
    one fold per demo) on the training demonstrations ``Y`` (N, T, d) at phases ``x`` (T,) — the only
    data it is given. Deterministic in ``seed``; ``ValueError`` for fewer than 3 demos or an empty grid.
    """
    Y = np.asarray(Y, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    if Y.ndim != 3 or x.shape != (Y.shape[1],):
        raise ValueError(f"select_promp needs Y of shape (N, T, d) and x of shape (T,); got {Y.shape} and {x.shape}")
    n, t, d = Y.shape
    if n < 3:
        raise ValueError(f"cross-validation needs >= 3 demonstrations, got {n}")
    scales, noises = tuple(float(s) for s in cov_reg_scales), tuple(float(v) for v in via_noises)
    if not scales or not noises or min(scales) < 0 or min(noises) <= 0:
        raise ValueError(f"the grids must be non-empty, cov_reg_scales >= 0 and via_noises > 0; got {scales} and "
                         f"{noises}")
    k = max(2, min(int(folds), n))
    fold_of = fold_assignment(n, k, seed)
    sets = cv_via_sets(t, n, n_via, draws, seed)
    err = np.zeros((len(scales), len(noises), n, len(sets[0])))
    for f in range(k):
        tr, te = np.flatnonzero(fold_of != f), np.flatnonzero(fold_of == f)
        var = joint_spread(Y[tr]) ** 2
        for a, s in enumerate(scales):
            p = ProMP(d, n_basis, rhythmic=rhythmic, width=width, ridge=ridge, cov_reg_scale=s).fit(Y[tr], x)
            for b, v in enumerate(noises):
                for i in te:
                    for j, sel in enumerate(sets[i]):
                        pred = p.condition(x[sel], Y[i, sel], noise_var=v * v * var).mean_trajectory(x)
                        err[a, b, i, j] = float(((pred - Y[i]) ** 2).mean())
    table = tuple((s, v, *_flat(cv_score(err[a, b]))) for a, s in enumerate(scales) for b, v in enumerate(noises))
    best = min(table, key=lambda r: r[2])
    return ProMPSelection(best[0], best[1], best[2], k, n, table)


def _flat(score: tuple[float, tuple[float, ...]]) -> tuple[float, ...]:
    return (score[0], *score[1])
