"""The DeepProMP network (paper Sec. III-A): per-modality encoders, one shared affine head giving
the per-element (μ_i, σ²_i) that :func:`deepprompt_ros.model.aggregation.bayesian_aggregate`
combines, and an MLP decoder μ_y(z, x) — optionally a residual over a linear basis,
μ_y(z, x) = Φ(x)(b + A z) + s·MLP(z, x) (``ModelConfig.decoder_basis``; the linear part alone is a
PPCA-style ProMP in the latent), or with the latent split into a linear and a nonlinear block
(``ModelConfig.latent_linear``), μ_y(z, x) = Φ(x)(b + A z_lin) + s·MLP(z_nl, x), and with several
modes (``ModelConfig.decoder_modes``) μ_y(z, x) = Φ(x)(b + m_k + A z_lin) + s·MLP(z_nl, x), the mode k
chosen by the first coordinate of z_nl. The phase enters through :mod:`deepprompt_ros.model.phase`.

All tensors here are in *normalized* units (joint positions and low-dim contexts standardized
with the training set's statistics); :mod:`deepprompt_ros.primitive.deep_promp` converts to and from
radians. Shapes use B = batch, N = elements (via-points), T = query phases, d = joints,
k = latent dimension, p = phase-feature dimension.
"""
from __future__ import annotations

import dataclasses
import math
import statistics
from typing import Mapping

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from deepprompt_ros.common.params import param, validate
from deepprompt_ros.model.phase import PHASE_TYPES, phase_basis, phase_dim, phase_features

VARIANCE_HEADS = ("softplus", "exp")
LOGVAR_MAX = 12.0  # "exp" head: σ²_i ≤ e^12 ≈ 1.6e5 (precision ≥ 6e-6, an element can all but vanish)


def decoder_basis_error(n_b: int) -> str:
    """The rule of ``decoder_basis`` its range [0, inf] cannot state (one basis function per joint
    is no basis): ``''`` when ``n_b`` is 0 or >= 2, else a message saying what is expected."""
    return "" if n_b != 1 else f"decoder_basis = {n_b!r}: expected 0 (no linear basis) or >= 2"


def latent_linear_errors(k_l: int, latent_dim: int, n_b: int, n_joints: int) -> list[str]:
    """The rules of ``latent_linear`` k_l its range [0, inf] cannot state: a linear block needs a
    linear basis (``decoder_basis`` n_b >= 2), is part of the latent (k_l <= ``latent_dim``) and has
    no more directions than the basis has weights (k_l <= n_b·d). One message per broken rule."""
    if k_l == 0:
        return []
    errors = []
    if n_b < 2:
        errors.append(f"latent_linear = {k_l!r} needs a linear basis: expected decoder_basis >= 2, got {n_b!r} "
                      "(or latent_linear 0)")
    if k_l > latent_dim:
        errors.append(f"latent_linear = {k_l!r}: expected at most latent_dim = {latent_dim!r} (the linear block "
                      "is part of the latent)")
    if n_b >= 2 and k_l > n_b * n_joints:
        errors.append(f"latent_linear = {k_l!r}: expected at most decoder_basis x n_joints = {n_b} x {n_joints} = "
                      f"{n_b * n_joints} (the weights of the linear part)")
    return errors


def decoder_modes_error(k_m: int, k_l: int, latent_dim: int) -> str:
    """The rule of ``decoder_modes`` K its range cannot state: K >= 2 modes need a split latent with a
    nonlinear block that chooses the mode (1 <= ``latent_linear`` < ``latent_dim``); ``''`` when it holds."""
    if k_m == 1:
        return "decoder_modes = 1: expected 0 (one mode) or >= 2"
    if k_m >= 2 and not 1 <= k_l < latent_dim:
        return (f"decoder_modes = {k_m!r} needs a split latent whose nonlinear block chooses the mode: expected "
                f"1 <= latent_linear < latent_dim, got latent_linear {k_l!r}, latent_dim {latent_dim!r} (or "
                "decoder_modes 0)")
    return ""


def mode_thresholds(cumulative_shares) -> list[float]:
    """The K − 1 standard normal quantiles t_k = Φ_N⁻¹(S_k) of the modes' cumulative shares S_1 … S_{K−1}:
    the first z_nl coordinate below t_1 chooses mode 0, in [t_{k}, t_{k+1}) mode k (:func:`mode_of_latent`)."""
    inv = statistics.NormalDist().inv_cdf
    return [inv(min(max(float(s), 1e-12), 1.0 - 1e-12)) for s in list(cumulative_shares)[:-1]]


def mode_of_latent(z_nl0, cumulative_shares):
    """The mode of each first z_nl coordinate: k with t_k <= z_nl0 < t_{k+1} (:func:`mode_thresholds`), so
    z_nl ~ N(0, I) chooses mode k with probability π_k = S_k − S_{k−1}. numpy arrays give an index array,
    torch tensors an index tensor."""
    t = mode_thresholds(cumulative_shares.tolist() if isinstance(cumulative_shares, torch.Tensor)
                        else cumulative_shares)
    if isinstance(z_nl0, torch.Tensor):
        return torch.bucketize(z_nl0, torch.tensor(t, dtype=z_nl0.dtype, device=z_nl0.device), right=True)
    return np.searchsorted(np.asarray(t, dtype=np.float64), z_nl0, side="right")


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Architecture of a DeepProMP (stored inside every checkpoint).

    Every field but ``context_dims`` and ``image_shape`` is a parameter declared once with
    :func:`deepprompt_ros.common.params.param` (description, range or choices); the training
    configuration (:class:`deepprompt_ros.training.config.TrainConfig`) and the concatenating
    baselines' network take over the ones they share with :func:`~deepprompt_ros.common.params.param_from`.

    Attributes
    ----------
    context_dims : tuple of (str, int)
        Low-dimensional context modalities and their dimensions, one encoder each.
    image_shape : (int, int) or None
        (H, W) of RGB context images, None when the model takes no images.

    Notes
    -----
    ``phase_harmonics`` keep a rhythmic phase periodic (h = 1..max(1, H) of [sin 2πhx, cos 2πhx]).

    ``decoder_basis`` n_b > 0 adds a linear-basis part to the decoder: μ_y(z, x) = Φ(x)(b + A z) +
    s·MLP(z, x), with Φ(x) the n_b normalized RBFs in phase of :class:`deepprompt_ros.baselines.promp.ProMP`
    (von Mises functions for a rhythmic phase; :func:`deepprompt_ros.model.phase.phase_basis`), b (n_b, d)
    and A (n_b, d, k) learned (parameter ``basis``). The linear part is a PPCA-style ProMP whose
    weights are b + A z; the MLP adds the nonlinearity. 0: the plain MLP decoder of the paper.

    ``latent_linear`` k_l > 0 splits the latent into z = [z_lin (k_l), z_nl (k − k_l)] and the residual
    decoder into μ_y(z, x) = Φ(x)(b + A z_lin) + s·MLP(z_nl, x): A is (n_b, d, k_l) and the MLP never
    sees z_lin, so the decoder is linear in z_lin for a fixed z_nl and via-point conditioning of z_lin
    is exact Gaussian conditioning (:meth:`deepprompt_ros.primitive.deep_promp.DeepProMP.condition`),
    with ``via_noise`` the standard deviation of a via-point there (normalized joint units). 0: the
    linear part and the MLP both read all of z.

    ``variance_head`` "exp": a large σ²_i (an element that says almost nothing, precision → 0) is a
    moderate r, reached by gradient steps of the usual size; with softplus σ²_i grows only linearly in r.
    """

    n_joints: int = param(dataclasses.MISSING, "d, the number of joints", min=1)
    phase_type: str = param("linear", "linear: x in [0, 1]; rhythmic: the network sees [sin 2πx, cos 2πx] (paper "
                                      "Sec. III-C)", choices=PHASE_TYPES)
    latent_dim: int = param(16, "k, the dimension of the latent z (16 or 32 in the paper)", min=1)
    hidden: int = param(128, "width of the 2 hidden ReLU layers of every encoder and of the decoder (128 in the "
                             "paper)", min=1)
    context_dims: tuple[tuple[str, int], ...] = ()
    image_shape: tuple[int, int] | None = None
    sigma_y: float = param(0.05, "fixed decoder standard deviation σ_y of the reconstruction likelihood",
                           gt=0.0, unit="normalized")
    var_floor: float = param(1e-4, "lower bound added to every encoder variance σ²_i of the latent (the prior's "
                                   "variance is 1); keeps the aggregation finite", gt=0.0)
    phase_harmonics: int = param(0, "extra Fourier features of the phase fed to encoders and decoder: linear "
                                    "adds [sin πhx, cos πhx] for h = 1..H, rhythmic uses h = 1..max(1, H)", min=0)
    decoder_basis: int = param(0, "n_b: 0 = the paper's MLP decoder; >= 2 adds a linear part Φ(x)(b + A z) of n_b "
                                  "basis functions per joint under the MLP (residual decoder)", min=0)
    basis_width: float = param(1.0, "basis function width of the linear part relative to the centre spacing "
                                    "(ProMP's width)", gt=0.0)
    residual_scale: float = param(1.0, "s, the factor on the MLP part of a residual decoder (0 = the linear part "
                                       "only)", min=0.0)
    variance_head: str = param("softplus", "how the shared head's output r becomes σ²_i: softplus(r) + var_floor, "
                                           "or exp(min(r, 12)) + var_floor (a large σ²_i, an element that says "
                                           "almost nothing, is then a moderate r)", choices=VARIANCE_HEADS)
    latent_linear: int = param(0, "k_l: 0 = the linear part and the MLP both read all of z; > 0 = the first k_l "
                                  "latent dimensions z_lin drive the linear part alone and the MLP reads only the "
                                  "other k - k_l (the decoder is linear in z_lin: via-points condition it exactly); "
                                  "needs decoder_basis >= 2, k_l <= latent_dim and k_l <= decoder_basis x n_joints",
                               min=0)
    via_noise: float = param(1e-4, "standard deviation of a via-point in the exact conditioning of the linear "
                                   "latent block (latent_linear > 0) when a request states none", gt=0.0,
                             unit="normalized")
    mode_noise: float = param(0.0, "decoder_modes >= 2: the via-point standard deviation at which the modes' "
                                   "posterior probabilities are computed, whatever noise a request states (the "
                                   "modes' offsets are estimates: where the modes meet they differ by their "
                                   "estimation error alone); 0 = via_noise", min=0.0, unit="normalized")
    decoder_modes: int = param(0, "K: 0 = one mode; K >= 2 = the linear part's weights are b + m_k + A z_lin with "
                                  "the mode k chosen by z_nl (mode_of_latent: the first z_nl coordinate's prior "
                                  "mass split by the modes' shares), a mixture of K linear Gaussians; needs "
                                  "latent_linear >= 1 and latent_linear < latent_dim", min=0)

    def __post_init__(self):
        validate(self, rules=lambda c: [decoder_basis_error(c.decoder_basis),
                                        *latent_linear_errors(c.latent_linear, c.latent_dim, c.decoder_basis,
                                                              c.n_joints),
                                        decoder_modes_error(c.decoder_modes, c.latent_linear, c.latent_dim)])

    @property
    def latent_nonlinear(self) -> int:
        """k − k_l, the dimension of the block z_nl the MLP reads (all of z when ``latent_linear`` is 0)."""
        return self.latent_dim - self.latent_linear

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
            nn.Linear(cfg.latent_nonlinear + cfg.phase_dim, h), nn.ReLU(), nn.Linear(h, h), nn.ReLU(),
            nn.Linear(h, cfg.n_joints))
        if cfg.decoder_basis:
            # linear part: weights b + A z (z_lin when latent_linear > 0) of the n_b basis functions of
            # each joint, row b·d + j
            k_in = cfg.latent_linear or k
            self.basis = nn.Linear(k_in, cfg.decoder_basis * cfg.n_joints)
            nn.init.zeros_(self.basis.bias)
            nn.init.normal_(self.basis.weight, std=0.1 / math.sqrt(k_in))
        if cfg.decoder_modes:
            # the modes' offsets m_k of the linear part's weights (rows as the basis') and their cumulative
            # shares S_k (mode_of_latent); set from the training demos (training/basis.init_basis_pca)
            k_m = cfg.decoder_modes
            self.register_buffer("mode_offsets", torch.zeros(k_m, cfg.decoder_basis * cfg.n_joints))
            self.register_buffer("mode_cumulative_shares", torch.arange(1, k_m + 1, dtype=torch.float32) / k_m)

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
        """μ_y(z, x): z (B, k), x (B, T) or (T,) → (B, T, d). With ``latent_linear`` k_l > 0 the MLP
        reads z_nl = z[:, k_l:] only."""
        if x.dim() == 1:
            x = x.unsqueeze(0).expand(z.shape[0], -1)
        zz = z[:, self.cfg.latent_linear:].unsqueeze(1).expand(-1, x.shape[1], -1)
        out = self.decoder(torch.cat([zz, self.phase_features(x)], -1))
        if not self.cfg.decoder_basis:
            return out
        return self.cfg.residual_scale * out + self.decode_linear(z, x)

    def mode_of(self, z: torch.Tensor) -> torch.Tensor:
        """The mode of each latent z (B, k) of a model with ``decoder_modes`` (:func:`mode_of_latent`), (B,)."""
        return mode_of_latent(z[:, self.cfg.latent_linear].contiguous(), self.mode_cumulative_shares)

    def basis_functions(self, x: torch.Tensor) -> torch.Tensor:
        """Φ(x) of the linear part: x (..., ) → (..., n_b)."""
        c = self.cfg
        return phase_basis(x, c.decoder_basis, c.basis_width, c.phase_type == "rhythmic")

    def decode_linear(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """The linear part Φ(x)(b + A z): z (B, k), x (B, T) → (B, T, d); with ``latent_linear`` k_l > 0
        it reads z_lin = z[:, :k_l] only; with ``decoder_modes`` it is Φ(x)(b + m_k + A z_lin), k the mode
        of z (:meth:`mode_of`)."""
        k_l = self.cfg.latent_linear
        w = self.basis(z[:, :k_l] if k_l else z)
        if self.cfg.decoder_modes:  # b + m_k + A z_lin, k the mode z_nl chooses
            w = w + self.mode_offsets[self.mode_of(z)]
        w = w.reshape(z.shape[0], self.cfg.decoder_basis, self.cfg.n_joints)
        return torch.bmm(self.basis_functions(x), w)

