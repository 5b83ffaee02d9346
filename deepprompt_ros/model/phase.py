"""Phase features and the phase basis shared by the networks, the numpy fast path and training.

φ(x) is what the encoders and the decoder see of the phase x (paper Sec. III-C: a rhythmic phase
enters as [sin 2πx, cos 2πx]); Φ(x) is the normalized basis of the residual decoder's linear part,
the same basis as :class:`deepprompt_ros.baselines.promp.ProMP`. Both work on numpy arrays and on
torch tensors.
"""
from __future__ import annotations

import math

import numpy as np
import torch

__all__ = ["PHASE_TYPES", "phase_dim", "phase_features", "phase_basis"]

PHASE_TYPES = ("linear", "rhythmic")


def phase_dim(phase_type: str, harmonics: int) -> int:
    """p, the length of φ(x) (see :func:`phase_features`)."""
    if phase_type == "rhythmic":
        return 2 * max(1, harmonics)
    return 1 + 2 * harmonics


def phase_features(x, phase_type: str, harmonics: int):
    """Phase features φ(x) fed to the networks (works on numpy arrays and torch tensors).

    Linear: [x, sin πhx, cos πhx for h = 1..H]; rhythmic: [sin 2πhx, cos 2πhx for h = 1..max(1, H)]
    (periodic in x).

    Parameters
    ----------
    x : array, shape (...,)
        Normalized phase.

    Returns
    -------
    array, shape (..., p)
    """
    lib = torch if isinstance(x, torch.Tensor) else np
    feats = []
    if phase_type == "rhythmic":
        for h in range(1, max(1, harmonics) + 1):
            feats += [lib.sin(2 * math.pi * h * x), lib.cos(2 * math.pi * h * x)]
    else:
        feats.append(x)
        for h in range(1, harmonics + 1):
            feats += [lib.sin(math.pi * h * x), lib.cos(math.pi * h * x)]
    return lib.stack(feats, -1)


def phase_basis(x, n_basis: int, width: float, rhythmic: bool):
    """Normalized basis Φ(x) of the decoder's linear part (numpy arrays or torch tensors).

    Linear phase: Gaussian RBFs with centres linspace(0, 1, n) and standard deviation width/(n−1);
    rhythmic: von Mises functions with centres j/n and concentration 1/(2π·width/n)², periodic in x.
    Both normalized to sum to 1 at every phase (the basis of
    :class:`deepprompt_ros.baselines.promp.ProMP`).

    Parameters
    ----------
    x : array, shape (...,)

    Returns
    -------
    array, shape (..., n)
    """
    lib = torch if isinstance(x, torch.Tensor) else np
    if rhythmic:
        centres = np.arange(n_basis) / n_basis
        kappa = 1.0 / (2.0 * math.pi * width / n_basis) ** 2
        u = x[..., None] - (torch.as_tensor(centres, dtype=x.dtype) if lib is torch else centres)
        e = kappa * (lib.cos(2.0 * math.pi * u) - 1.0)
    else:
        centres = np.linspace(0.0, 1.0, n_basis)
        h = width / (n_basis - 1)
        u = x[..., None] - (torch.as_tensor(centres, dtype=x.dtype) if lib is torch else centres)
        e = -0.5 * (u / h) ** 2
    if lib is torch:
        e = e - e.amax(-1, keepdim=True)  # the shift cancels in the normalization
        b = torch.exp(e)
        return b / b.sum(-1, keepdim=True)
    e = e - e.max(-1, keepdims=True)
    b = np.exp(e)
    return b / b.sum(-1, keepdims=True)
