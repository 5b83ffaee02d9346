"""A low-dimensional context as a linear Gaussian observation of the linear latent block z_lin.

With a split latent (``latent_linear`` k_l > 0) the trajectory is linear in z_lin ~ N(0, I), and a
context c that varies with the trajectory roughly linearly is modelled as ProMP models it, by the
joint Gaussian of (z_lin, c) (Paraschos et al., "Probabilistic Movement Primitives", NIPS 2013, the
context-augmented weight distribution; here in the latent): with z_lin ~ N(0, I) the joint is

    c = c̄ + B z_lin + ε,   ε ~ N(0, R),   B = Cov(c, z_lin),   R = Cov(c) − B Bᵀ,

B and R estimated from the training demonstrations' z_lin (each demo's posterior mean under the
trained model) and their contexts. A decoder of several modes (``ModelConfig.decoder_modes``) gives
each mode k its own c̄_k (B and R pooled within the modes): a context that tells the modes apart then
weighs the candidates of z_nl, which choose the mode, through their likelihood. Conditioning on c is then exact Gaussian conditioning of z_lin,
done together with the via-points (:func:`deepprompt_ros.primitive.linear_conditioning.condition_split`
appends the rows below to the via-points' rows). The learned context encoder still gives the
context's factor on z_nl. The training keeps this path for a modality only when it reconstructs the
validation demos better than the encoder (:func:`deepprompt_ros.training.selection.choose_context_paths`).

Units: contexts in their raw units; internally standardized by the training contexts' spread.
"""
from __future__ import annotations

import dataclasses
from typing import Mapping

import numpy as np

__all__ = ["LinearContext", "fit_linear_context", "R_FLOOR"]

#: Each eigenvalue of R (standardized context units) is at least this share of the context's variance
#: (1 per standardized dimension): the estimated B Bᵀ can exceed Cov(c) in a direction when the demos'
#: z_lin spread is not exactly I, and a context is never an exact function of the trajectory.
R_FLOOR = 1e-3


@dataclasses.dataclass(frozen=True)
class LinearContext:
    """The linear Gaussian model of the low-dimensional contexts given z_lin (see the module's
    docstring): one joint model of the modalities ``names`` (their vectors concatenated in that order),
    so that contexts which carry information only together (a position and a task switch) condition
    z_lin as ProMP's joint Gaussian does; a request with some of them conditions on their marginal.

    Attributes
    ----------
    names : tuple of str; dims : tuple of int — the modalities and their sizes
    mean, scale : array, shape (C,) — the training contexts' mean at z_lin = 0 and spread (raw units)
    b : array, shape (C, k_l) — B in standardized context units
    r : array, shape (C, C) — R, standardized units (eigenvalues >= :data:`R_FLOOR`)
    mode_means : array, shape (K, C), or None — per mode of the decoder, its mean at z_lin = 0 (raw
        units; ``mean`` is then their average over the training demos)
    """

    names: tuple[str, ...]
    dims: tuple[int, ...]
    mean: np.ndarray
    scale: np.ndarray
    b: np.ndarray
    r: np.ndarray
    mode_means: np.ndarray | None = None

    def rows(self, contexts: Mapping[str, np.ndarray], weights: Mapping[str, np.ndarray] | None = None
             ) -> tuple[np.ndarray, np.ndarray] | None:
        """The whitened observation rows of the modalities of ``contexts`` (name -> (m, c) raw units)
        that this model holds: (G (C', k_l), e (C',)) with e − G z_lin ~ N(0, I), C' their summed sizes
        (e (K, C'), one row per mode, with ``mode_means``); None if it holds none of them. A modality's vectors are averaged with their ``weights`` (default
        1 each); a modality whose weights are all 0 counts as absent."""
        idx, vals = [], []
        start = 0
        for name, dim in zip(self.names, self.dims):
            if name in contexts:
                c = np.atleast_2d(np.asarray(contexts[name], dtype=np.float64))
                w = np.ones(c.shape[0]) if weights is None or weights.get(name) is None else \
                    np.asarray(weights[name], dtype=np.float64)
                if w.sum() > 0:
                    idx.extend(range(start, start + dim))
                    vals.append(w @ c / w.sum())
            start += dim
        if not idx:
            return None
        idx = np.asarray(idx)
        ev, vec = np.linalg.eigh(self.r[np.ix_(idx, idx)])
        whiten = (vec / np.sqrt(np.maximum(ev, R_FLOOR))) @ vec.T
        mean = self.mean[idx] if self.mode_means is None else self.mode_means[:, idx]
        cs = (np.concatenate(vals) - mean) / self.scale[idx]
        return whiten @ self.b[idx], cs @ whiten.T

    def to_json(self) -> dict:
        out = {"names": list(self.names), "dims": list(self.dims), "mean": self.mean.tolist(),
               "scale": self.scale.tolist(), "b": self.b.tolist(), "r": self.r.tolist()}
        if self.mode_means is not None:
            out["mode_means"] = self.mode_means.tolist()
        return out

    @classmethod
    def from_json(cls, d: Mapping) -> "LinearContext":
        try:
            arrs = {k: np.asarray(d[k], dtype=np.float64) for k in ("mean", "scale", "b", "r")}
            names, dims = tuple(str(n) for n in d["names"]), tuple(int(v) for v in d["dims"])
            mode_means = None if d.get("mode_means") is None else np.asarray(d["mode_means"], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"a linear context record needs names, dims, mean, scale, b and r: {exc!r}") from None
        c = sum(dims)
        if (len(names) != len(dims) or not names or min(dims) < 1 or arrs["mean"].shape != (c,)
                or arrs["scale"].shape != (c,) or arrs["b"].ndim != 2 or arrs["b"].shape[0] != c
                or arrs["r"].shape != (c, c) or not all(np.isfinite(a).all() for a in arrs.values())
                or (arrs["scale"] <= 0).any()
                or (mode_means is not None and (mode_means.ndim != 2 or mode_means.shape[0] < 2
                                                or mode_means.shape[1] != c or not np.isfinite(mode_means).all()))):
            raise ValueError(f"linear context {names}: inconsistent or non-finite arrays (dims {dims}, mean "
                             f"{arrs['mean'].shape}, scale {arrs['scale'].shape}, b {arrs['b'].shape}, r "
                             f"{arrs['r'].shape}, mode_means {None if mode_means is None else mode_means.shape}); "
                             "expected mean and scale (C,) with scale > 0, b (C, k_l), r (C, C), mode_means absent or "
                             "(K >= 2, C), C the summed dims")
        return cls(names, dims, arrs["mean"], arrs["scale"], arrs["b"], arrs["r"], mode_means)


def fit_linear_context(contexts: Mapping[str, np.ndarray], scores: np.ndarray, modes: np.ndarray | None = None,
                       n_modes: int = 0) -> LinearContext:
    """The joint model of the modalities of ``contexts`` (name -> (N, c), one vector per training demo,
    raw units; taken in name order) given ``scores`` (N, k_l), the demos' z_lin; with ``modes`` (N,) the
    mode of each demo (0 … ``n_modes`` − 1, a decoder of several modes) a mean per mode, B and R from the
    deviations from the modes' means (a mode without a demo takes the overall mean). ``ValueError`` for
    fewer than 3 demos, no modality or mismatching shapes."""
    z = np.asarray(scores, dtype=np.float64)
    names = tuple(sorted(contexts))
    cols = [np.asarray(contexts[n], dtype=np.float64) for n in names]
    if (not names or z.ndim != 2 or z.shape[0] < 3
            or any(c.ndim != 2 or c.shape[0] != z.shape[0] for c in cols)):
        raise ValueError(f"fit_linear_context needs scores (N, k_l) of N >= 3 demos and contexts (N, c) each; got "
                         f"{z.shape} and {[c.shape for c in cols]}")
    c = np.concatenate(cols, 1)
    mean, scale = c.mean(0), np.maximum(c.std(0), 1e-9)
    cs = (c - mean) / scale
    n = z.shape[0]
    groups = [np.ones(n, dtype=bool)] if modes is None else [np.asarray(modes) == k for k in range(n_modes)]
    if modes is not None and (len(groups) < 2 or np.shape(modes) != (n,)):
        raise ValueError(f"fit_linear_context: modes must be one label in 0 … n_modes - 1 per demo with n_modes >= 2; "
                         f"got modes of shape {np.shape(modes)} and n_modes {n_modes}")
    # deviations from each mode's (or the demos') means; a mode without a demo has none
    c_mean = np.stack([cs[g].mean(0) if g.any() else np.zeros(cs.shape[1]) for g in groups])
    z_mean = np.stack([z[g].mean(0) if g.any() else z.mean(0) for g in groups])
    lab = np.zeros(n, dtype=int) if modes is None else np.asarray(modes)
    cd, zc = cs - c_mean[lab], z - z_mean[lab]
    dof = max(n - sum(int(g.any()) for g in groups), 1)
    b = cd.T @ zc / dof  # (C, k_l) = Cov(c, z) (within the modes)
    r = cd.T @ cd / dof - b @ b.T
    ev, vec = np.linalg.eigh((r + r.T) / 2)
    r = (vec * np.maximum(ev, R_FLOOR)) @ vec.T
    # c̄ + B (z − z̄) = (c̄ − B z̄) + B z: the mean of c at z_lin = 0, in raw units (per mode)
    at_zero = mean + scale * (c_mean - z_mean @ b.T)  # (groups, C)
    dims = tuple(x.shape[1] for x in cols)
    if modes is None:
        return LinearContext(names, dims, at_zero[0], scale, b, r)
    return LinearContext(names, dims, at_zero[lab].mean(0), scale, b, r, at_zero)
