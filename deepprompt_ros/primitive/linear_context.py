"""A low-dimensional context as a linear Gaussian observation of the linear latent block z_lin.

With a split latent (``latent_linear`` k_l > 0) the trajectory is linear in z_lin ~ N(0, I), and a
context c that varies with the trajectory roughly linearly is modelled as ProMP models it, by the
joint Gaussian of (z_lin, c) (Paraschos et al., "Probabilistic Movement Primitives", NIPS 2013, the
context-augmented weight distribution; here in the latent): with z_lin ~ N(0, I) the joint is

    c = c̄ + B z_lin + ε,   ε ~ N(0, R),   B = Cov(c, z_lin),   R = Cov(c) − B Bᵀ,

B and R estimated from the training demonstrations' z_lin (each demo's posterior mean under the
trained model) and their contexts. Conditioning on c is then exact Gaussian conditioning of z_lin,
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
    """

    names: tuple[str, ...]
    dims: tuple[int, ...]
    mean: np.ndarray
    scale: np.ndarray
    b: np.ndarray
    r: np.ndarray

    def rows(self, contexts: Mapping[str, np.ndarray], weights: Mapping[str, np.ndarray] | None = None
             ) -> tuple[np.ndarray, np.ndarray] | None:
        """The whitened observation rows of the modalities of ``contexts`` (name -> (m, c) raw units)
        that this model holds: (G (C', k_l), e (C',)) with e − G z_lin ~ N(0, I), C' their summed sizes;
        None if it holds none of them. A modality's vectors are averaged with their ``weights`` (default
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
        cs = (np.concatenate(vals) - self.mean[idx]) / self.scale[idx]
        return whiten @ self.b[idx], whiten @ cs

    def to_json(self) -> dict:
        return {"names": list(self.names), "dims": list(self.dims), "mean": self.mean.tolist(),
                "scale": self.scale.tolist(), "b": self.b.tolist(), "r": self.r.tolist()}

    @classmethod
    def from_json(cls, d: Mapping) -> "LinearContext":
        try:
            arrs = {k: np.asarray(d[k], dtype=np.float64) for k in ("mean", "scale", "b", "r")}
            names, dims = tuple(str(n) for n in d["names"]), tuple(int(v) for v in d["dims"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"a linear context record needs names, dims, mean, scale, b and r: {exc!r}") from None
        c = sum(dims)
        if (len(names) != len(dims) or not names or min(dims) < 1 or arrs["mean"].shape != (c,)
                or arrs["scale"].shape != (c,) or arrs["b"].ndim != 2 or arrs["b"].shape[0] != c
                or arrs["r"].shape != (c, c) or not all(np.isfinite(a).all() for a in arrs.values())
                or (arrs["scale"] <= 0).any()):
            raise ValueError(f"linear context {names}: inconsistent or non-finite arrays (dims {dims}, mean "
                             f"{arrs['mean'].shape}, scale {arrs['scale'].shape}, b {arrs['b'].shape}, r "
                             f"{arrs['r'].shape}); expected mean and scale (C,) with scale > 0, b (C, k_l), r (C, C), "
                             "C the summed dims")
        return cls(names, dims, arrs["mean"], arrs["scale"], arrs["b"], arrs["r"])


def fit_linear_context(contexts: Mapping[str, np.ndarray], scores: np.ndarray) -> LinearContext:
    """The joint model of the modalities of ``contexts`` (name -> (N, c), one vector per training demo,
    raw units; taken in name order) given ``scores`` (N, k_l), the demos' z_lin. ``ValueError`` for
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
    zc = z - z.mean(0)
    n = z.shape[0]
    b = cs.T @ zc / (n - 1)  # (C, k_l) = Cov(c, z)
    r = cs.T @ cs / (n - 1) - b @ b.T
    ev, vec = np.linalg.eigh((r + r.T) / 2)
    r = (vec * np.maximum(ev, R_FLOOR)) @ vec.T
    # c̄ + B (z − z̄) = (c̄ − B z̄) + B z: the mean of c at z_lin = 0, in raw units
    return LinearContext(names, tuple(x.shape[1] for x in cols), mean - scale * (b @ z.mean(0)), scale, b, r)
