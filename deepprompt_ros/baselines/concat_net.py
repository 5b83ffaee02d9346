"""The network of CNMP and VAE-CNMP (paper Sec. II-A and IV): ONE encoder on the concatenation
[via-point, low-dim contexts, image embedding] of each element, mean aggregation, and a decoder —
its architecture (:class:`ConcatNetConfig`, stored in every file) and the torch module
(:class:`ConcatEncoderNet`). All tensors in normalized units.
"""
from __future__ import annotations

import dataclasses
from typing import Mapping

import torch
from torch import nn
from torch.nn import functional as F

from deepprompt_ros.model.network import ImageEncoder, config_from_json, config_to_json, mlp_trunk
from deepprompt_ros.model.phase import phase_dim, phase_features

__all__ = ["VARIANTS", "ConcatNetConfig", "ConcatEncoderNet"]


VARIANTS = ("cnmp", "vae_cnmp")


@dataclasses.dataclass(frozen=True)
class ConcatNetConfig:
    """Architecture of a CNMP / VAE-CNMP (stored in every file).

    Attributes
    ----------
    variant : {"cnmp", "vae_cnmp"}
    n_joints, phase_type, latent_dim, hidden, context_dims, image_shape, phase_harmonics :
        as :class:`deepprompt_ros.model.network.ModelConfig` (2 hidden ReLU layers of ``hidden`` units everywhere).
    sigma_y : float
        VAE-CNMP's fixed decoder standard deviation (normalized units).
    var_floor : float
        VAE-CNMP's floor of every encoder variance σ²_i.
    std_floor : float
        CNMP's floor of the predicted σ_y(r, x) (normalized units): σ_y = softplus(·) + std_floor.
    """

    variant: str
    n_joints: int
    phase_type: str = "linear"
    latent_dim: int = 16
    hidden: int = 128
    context_dims: tuple[tuple[str, int], ...] = ()
    image_shape: tuple[int, int] | None = None
    sigma_y: float = 0.05
    var_floor: float = 1e-4
    std_floor: float = 1e-2
    phase_harmonics: int = 0

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"variant '{self.variant}' unknown; expected one of {VARIANTS}")
        if self.n_joints < 1 or self.latent_dim < 1 or self.hidden < 1:
            raise ValueError("n_joints, latent_dim and hidden must be >= 1")
        if not (self.sigma_y > 0 and self.var_floor > 0 and self.std_floor > 0):
            raise ValueError("sigma_y, var_floor and std_floor must be > 0")

    @property
    def phase_dim(self) -> int:
        return phase_dim(self.phase_type, self.phase_harmonics)

    @property
    def context_names(self) -> tuple[str, ...]:
        return tuple(n for n, _ in self.context_dims)

    @property
    def via_dim(self) -> int:
        return self.phase_dim + self.n_joints

    @property
    def input_dim(self) -> int:
        """[φ(x), y] + Σ c_dims + (hidden if images)."""
        return self.via_dim + sum(c for _, c in self.context_dims) + (self.hidden if self.image_shape else 0)

    def to_json(self) -> dict:
        return config_to_json(self)

    @classmethod
    def from_json(cls, d: Mapping) -> "ConcatNetConfig":
        return config_from_json(cls, d, "network config")


class ConcatEncoderNet(nn.Module):
    """Encoder on concatenated element inputs + mean aggregation + decoder (normalized units).

    Element i of a demonstration is e_i = [φ(x_i), y_i, c, emb(images)] (zero blocks for what is
    missing); with no via-point the set is the single element [0, c, emb]. Shapes: B batch, N elements,
    T phases, k latent, d joints.
    """

    def __init__(self, cfg: ConcatNetConfig):
        super().__init__()
        self.cfg = cfg
        h, k = cfg.hidden, cfg.latent_dim
        self.encoder = mlp_trunk(cfg.input_dim, h)
        self.head = nn.Linear(h, k if cfg.variant == "cnmp" else 2 * k)
        self.image_encoder = ImageEncoder(h) if cfg.image_shape else None
        n_out = 2 * cfg.n_joints if cfg.variant == "cnmp" else cfg.n_joints
        self.decoder = nn.Sequential(nn.Linear(k + cfg.phase_dim, h), nn.ReLU(), nn.Linear(h, h), nn.ReLU(),
                                     nn.Linear(h, n_out))

    def phase_features(self, x: torch.Tensor) -> torch.Tensor:
        return phase_features(x, self.cfg.phase_type, self.cfg.phase_harmonics)

    def elements(self, via: torch.Tensor, via_mask: torch.Tensor, shared: torch.Tensor):
        """Concatenated element inputs with zero padding.

        Parameters
        ----------
        via : (B, N, p + d)   [φ(x_i), y_i] of the candidate via-points
        via_mask : (B, N)     1 = given
        shared : (B, S)       [contexts, image embedding], zeros where missing

        Returns
        -------
        inp : (B, N + 1, input_dim), mask : (B, N + 1) — element N is the zero-via-point element,
        present only when no via-point is given.
        """
        b = via.shape[0]
        via = torch.cat([via * via_mask.unsqueeze(-1), via.new_zeros(b, 1, via.shape[-1])], 1)
        none = (via_mask.sum(1, keepdim=True) == 0).to(via.dtype)
        mask = torch.cat([via_mask, none], 1)
        inp = torch.cat([via, shared.unsqueeze(1).expand(-1, via.shape[1], -1)], -1)
        return inp, mask

    def encode(self, inp: torch.Tensor, mask: torch.Tensor):
        """Mean aggregation over the given elements.

        CNMP: r = 1/n Σ_i φ(e_i) → (r (B, k), None).
        VAE-CNMP: μ_z = 1/n Σ_i μ_i, σ²_z = 1/n Σ_i σ²_i → (μ_z, σ²_z), each (B, k).
        """
        out = self.head(self.encoder(inp))  # (B, N, k or 2k)
        m = mask.unsqueeze(-1)
        n = m.sum(1).clamp_min(1.0)
        if self.cfg.variant == "cnmp":
            return (out * m).sum(1) / n, None
        mu, raw = out.chunk(2, -1)
        var = F.softplus(raw) + self.cfg.var_floor
        return (mu * m).sum(1) / n, (var * m).sum(1) / n

    def decode(self, z: torch.Tensor, x: torch.Tensor):
        """z (B, k), x (T,) → mean (B, T, d) and, for CNMP, σ_y(z, x) (B, T, d) (else None)."""
        zz = z.unsqueeze(1).expand(-1, x.shape[0], -1)
        xf = self.phase_features(x).unsqueeze(0).expand(z.shape[0], -1, -1)
        out = self.decoder(torch.cat([zz, xf], -1))
        if self.cfg.variant == "cnmp":
            mean, raw = out.chunk(2, -1)
            return mean, F.softplus(raw) + self.cfg.std_floor
        return out, None
