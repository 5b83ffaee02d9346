"""Blending two latent distributions along the phase (paper Eq. 4) and the weights of the decoder's
modes with them, written once for
:meth:`deepprompt_ros.primitive.deep_promp.DeepProMP.blend` and the server's blended handles
(:class:`deepprompt_ros.server.handles.BlendedLatent`). numpy only (no torch).
"""
from __future__ import annotations

import numpy as np

__all__ = ["blend_gaussians", "blend_mode_weights"]


def blend_gaussians(omega, mean_a, var_a, mean_b, var_b) -> tuple[np.ndarray, np.ndarray]:
    """q_b(z | x) ∝ q_a(z | x)^ω(x) q_b(z | x)^(1−ω(x)) per phase and latent dimension (paper Eq. 4).

    The product of two diagonal Gaussians raised to ω and 1 − ω: precision ω/σ²_a + (1−ω)/σ²_b,
    mean (ω μ_a/σ²_a + (1−ω) μ_b/σ²_b) / precision. ω = 1 gives a, ω = 0 gives b.

    Parameters
    ----------
    omega : array, shape (T,)
        ω(x) at T phases, in [0, 1] (not checked here).
    mean_a, var_a, mean_b, var_b : array, shape (k,) or (T, k)
        The two distributions, constant or per phase.

    Returns
    -------
    mean, var : array, shape (T, k)
    """
    w = np.asarray(omega, dtype=np.float64)[:, None]
    prec = w / var_a + (1 - w) / var_b
    mean = (w * mean_a / var_a + (1 - w) * mean_b / var_b) / prec
    return mean, 1.0 / prec


def blend_mode_weights(omega, weights_a, weights_b) -> np.ndarray:
    """The weights of a decoder's modes along a blend, (T, K): ω(x) times a's plus 1 − ω(x) times b's, so
    a blend between two modes moves from one mode's offset to the other's as ω does (the modes' gate on
    the blended latent would jump where z_nl crosses a threshold).

    Parameters
    ----------
    omega : array, shape (T,)
        ω(x), in [0, 1] (not checked here).
    weights_a, weights_b : array, shape (K,) or (T, K)
        The modes' weights of the two distributions, constant or per phase.
    """
    w = np.asarray(omega, dtype=np.float64)[:, None]
    return w * weights_a + (1.0 - w) * weights_b
