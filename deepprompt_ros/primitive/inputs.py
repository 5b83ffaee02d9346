"""Validation of what users pass to a primitive (phases, images, importance weights), shared by
:class:`deepprompt_ros.primitive.deep_promp.DeepProMP` and the baselines' common interface. Every
check raises ``ValueError`` saying what is expected."""
from __future__ import annotations

import numpy as np

__all__ = ["check_phases", "check_images", "check_weights"]


def check_images(images, image_shape: tuple[int, int]) -> np.ndarray:
    """Validate the images of one scene: uint8 RGB, shape (n, H, W, 3) or (H, W, 3) → (n, H, W, 3)."""
    im = np.asarray(images)
    h, w = image_shape
    if im.ndim == 3:
        im = im[None]
    if im.ndim != 4 or im.shape[1:] != (h, w, 3) or im.dtype != np.uint8 or im.shape[0] < 1:
        raise ValueError(f"images must be uint8 RGB with shape (n, {h}, {w}, 3), got dtype {im.dtype}, "
                         f"shape {im.shape}")
    return im


def check_phases(x, what: str = "phase", rhythmic: bool = False) -> np.ndarray:
    """Validate phases: a finite 1-D array in [0, 1]; returns it as float64, shape (T,)."""
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 1:
        raise ValueError(f"{what} must be a 1-D array of phases in [0, 1], got shape {x.shape}")
    if x.size and not (x.min() >= 0.0 and x.max() <= 1.0):  # (false for NaN too)
        if not np.all(np.isfinite(x)):
            raise ValueError(f"{what} contains NaN or inf; expected finite phases in [0, 1]")
        bad = x[(x < 0) | (x > 1)][0]
        raise ValueError(f"{what} {bad:.6g} is outside [0, 1]; phases are normalized time "
                         f"({'fraction of a cycle' if rhythmic else 'start=0, end=1'})")
    return x


def check_weights(w, n: int, what: str) -> np.ndarray:
    """Importance weights ω of ``n`` elements: finite, >= 0, one per element; None → all 1. Shape (n,)."""
    if w is None:
        return np.ones(n)
    w = np.asarray(w, dtype=np.float64).reshape(-1)
    if w.shape[0] != n:
        raise ValueError(f"{what}: {w.shape[0]} importance weights for {n} elements; expected one per element")
    if not np.isfinite(w).all() or (w < 0).any():
        raise ValueError(f"{what}: importance weights must be finite and >= 0, got {w.tolist()}")
    return w
