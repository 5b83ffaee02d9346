"""The DeepProMP network (paper Sec. III-A): per-modality encoders, one shared affine head giving
the per-element (μ_i, σ²_i) that :func:`deepprompt_ros.model.aggregation.bayesian_aggregate`
combines, and an MLP decoder μ_y(z, x) — optionally a residual over a linear basis,
μ_y(z, x) = Φ(x)(b + A z) + s·MLP(z, x) (``ModelConfig.decoder_basis``; the linear part alone is a
PPCA-style ProMP in the latent). The phase enters through
:mod:`deepprompt_ros.model.phase`.

All tensors here are in *normalized* units (joint positions and low-dim contexts standardized
with the training set's statistics); :mod:`deepprompt_ros.primitive.deep_promp` converts to and from
radians. Shapes use B = batch, N = elements (via-points), T = query phases, d = joints,
k = latent dimension, p = phase-feature dimension.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Mapping

import torch
from torch import nn
from torch.nn import functional as F

from deepprompt_ros.model.phase import PHASE_TYPES, phase_basis, phase_dim, phase_features

VARIANCE_HEADS = ("softplus", "exp")
LOGVAR_MAX = 12.0  # "exp" head: σ²_i ≤ e^12 ≈ 1.6e5 (precision ≥ 6e-6, an element can all but vanish)


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Architecture of a DeepProMP (stored inside every checkpoint).

    Attributes
    ----------
    n_joints : int
        d, the number of joints.
    phase_type : {"linear", "rhythmic"}
        linear: x in [0, 1]; rhythmic: the network sees [sin 2πx, cos 2πx] (paper Sec. III-C).
    latent_dim : int
        k (16 or 32 in the paper).
    hidden : int
        Width of the 2 hidden ReLU layers of every MLP (128 in the paper).
    context_dims : tuple of (str, int)
        Low-dimensional context modalities and their dimensions, one encoder each.
    image_shape : (int, int) or None
        (H, W) of RGB context images, None when the model takes no images.
    sigma_y : float
        Fixed decoder standard deviation σ_y (normalized units).
    var_floor : float
        Lower bound added to every encoder variance σ²_i (keeps the aggregation finite).
    phase_harmonics : int
        Extra Fourier features of the phase fed to encoders and decoder: linear adds
        [sin πhx, cos πhx] for h = 1..H to x; rhythmic uses [sin 2πhx, cos 2πhx] for h = 1..max(1, H).
        Both keep the rhythmic phase periodic.
    decoder_basis : int
        n_b > 0 adds a linear-basis part to the decoder: μ_y(z, x) = Φ(x)(b + A z) + s·MLP(z, x),
        with Φ(x) the n_b normalized RBFs in phase of :class:`deepprompt_ros.baselines.promp.ProMP`
        (von Mises functions for a rhythmic phase; :func:`deepprompt_ros.model.phase.phase_basis`),
        b (n_b, d) and A (n_b, d, k) learned (parameter ``basis``). The linear part is a PPCA-style
        ProMP whose weights are b + A z; the MLP adds the nonlinearity.
        0 (default): the plain MLP decoder of the paper.
    basis_width : float
        RBF standard deviation relative to the centre spacing (ProMP's ``width``).
    residual_scale : float
        s, the factor on the MLP part when ``decoder_basis`` > 0 (0 = the linear part only).
    variance_head : {"softplus", "exp"}
        How the shared head's second half r becomes σ²_i: softplus(r) + var_floor (default), or
        exp(min(r, 12)) + var_floor. With "exp" a large σ²_i (an element that says almost nothing,
        precision → 0) is a moderate r, reached by gradient steps of the usual size; with softplus
        σ²_i grows only linearly in r.
    """

    n_joints: int
    phase_type: str = "linear"
    latent_dim: int = 16
    hidden: int = 128
    context_dims: tuple[tuple[str, int], ...] = ()
    image_shape: tuple[int, int] | None = None
    sigma_y: float = 0.05
    var_floor: float = 1e-4
    phase_harmonics: int = 0
    decoder_basis: int = 0
    basis_width: float = 1.0
    residual_scale: float = 1.0
    variance_head: str = "softplus"

    def __post_init__(self):
        if self.n_joints < 1:
            raise ValueError(f"n_joints must be >= 1, got {self.n_joints}")
        if self.phase_type not in PHASE_TYPES:
            raise ValueError(f"phase_type '{self.phase_type}' unknown; expected one of {PHASE_TYPES}")
        if self.latent_dim < 1 or self.hidden < 1:
            raise ValueError("latent_dim and hidden must be >= 1")
        if not self.sigma_y > 0 or not self.var_floor > 0:
            raise ValueError("sigma_y and var_floor must be > 0")
        if self.decoder_basis < 0 or self.decoder_basis == 1:
            raise ValueError(f"decoder_basis must be 0 (no linear basis) or >= 2, got {self.decoder_basis}")
        if self.variance_head not in VARIANCE_HEADS:
            raise ValueError(f"variance_head '{self.variance_head}' unknown; expected one of {VARIANCE_HEADS}")
        if not self.basis_width > 0 or not self.residual_scale >= 0:
            raise ValueError("basis_width must be > 0 and residual_scale >= 0")

    @property
    def phase_dim(self) -> int:
        return phase_dim(self.phase_type, self.phase_harmonics)

    @property
    def context_names(self) -> tuple[str, ...]:
        return tuple(n for n, _ in self.context_dims)

    def to_json(self) -> dict:
        return config_to_json(self)

    @classmethod
    def from_json(cls, d: Mapping) -> "ModelConfig":
        return config_from_json(cls, d, "model config")


def config_to_json(cfg) -> dict:
    """A frozen network-config dataclass with ``context_dims`` and ``image_shape`` as JSON types."""
    d = dataclasses.asdict(cfg)
    d["context_dims"] = [list(c) for c in cfg.context_dims]
    d["image_shape"] = list(cfg.image_shape) if cfg.image_shape else None
    return d


def config_from_json(cls, d: Mapping, what: str):
    """Inverse of :func:`config_to_json`; unknown keys are refused naming ``what``."""
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = set(d) - fields
    if unknown:
        raise ValueError(f"{what} has unknown keys {sorted(unknown)}; expected a subset of {sorted(fields)}")
    d = dict(d)
    d["context_dims"] = tuple((str(n), int(c)) for n, c in d.get("context_dims", ()))
    if d.get("image_shape") is not None:
        d["image_shape"] = tuple(int(v) for v in d["image_shape"])
    return cls(**d)


def mlp_trunk(n_in: int, hidden: int) -> nn.Sequential:
    """2 hidden ReLU layers (the paper's encoder body); the shared head follows."""
    return nn.Sequential(nn.Linear(n_in, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU())


class ImageEncoder(nn.Module):
    """Small CNN trained from scratch (stand-in for the paper's ResNet-50, which cannot be
    downloaded here). Input (B, n, 3, H, W) in [0, 1]; the n images of one demonstration are
    averaged in embedding space (paper Sec. IV), giving one aggregator element per demo."""

    def __init__(self, hidden: int):
        super().__init__()
        self.conv = nn.Sequential(
            nn.Conv2d(3, 16, 5, stride=2, padding=2), nn.ReLU(),
            nn.Conv2d(16, 32, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(32, 32, 3, stride=2, padding=1), nn.ReLU(),
            nn.AdaptiveAvgPool2d(1), nn.Flatten())
        self.fc = nn.Sequential(nn.Linear(32, hidden), nn.ReLU())

    def forward(self, images: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        b, n = images.shape[:2]
        feat = self.fc(self.conv(images.reshape(b * n, *images.shape[2:]))).reshape(b, n, -1)  # (B, n, h)
        m = mask.unsqueeze(-1)
        return (feat * m).sum(1) / m.sum(1).clamp_min(1.0)  # (B, h)


class DeepProMPNet(nn.Module):
    """Encoders + shared affine head + decoder. See module docstring for units and shapes."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        h, k = cfg.hidden, cfg.latent_dim
        self.via_encoder = mlp_trunk(cfg.phase_dim + cfg.n_joints, h)
        self.context_encoders = nn.ModuleDict({n: mlp_trunk(c, h) for n, c in cfg.context_dims})
        self.image_encoder = ImageEncoder(h) if cfg.image_shape else None
        self.head = nn.Linear(h, 2 * k)  # ONE affine head shared by all encoders
        self.decoder = nn.Sequential(
            nn.Linear(k + cfg.phase_dim, h), nn.ReLU(), nn.Linear(h, h), nn.ReLU(), nn.Linear(h, cfg.n_joints))
        if cfg.decoder_basis:
            # linear part: weights b + A z of the n_b basis functions of each joint, row b·d + j
            self.basis = nn.Linear(k, cfg.decoder_basis * cfg.n_joints)
            nn.init.zeros_(self.basis.bias)
            nn.init.normal_(self.basis.weight, std=0.1 / math.sqrt(k))

    # -- encoders -------------------------------------------------------------------------
    def _head(self, feat: torch.Tensor):
        mu, raw = self.head(feat).chunk(2, dim=-1)
        if self.cfg.variance_head == "exp":
            return mu, torch.exp(raw.clamp_max(LOGVAR_MAX)) + self.cfg.var_floor
        return mu, F.softplus(raw) + self.cfg.var_floor

    def phase_features(self, x: torch.Tensor) -> torch.Tensor:
        return phase_features(x, self.cfg.phase_type, self.cfg.phase_harmonics)

    def encode_via_points(self, x: torch.Tensor, y: torch.Tensor):
        """x (B, N) phases, y (B, N, d) normalized positions → μ, σ² (B, N, k)."""
        return self._head(self.via_encoder(torch.cat([self.phase_features(x), y], -1)))

    def encode_context(self, name: str, c: torch.Tensor):
        """c (B, M, c_dim) normalized context vectors → μ, σ² (B, M, k)."""
        return self._head(self.context_encoders[name](c))

    def encode_images(self, images: torch.Tensor, mask: torch.Tensor):
        """images (B, n, 3, H, W) in [0, 1], mask (B, n) → μ, σ² (B, 1, k)."""
        mu, var = self._head(self.image_encoder(images, mask))
        return mu.unsqueeze(1), var.unsqueeze(1)

    # -- decoder --------------------------------------------------------------------------
    def decode(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """μ_y(z, x): z (B, k), x (B, T) or (T,) → (B, T, d)."""
        if x.dim() == 1:
            x = x.unsqueeze(0).expand(z.shape[0], -1)
        zz = z.unsqueeze(1).expand(-1, x.shape[1], -1)
        out = self.decoder(torch.cat([zz, self.phase_features(x)], -1))
        if not self.cfg.decoder_basis:
            return out
        return self.cfg.residual_scale * out + self.decode_linear(z, x)

    def basis_functions(self, x: torch.Tensor) -> torch.Tensor:
        """Φ(x) of the linear part: x (..., ) → (..., n_b)."""
        c = self.cfg
        return phase_basis(x, c.decoder_basis, c.basis_width, c.phase_type == "rhythmic")

    def decode_linear(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """The linear part Φ(x)(b + A z): z (B, k), x (B, T) → (B, T, d)."""
        w = self.basis(z).reshape(z.shape[0], self.cfg.decoder_basis, self.cfg.n_joints)  # (B, n_b, d)
        return torch.bmm(self.basis_functions(x), w)

