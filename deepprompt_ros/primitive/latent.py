"""The conditioned latent distribution q(z) of a primitive (torch-free: the server's handle store
imports it before loading torch)."""
from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["LatentGaussian"]


@dataclasses.dataclass(frozen=True)
class LatentGaussian:
    """q(z) = N(mean, diag(var)), the conditioned latent distribution of a primitive.

    Attributes
    ----------
    mean, var : array, shape (k,)
    """

    mean: np.ndarray
    var: np.ndarray

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(self.var)
