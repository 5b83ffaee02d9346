"""Bayesian aggregation of per-element latent Gaussians (paper Eq. 1 and Eq. 3) and the KL
divergence of diagonal Gaussians used by the training objectives.

One implementation for the torch training path and the float64 numpy deployment path
(:meth:`deepprompt_ros.primitive.deep_promp.DeepProMP.aggregate`).
"""
from __future__ import annotations

import torch

__all__ = ["bayesian_aggregate", "gaussian_kl"]


def bayesian_aggregate(mu, var, weight):
    """Bayesian aggregation with prior N(0, I) and importance weights (paper Eq. 1 and Eq. 3).

    σ²_z = (1 + Σ_i ω_i / σ²_i)^-1,   μ_z = σ²_z Σ_i ω_i μ_i / σ²_i.

    Works on torch tensors and on numpy arrays (the elements are the second-to-last axis).

    Parameters
    ----------
    mu, var : array, shape (..., N, k)
        Per-element means μ_i and variances σ²_i (B = batch in training, none at deployment).
    weight : array, shape (..., N)
        ω_i ≥ 0; 0 removes element i exactly (also used as the padding mask).

    Returns
    -------
    mu_z, var_z : array, shape (..., k)
    """
    prec = weight[..., None] / var  # (..., N, k)
    var_z = 1.0 / (1.0 + prec.sum(-2))
    mu_z = var_z * (prec * mu).sum(-2)
    return mu_z, var_z


def gaussian_kl(mu_q, var_q, mu_p, var_p) -> torch.Tensor:
    """KL(N(mu_q, var_q) || N(mu_p, var_p)) summed over the last dim (diagonal Gaussians)."""
    return 0.5 * (torch.log(var_p / var_q) + (var_q + (mu_q - mu_p) ** 2) / var_p - 1.0).sum(-1)
