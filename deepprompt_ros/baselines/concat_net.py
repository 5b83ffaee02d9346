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

from deepprompt_ros.common.params import param, param_from, validate
from deepprompt_ros.model.network import ImageEncoder, ModelConfig, config_from_json, config_to_json, mlp_trunk
from deepprompt_ros.model.phase import phase_dim, phase_features

__all__ = ["VARIANTS", "ConcatNetConfig", "ConcatEncoderNet"]


VARIANTS = ("cnmp", "vae_cnmp")


@dataclasses.dataclass(frozen=True)
class ConcatNetConfig:
    """Architecture of a CNMP / VAE-CNMP (stored in every file).

    The fields it shares with :class:`deepprompt_ros.model.network.ModelConfig` (``n_joints``,
    ``phase_type``, ``latent_dim``, ``hidden``, ``context_dims``, ``image_shape``, ``sigma_y``,
    ``var_floor``, ``phase_harmonics``) mean the same there (2 hidden ReLU layers of ``hidden``
    units everywhere) and are declared there; ``sigma_y`` and ``var_floor`` are VAE-CNMP's.
    """

    variant: str = param(dataclasses.MISSING, "which network: CNMP or VAE-CNMP", choices=VARIANTS)
    n_joints: int = param_from(ModelConfig, "n_joints")
    phase_type: str = param_from(ModelConfig, "phase_type")
    latent_dim: int = param_from(ModelConfig, "latent_dim")
    hidden: int = param_from(ModelConfig, "hidden")
    context_dims: tuple[tuple[str, int], ...] = ()
    image_shape: tuple[int, int] | None = None
    sigma_y: float = param_from(ModelConfig, "sigma_y")
    var_floor: float = param_from(ModelConfig, "var_floor")
    std_floor: float = param(1e-2, "CNMP's floor of the predicted σ_y(r, x): σ_y = softplus(·) + std_floor",
                             gt=0.0, unit="normalized")
    phase_harmonics: int = param_from(ModelConfig, "phase_harmonics")

    def __post_init__(self):
        validate(self)

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
