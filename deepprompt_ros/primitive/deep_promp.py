"""A trained DeepProMP and every operation of the paper (Sec. III-C and appendix).

:class:`DeepProMP` wraps a trained network with a float64 numpy path for the operations that run
at deployment (conditioning, decoding, refinement): small MLPs are dominated by per-call overhead
in torch, and refinement needs float64 to reach 1e-6 rad. Images go through the torch CNN.

Units: phases x in [0, 1]; joint positions in the robot's units (rad); contexts in their raw
units. Every public method validates its inputs and raises ``ValueError`` saying what is expected.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable, Mapping, Sequence

import numpy as np
import torch

from deepprompt_ros.model.checkpoint import Checkpoint, Normalization, load_checkpoint
from deepprompt_ros.model.network import LOGVAR_MAX, DeepProMPNet, phase_basis, phase_features


def joint_list_text(names: Sequence[str]) -> str:
    """'j1, j2, j3' or 'j1..j7' for messages that name a primitive's joints."""
    return ", ".join(names) if len(names) <= 4 else f"{names[0]}..{names[-1]}"


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
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{what} contains NaN or inf; expected finite phases in [0, 1]")
    if x.size and (x.min() < 0.0 or x.max() > 1.0):
        bad = x[(x < 0) | (x > 1)][0]
        raise ValueError(f"{what} {bad:.6g} is outside [0, 1]; phases are normalized time "
                         f"({'fraction of a cycle' if rhythmic else 'start=0, end=1'})")
    return x


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


@dataclasses.dataclass(frozen=True)
class RefinementResult:
    """Outcome of :meth:`DeepProMP.refine`.

    Attributes
    ----------
    latent : LatentGaussian
        Refined (μ̃, σ̃²). The executed trajectory is the decoder at z = μ̃.
    max_error : float
        max_i,j |y_ij − μ_y(μ̃, x_i)_j| over the constrained joints (rad): what the robot will miss by.
    errors : array, shape (n, d)
        Signed residuals y − μ_y(μ̃, x) per via-point and joint (0 on unconstrained joints).
    sample_mean_error : float
        Same, for the mean over the K fixed Monte-Carlo samples (the paper's objective).
    iterations : int
    reachable : bool
        True when max_error <= tol. False means the solver reached a stationary point (or its
        budget) with a residual above tol: the via-points cannot all be met by this primitive; the
        best fit found is returned, never a silent miss.
    reason : str
    error_history : array, shape (iterations + 1,)
        Max via-point error of the exact decoder at the best μ̃ found so far: before the first
        iteration, then after each one (all stages: LM, continuation, restarts). Non-increasing;
        its last value is ``max_error``.
    """

    latent: LatentGaussian
    max_error: float
    errors: np.ndarray
    sample_mean_error: float
    iterations: int
    reachable: bool
    reason: str
    error_history: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))


class _NumpyMLP:
    """ReLU MLP evaluated in float64 numpy; keeps the pre-activation masks for Jacobians."""

    def __init__(self, seq: torch.nn.Sequential):
        lin = [m for m in seq if isinstance(m, torch.nn.Linear)]
        self.W = [m.weight.detach().double().numpy().copy() for m in lin]
        self.b = [m.bias.detach().double().numpy().copy() for m in lin]
        self.WT = [np.ascontiguousarray(w.T) for w in self.W]  # contiguous (in, out): faster GEMM
        self.relu_last = isinstance(list(seq)[-1], torch.nn.ReLU)

    def __call__(self, h: np.ndarray) -> np.ndarray:
        n = len(self.W)
        for i, (wt, b) in enumerate(zip(self.WT, self.b)):
            h = h @ wt
            h += b
            if i < n - 1 or self.relu_last:
                np.maximum(h, 0.0, out=h)
        return h


class DeepProMP:
    """A trained DeepProMP with its joint names and normalization.

    Parameters
    ----------
    net : DeepProMPNet
    normalization : Normalization
    joint_names : sequence of str, length d
    name : str
    metadata : mapping, optional (training provenance)
    """

    def __init__(self, net: DeepProMPNet, normalization: Normalization, joint_names: Sequence[str],
                 name: str = "primitive", metadata: Mapping | None = None):
        self.net = net.eval()
        self.cfg = net.cfg
        self.norm = normalization
        self.joint_names = tuple(joint_names)
        self.name = name
        self.metadata = dict(metadata or {})
        if len(self.joint_names) != self.cfg.n_joints:
            raise ValueError(f"{len(self.joint_names)} joint names for a model with {self.cfg.n_joints} joints")
        self._via = _NumpyMLP(net.via_encoder)
        self._ctx = {n: _NumpyMLP(m) for n, m in net.context_encoders.items()}
        self._head_W = net.head.weight.detach().double().numpy().copy()
        self._head_b = net.head.bias.detach().double().numpy().copy()
        self._head_WT = np.ascontiguousarray(self._head_W.T)
        self._dec = _NumpyMLP(net.decoder)
        k = self.cfg.latent_dim
        nb, d = self.cfg.decoder_basis, self.cfg.n_joints
        if nb:  # residual decoder: the MLP's output layer carries the factor s, the linear part is separate
            self._dec.W[-1] = self._dec.W[-1] * self.cfg.residual_scale
            self._dec.b[-1] = self._dec.b[-1] * self.cfg.residual_scale
            self._dec.WT[-1] = np.ascontiguousarray(self._dec.W[-1].T)
            ystd = np.asarray(normalization.y_std, dtype=np.float64)
            # Φ(x)(b + A z) in joint units: b (n_b, d), A as (k, n_b·d) for z @ A and (n_b, d, k) for the Jacobian
            bw = net.basis.weight.detach().double().numpy().reshape(nb, d, k) * ystd[None, :, None]
            self._basis_b = net.basis.bias.detach().double().numpy().reshape(nb, d) * ystd[None, :]
            self._basis_A = np.ascontiguousarray(bw)
            self._basis_AT = np.ascontiguousarray(bw.reshape(nb * d, k).T)
        self._phi_cache: dict[bytes, np.ndarray] = {}
        self._dec_W1z = self._dec.W[0][:, :k]
        self._dec_W1x = self._dec.W[0][:, k:]
        self._y_mean = np.asarray(normalization.y_mean, dtype=np.float64)
        self._y_std = np.asarray(normalization.y_std, dtype=np.float64)
        # decode() fast path: contiguous transposed weights, the output layer with the
        # de-normalization folded in, and the phase part of layer 1 cached per phase grid
        self._W1zT = np.ascontiguousarray(self._dec_W1z.T)
        self._W3T = np.ascontiguousarray(self._dec.W[2].T * self._y_std)
        self._b3 = self._dec.b[2] * self._y_std + self._y_mean
        self._pre_x_cache: dict[bytes, np.ndarray] = {}

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_checkpoint(cls, ck: Checkpoint | str, name: str | None = None) -> "DeepProMP":
        if not isinstance(ck, Checkpoint):
            import pathlib

            name = name or pathlib.Path(ck).stem
            ck = load_checkpoint(ck)
        return cls(ck.build(), ck.normalization, ck.joint_names, name or "primitive", ck.metadata)

    def with_residual_scale(self, residual_scale: float) -> "DeepProMP":
        """A copy whose decoder's MLP residual carries the factor ``residual_scale`` instead of the
        trained one (``decoder_basis`` > 0 only; 0 = the linear part Φ(x)(b + A z) alone). The
        weights are shared in value (copied), the encoders are unchanged."""
        if not self.cfg.decoder_basis:
            raise ValueError("with_residual_scale needs a residual decoder (decoder_basis > 0)")
        net = DeepProMPNet(dataclasses.replace(self.cfg, residual_scale=float(residual_scale)))
        net.load_state_dict(self.net.state_dict())
        return DeepProMP(net, self.norm, self.joint_names, self.name, self.metadata)

    # ------------------------------------------------------------------ properties
    @property
    def n_joints(self) -> int:
        return self.cfg.n_joints

    @property
    def latent_dim(self) -> int:
        return self.cfg.latent_dim

    @property
    def phase_type(self) -> str:
        return self.cfg.phase_type

    @property
    def context_dims(self) -> dict[str, int]:
        return dict(self.cfg.context_dims)

    @property
    def image_shape(self):
        return self.cfg.image_shape

    def _joint_list(self) -> str:
        return joint_list_text(self.joint_names)

    # ------------------------------------------------------------------ validation
    def check_phases(self, x, what: str = "phase") -> np.ndarray:
        return check_phases(x, what, rhythmic=self.phase_type == "rhythmic")

    def check_positions(self, y, n: int | None = None, what: str = "via-point") -> np.ndarray:
        y = np.asarray(y, dtype=np.float64)
        if y.ndim == 1:
            y = y[None, :]
        if y.ndim != 2:
            raise ValueError(f"{what} positions must have shape (n, {self.n_joints}), got {y.shape}")
        if y.shape[1] != self.n_joints:
            raise ValueError(f"{what} has {y.shape[1]} joint values; primitive '{self.name}' has "
                             f"{self.n_joints} joints: {self._joint_list()}")
        if n is not None and y.shape[0] != n:
            raise ValueError(f"{y.shape[0]} {what} position rows for {n} phases; expected one row per phase")
        bad = ~np.isfinite(y)
        if bad.any():
            i, j = np.argwhere(bad)[0]
            raise ValueError(f"{what} {i} joint '{self.joint_names[j]}' is NaN or inf; expected finite positions")
        return y

    @staticmethod
    def _check_weights(w, n: int, what: str) -> np.ndarray:
        if w is None:
            return np.ones(n)
        w = np.asarray(w, dtype=np.float64).reshape(-1)
        if w.shape[0] != n:
            raise ValueError(f"{what}: {w.shape[0]} importance weights for {n} elements; expected one per element")
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise ValueError(f"{what}: importance weights must be finite and >= 0, got {w.tolist()}")
        return w

    def _check_mask(self, mask, n: int) -> np.ndarray:
        if mask is None:
            return np.ones((n, self.n_joints), dtype=bool)
        m = np.asarray(mask, dtype=bool)
        if m.ndim == 1:
            m = np.broadcast_to(m, (n, m.shape[0]))
        if m.shape != (n, self.n_joints):
            raise ValueError(f"joint mask must have shape ({n}, {self.n_joints}) or ({self.n_joints},), got {m.shape}")
        return m

    # ------------------------------------------------------------------ encoders (numpy)
    def _head(self, feat: np.ndarray):
        out = feat @ self._head_WT
        out += self._head_b
        k = self.latent_dim
        raw = out[..., k:]
        if self.cfg.variance_head == "exp":  # as in the network (model.DeepProMPNet._head)
            var = np.exp(np.minimum(raw, LOGVAR_MAX)) + self.cfg.var_floor
        else:
            var = np.logaddexp(0.0, raw) + self.cfg.var_floor  # softplus + floor
        return out[..., :k], var

    def _phase_feats(self, x: np.ndarray) -> np.ndarray:
        return phase_features(x, self.cfg.phase_type, self.cfg.phase_harmonics)

    def encode_via_points(self, x, y):
        """Per-element q(z | a_i): x (n,), y (n, d) rad → μ_i, σ²_i (n, k)."""
        yn = (y - self._y_mean) / self._y_std
        return self._head(self._via(np.concatenate([self._phase_feats(x), yn], 1)))

    def encode_context(self, name: str, c):
        """q(z | c_i) for low-dim contexts: c (m, c_dim) raw units → μ_i, σ²_i (m, k)."""
        if name not in self._ctx:
            raise ValueError(f"primitive '{self.name}' takes no context '{name}'; it accepts "
                             f"{sorted(self._ctx) or 'no low-dimensional contexts'}"
                             f"{' and images' if self.image_shape else ''}")
        dim = self.context_dims[name]
        c = np.asarray(c, dtype=np.float64)
        if c.ndim == 1:
            c = c[None, :]
        if c.ndim != 2 or c.shape[1] != dim or c.shape[0] < 1:
            raise ValueError(f"context '{name}' must have {dim} values per vector (shape (m, {dim})), got {c.shape}")
        if not np.all(np.isfinite(c)):
            raise ValueError(f"context '{name}' contains NaN or inf; expected finite values")
        cn = (c - self.norm.ctx_mean[name]) / self.norm.ctx_std[name]
        return self._head(self._ctx[name](cn))

    def encode_images(self, images):
        """q(z | images): images (n, H, W, 3) uint8 of one scene, averaged in embedding space → (1, k)."""
        if self.image_shape is None:
            raise ValueError(f"primitive '{self.name}' takes no images")
        im = check_images(images, self.image_shape)
        with torch.inference_mode():
            t = torch.from_numpy(np.ascontiguousarray(im)).permute(0, 3, 1, 2).float().unsqueeze(0) / 255.0
            mu, var = self.net.encode_images(t, torch.ones(1, t.shape[1]))
        return mu[0].double().numpy(), var[0].double().numpy()

    # ------------------------------------------------------------------ conditioning
    def prior(self) -> LatentGaussian:
        """p0(z) = N(0, I)."""
        return LatentGaussian(np.zeros(self.latent_dim), np.ones(self.latent_dim))

    def condition(self, via_x=None, via_y=None, via_weights=None, via_mask=None,
                  contexts: Mapping[str, np.ndarray] | None = None,
                  context_weights: Mapping[str, Sequence[float]] | None = None,
                  images=None, image_weight: float = 1.0) -> LatentGaussian:
        """q(z | A, C, ω) by Bayesian aggregation (paper Eq. 1 and the importance-weighted Eq. 3).

        Parameters
        ----------
        via_x : array, shape (n,), phases in [0, 1]
        via_y : array, shape (n, d), joint positions
        via_weights : array, shape (n,), ω ≥ 0 (default 1; 0 removes the via-point exactly)
        via_mask : array of bool, shape (n, d) or (d,), optional
            Joints constrained by each via-point. The encoder needs whole configurations, so the
            unconstrained joints of a partial via-point are filled with the mean trajectory
            conditioned on everything else; :meth:`refine` with the same mask then meets the
            constrained joints exactly.
        contexts : mapping modality -> array, shape (m, c) or (c,)
        context_weights : mapping modality -> array, shape (m,)
        images : array, shape (n_img, H, W, 3) uint8, the images of one scene
        image_weight : float
        """
        mus, vars_, ws = [], [], []
        if contexts:
            for name, c in contexts.items():
                mu, var = self.encode_context(name, c)
                mus.append(mu), vars_.append(var)
                ws.append(self._check_weights((context_weights or {}).get(name), mu.shape[0], f"context '{name}'"))
        if images is not None:
            mu, var = self.encode_images(images)
            mus.append(mu), vars_.append(var)
            ws.append(self._check_weights([image_weight], 1, "images"))
        if via_x is not None or via_y is not None:
            if via_x is None or via_y is None:
                raise ValueError("via-points need both phases via_x (n,) and positions via_y (n, d)")
            x = self.check_phases(via_x, "via-point phase")
            y = self.check_positions(via_y, x.shape[0])
            w = self._check_weights(via_weights, x.shape[0], "via-points")
            mask = self._check_mask(via_mask, x.shape[0])
            if not mask.all():
                full = mask.all(1)
                base = self.condition(x[full], y[full], w[full], None, contexts, context_weights, images, image_weight)
                fill = self.decode(base.mean, x)
                y = np.where(mask, y, fill)
            mu, var = self.encode_via_points(x, y)
            mus.append(mu), vars_.append(var), ws.append(w)
        if not mus:
            return self.prior()
        mu, var, w = np.concatenate(mus), np.concatenate(vars_), np.concatenate(ws)
        return self.aggregate(mu, var, w)

    @staticmethod
    def aggregate(mu: np.ndarray, var: np.ndarray, w: np.ndarray) -> LatentGaussian:
        """σ²_z = (1 + Σ ω_i/σ²_i)^-1, μ_z = σ²_z Σ ω_i μ_i/σ²_i  (mu, var (n, k); w (n,))."""
        prec = w[:, None] / var
        var_z = 1.0 / (1.0 + prec.sum(0))
        return LatentGaussian(var_z * (prec * mu).sum(0), var_z)

    # ------------------------------------------------------------------ decoding
    def decode(self, z, x) -> np.ndarray:
        """μ_y(z, x) in joint units.

        Parameters
        ----------
        z : array, shape (k,) or (n, k)
        x : array, shape (T,) — or shape (T,) with z of shape (T, k) when ``per_phase`` use

        Returns
        -------
        array, shape (T, d) or (n, T, d)
        """
        z = np.asarray(z, dtype=np.float64)
        pre_x = self._layer1_phase(x)  # (T, h)
        if z.ndim == 1:
            h = pre_x + z @ self._W1zT
        else:
            h = pre_x[None] + (z @ self._W1zT)[:, None, :]
        np.maximum(h, 0.0, out=h)
        out = self._decode_hidden(h)
        if self.cfg.decoder_basis:
            out += self._linear_part(z, x)
        return out

    @staticmethod
    def _per_grid(cache: dict, x, compute: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """compute(x) cached per phase grid (a server decodes the same preview / control grid again
        and again); at most 16 grids, the result read-only: do not modify."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        key = x.tobytes()
        out = cache.get(key)
        if out is None:
            out = compute(x)
            out.flags.writeable = False
            if len(cache) >= 16:
                cache.clear()  # atomic (several server threads decode)
            cache[key] = out
        return out

    def _phi(self, x) -> np.ndarray:
        """Φ(x) of the decoder's linear part, (T, n_b); cached per phase grid like the phase layer."""
        c = self.cfg
        return self._per_grid(self._phi_cache, x, lambda x: phase_basis(x, c.decoder_basis, c.basis_width,
                                                                         c.phase_type == "rhythmic"))

    def _linear_part(self, z: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Φ(x)(b + A z) in joint units (without the mean, which ``_b3`` carries): z (k,) → (T, d),
        z (n, k) → (n, T, d)."""
        nb, d = self.cfg.decoder_basis, self.n_joints
        w = (z @ self._basis_AT).reshape(*z.shape[:-1], nb, d) + self._basis_b  # (..., n_b, d)
        return self._phi(x) @ w

    def _decode_hidden(self, h1: np.ndarray) -> np.ndarray:
        """Decoder layers 2 and 3 from the first hidden layer's activations (..., h) → joint units (..., d)."""
        h = h1 @ self._dec.WT[1]
        h += self._dec.b[1]
        np.maximum(h, 0.0, out=h)
        out = h @ self._W3T
        out += self._b3
        return out

    def _layer1_phase(self, x) -> np.ndarray:
        """W1x φ(x) + b1 of the decoder's first layer, (T, h); cached per phase grid (a server
        decodes the same preview / control grid again and again). Read-only: do not modify."""
        return self._per_grid(self._pre_x_cache, x, lambda x: self._phase_feats(x) @ self._dec_W1x.T + self._dec.b[0])

    def decode_per_phase(self, z_x: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Decode a latent that varies with phase (blending): z_x (T, k), x (T,) → (T, d)."""
        h = self._layer1_phase(x) + z_x @ self._W1zT
        np.maximum(h, 0.0, out=h)
        out = self._decode_hidden(h)
        if self.cfg.decoder_basis:  # Σ_b φ_b(x_t)(b_b + A_b z_t), one z per phase
            w = (z_x @ self._basis_AT).reshape(z_x.shape[0], self.cfg.decoder_basis, self.n_joints) + self._basis_b
            out += np.einsum("tb,tbd->td", self._phi(x), w)
        return out

    def decoder_jacobian(self, z: np.ndarray, x: np.ndarray, smoothing: float | None = None):
        """μ_y(z, x_i) and ∂μ_y/∂z at each phase, joint units.

        Parameters
        ----------
        z : array, shape (k,) or (K, k)
        x : array, shape (n,)
        smoothing : float, optional
            β of a softplus log(1 + e^{βh})/β standing in for ReLU (a smooth surrogate of the
            decoder used by refinement's continuation; None = the exact ReLU decoder).

        Returns
        -------
        y : array, shape (n, d) or (K, n, d); jac : array, shape (n, d, k) or (K, n, d, k)
        """
        if smoothing is None:
            act = lambda h: np.maximum(h, 0.0)  # noqa: E731
            dact = lambda h: (h > 0).astype(np.float64)  # noqa: E731
        else:
            b = float(smoothing)
            act = lambda h: np.logaddexp(0.0, b * h) / b  # noqa: E731
            dact = lambda h: 0.5 * (1.0 + np.tanh(0.5 * b * h))  # noqa: E731  (= sigmoid(βh))
        zw = z @ self._W1zT  # (h,) or (K, h)
        pre1 = self._layer1_phase(x) + zw[..., None, :]  # (..., n, h)
        pre2 = act(pre1) @ self._dec.WT[1] + self._dec.b[1]
        y = act(pre2) @ self._W3T + self._b3
        # chain rule multiplied from the output side (d < k < h): per phase d·h² + d·h·k flops
        # instead of h²·k + d·h·k
        c = self._dec.W[2][..., None, :, :] * dact(pre2)[..., None, :]  # (..., n, d, h)
        c = np.matmul(c, self._dec.W[1]) * dact(pre1)[..., None, :]  # batched BLAS, (..., n, d, h)
        jac = np.matmul(c, self._dec_W1z) * self._y_std[:, None]  # (..., n, d, k)
        if self.cfg.decoder_basis:  # the linear part: its Jacobian Σ_b φ_b(x) A_b is the same for every z
            y = y + self._linear_part(z, x)
            jac = jac + np.einsum("nb,bdk->ndk", self._phi(x), self._basis_A)
        return y, jac

    def mean_trajectory(self, latent: LatentGaussian, x) -> np.ndarray:
        """The trajectory a robot executes for ``latent``: μ_y(μ_z, x), shape (T, d)."""
        return self.decode(latent.mean, self.check_phases(x))

    def sample(self, latent: LatentGaussian, x, n: int, rng: np.random.Generator | int | None = None) -> np.ndarray:
        """n trajectories, each with ONE z ~ q(z) held constant over the trajectory (paper Sec. III-C).

        Returns
        -------
        array, shape (n, T, d)
        """
        if n < 1:
            raise ValueError(f"number of samples must be >= 1, got {n}")
        rng = np.random.default_rng(rng)
        z = latent.mean + rng.standard_normal((n, self.latent_dim)) * latent.std
        return self.decode(z, self.check_phases(x))

    def trajectory_std(self, latent: LatentGaussian, x, n_samples: int = 64, seed: int = 0) -> np.ndarray:
        """Per-point standard deviation of the trajectory distribution (Monte Carlo), shape (T, d)."""
        return self.sample(latent, x, n_samples, seed).std(0)

    # ------------------------------------------------------------------ blending
    @staticmethod
    def blend_latent(a: LatentGaussian, b: LatentGaussian, omega) -> tuple[np.ndarray, np.ndarray]:
        """q_b(z | x) ∝ q_a(z)^ω(x) q_b(z)^(1−ω(x)) (paper Eq. 4), per phase.

        Parameters
        ----------
        omega : array, shape (T,), values in [0, 1]

        Returns
        -------
        mean, var : array, shape (T, k)
        """
        w = np.asarray(omega, dtype=np.float64)[:, None]
        if not np.all(np.isfinite(w)) or w.min() < 0 or w.max() > 1:
            raise ValueError("blending weights ω(x) must be finite and in [0, 1]")
        prec = w / a.var + (1 - w) / b.var
        mean = (w * a.mean / a.var + (1 - w) * b.mean / b.var) / prec
        return mean, 1.0 / prec

    def blend(self, a: LatentGaussian, b: LatentGaussian, omega: Callable | np.ndarray, x,
              eps: np.ndarray | None = None) -> np.ndarray:
        """Blended trajectory z(x) = μ_b(x) + ε σ_b(x) with ONE ε per trajectory (smooth in x).

        Parameters
        ----------
        omega : callable x -> ω(x) in [0, 1], or array shape (T,)
        eps : array, shape (k,), optional; None decodes the blended mean (ε = 0)

        Returns
        -------
        array, shape (T, d)
        """
        x = self.check_phases(x)
        w = omega(x) if callable(omega) else np.asarray(omega, dtype=np.float64)
        if np.shape(w) != x.shape:
            raise ValueError(f"ω(x) must give one weight per phase: got shape {np.shape(w)} for {x.shape[0]} phases")
        mean, var = self.blend_latent(a, b, w)
        z = mean if eps is None else mean + np.asarray(eps)[None, :] * np.sqrt(var)
        return self.decode_per_phase(z, x)

    # ------------------------------------------------------------------ refinement
    def _refine_inputs(self, via_x, via_y, joint_mask, max_iterations, tol):
        x = self.check_phases(via_x, "via-point phase")
        if x.size == 0:
            raise ValueError("refinement needs at least one via-point")
        y = self.check_positions(via_y, x.shape[0])
        mask = self._check_mask(joint_mask, x.shape[0])
        if not mask.any():
            raise ValueError("joint mask selects no joint; expected at least one constrained joint")
        if max_iterations < 1 or not tol > 0:
            raise ValueError("max_iterations must be >= 1 and tol > 0")
        return x, y, mask

    def refine_map(self, latent: LatentGaussian, via_x, via_y, joint_mask=None, prior: str = "posterior",
                   noise_std=None, max_iterations: int = 50, tol: float = 1e-6,
                   latent_bound: float = 5.0) -> RefinementResult:
        """MAP refinement: μ̃ = argmin_z Σ_ij m_ij (y_ij − μ_y(z, x_i)_j)² / s_j² + (z − m)ᵀ P (z − m).

        A regularized least-squares step instead of meeting the via-points exactly. ``prior``:
        ``"posterior"`` — m, P = the mean and precision diag(1/σ²) of ``latent`` (normally
        q(z | via-points)); ``"standard"`` — the model's prior N(0, I). For a decoder that is linear
        in z (``decoder_basis`` > 0 with ``residual_scale`` 0) and the standard prior this is exactly
        Gaussian conditioning of the latent linear-Gaussian model — ProMP conditioning in the latent.
        Solved by Levenberg–Marquardt with the decoder's exact Jacobian (one step when it is linear).

        Parameters
        ----------
        noise_std : float or array (d,), optional
            s_j, the via-point standard deviation in joint units; default σ_y · the joint's
            normalization std (the decoder's own noise level).

        Returns
        -------
        RefinementResult with latent N(μ̃, diag of the Laplace covariance (JᵀJ/s² + P)⁻¹);
        ``max_error`` / ``reachable`` as in :meth:`refine` (a MAP fit usually does not meet
        tol: it is not meant to), ``sample_mean_error`` = ``max_error``.
        """
        x, y, mask = self._refine_inputs(via_x, via_y, joint_mask, max_iterations, tol)
        if prior == "posterior":
            m, prec = np.asarray(latent.mean, dtype=np.float64), 1.0 / np.asarray(latent.var, dtype=np.float64)
        elif prior == "standard":
            m, prec = np.zeros(self.latent_dim), np.ones(self.latent_dim)
        else:
            raise ValueError(f"MAP prior '{prior}' unknown; expected 'posterior' or 'standard'")
        s = self.cfg.sigma_y * self._y_std if noise_std is None else np.broadcast_to(
            np.asarray(noise_std, dtype=np.float64), (self.n_joints,))
        if not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise ValueError(f"noise_std must be > 0 (joint units), got {noise_std}")
        wgt = mask.astype(np.float64) / s[None, :]  # residual weights m_ij / s_j

        def terms(z):
            y_hat, jac = self.decoder_jacobian(z, x)
            r = ((y - y_hat) * wgt).reshape(-1)
            J = (jac * wgt[:, :, None]).reshape(-1, self.latent_dim)
            dz = z - m
            return r, J, float(r @ r + dz @ (prec * dz)), y_hat

        z = np.clip(latent.mean, -latent_bound, latent_bound).astype(np.float64)
        r, J, cost, y_hat = terms(z)
        history = [float(np.abs((y - y_hat) * mask).max())]
        lam, it, reason = 0.0, 0, "budget"
        while it < max_iterations:
            it += 1
            H = J.T @ J + np.diag(prec)
            g = J.T @ r - prec * (z - m)  # −½ ∇cost
            step = np.clip(z + np.linalg.solve(H + lam * np.diag(np.diag(H)), g), -latent_bound, latent_bound) - z
            r2, J2, c2, y2 = terms(z + step)
            if c2 <= cost:
                converged = cost - c2 <= 1e-12 * max(1.0, cost) or np.abs(step).max() < 1e-10
                z, r, J, cost, y_hat = z + step, r2, J2, c2, y2
                lam = lam / 3.0
                history.append(float(np.abs((y - y_hat) * mask).max()))
                if converged:
                    reason = "converged (MAP)"
                    break
            else:
                lam = max(lam * 4.0, 1e-6)
                history.append(history[-1])
                if lam > 1e8:
                    reason = "converged (MAP, no descent step)"
                    break
        cov = np.linalg.inv(J.T @ J + np.diag(prec))
        err = (y - y_hat) * mask
        max_err = float(np.abs(err).max())
        return RefinementResult(latent=LatentGaussian(z, np.diag(cov).copy()), max_error=max_err, errors=err,
                                sample_mean_error=max_err, iterations=it, reachable=max_err <= tol, reason=reason,
                                error_history=np.minimum.accumulate(np.array(history)))

    def refine(self, latent: LatentGaussian, via_x, via_y, joint_mask=None, max_iterations: int = 200,
               tol: float = 1e-6, n_samples: int = 16, seed: int = 0, sigma_target: np.ndarray | None = None,
               sigma_iterations: int = 5, max_restarts: int = 5,
               smoothing_schedule: Sequence[float] = (3.0, 10.0, 30.0, 100.0), latent_bound: float = 5.0,
               objective: str = "exact", map_prior: str = "posterior", noise_std=None) -> RefinementResult:
        """Deployment-time refinement of (μ̃, σ̃) (paper Eq. 5 and appendix).

        ``objective="exact"`` (default) is described below. ``objective="map"`` instead returns the
        MAP latent of a regularized least-squares problem (see :meth:`refine_map`; ``map_prior``,
        ``noise_std``, ``max_iterations``, ``tol``, ``latent_bound`` are passed on) — it trades
        meeting the via-points exactly for staying where the model has seen demonstrations.

        Stage 1 moves μ̃ — starting at the given (posterior) mean — so that the trajectory the robot
        executes, μ_y(μ̃, x), passes through the via-points: damped Gauss–Newton
        (Levenberg–Marquardt) in float64 with the decoder's exact Jacobian. Stage 2 keeps μ̃ and fits
        σ̃ to the paper's objective Σ_i ||y_i − 1/K Σ_k μ_y(μ̃ + ε_k σ̃, x_i)||² + ||σ* − σ̃||² with
        K FIXED samples ε_k (common random numbers: fresh samples at every step leave Monte-Carlo
        noise of ~1e-2 that no optimizer removes).

        Unreachable via-points: stage 1 stops at a stationary point when no damped step (damping up
        to 1e6) decreases the squared error or the gradient Jᵀr vanishes; it then restarts from
        small seeded perturbations (``max_restarts``) while iterations remain (all runs share the
        ``max_iterations`` budget). If the best fit still misses by more than ``tol``, the result
        says ``reachable=False`` and carries that best fit and its residuals — never a silent miss.

        Parameters
        ----------
        latent : LatentGaussian, the initialization (normally the posterior from :meth:`condition`)
        via_x : array, shape (n,)
        via_y : array, shape (n, d)
        joint_mask : array of bool, shape (n, d) or (d,), optional; joints to meet (default all)
        sigma_target : array, shape (k,), σ*; default the initial std
        latent_bound : float
            μ̃ stays in the box |μ̃_i| ≤ latent_bound (units of the prior's std). The ReLU decoder
            extrapolates linearly, so almost any target is "reachable" with a huge z — far outside
            what was demonstrated. Via-points that need more are reported unreachable.
        """
        if objective == "map":
            return self.refine_map(latent, via_x, via_y, joint_mask, prior=map_prior, noise_std=noise_std,
                                   max_iterations=max_iterations, tol=tol, latent_bound=latent_bound)
        if objective != "exact":
            raise ValueError(f"refinement objective '{objective}' unknown; expected 'exact' or 'map'")
        x, y, mask = self._refine_inputs(via_x, via_y, joint_mask, max_iterations, tol)
        mf = mask.astype(np.float64)

        smoothing = [None]

        def residual(z):
            y_hat, jac = self.decoder_jacobian(z, x, smoothing[0])
            r = (y - y_hat) * mf
            return r, jac * mf[:, :, None]

        eye = np.eye(self.latent_dim)
        rng = np.random.default_rng(seed)
        history = []  # exact-decoder max error at the best μ̃ so far, one entry per iteration
        best = [None, math.inf]  # the iterate with the smallest exact error seen in any stage

        def record(mu, r):
            # r is exact when no smoothing is active; on a smooth surrogate, decode exactly once more
            err = float(np.abs(r).max()) if smoothing[0] is None else float(np.abs((y - self.decode(mu, x)) * mf).max())
            if err < best[1]:
                best[0], best[1] = mu.copy(), err
            history.append(best[1])

        def levenberg_marquardt(mu, budget):
            """Levenberg–Marquardt with Nielsen's damping update (Madsen, Nielsen & Tingleff 2004,
            "Methods for non-linear least squares problems", Alg. 3.16); returns (mu, r, its, reason).

            δ = (JᵀJ + λI)⁻¹ Jᵀ r; the step is accepted when the squared error decreases, and λ
            follows the gain ratio ρ between actual and predicted decrease (λ ← λ·max(1/3, 1−(2ρ−1)³)
            on success, λ ← λν, ν ← 2ν on failure)."""
            r, jac = residual(mu)
            if not history:
                record(mu, r)
            cost = float((r ** 2).sum())
            J = jac.reshape(-1, self.latent_dim)
            A, g = J.T @ J, J.T @ r.reshape(-1)
            lam, nu, it = 1e-3 * max(float(np.diag(A).max()), 1e-12), 2.0, 0
            while it < budget:
                if np.abs(r).max() <= 0.1 * tol:
                    return mu, r, it, "converged"
                if np.abs(g).max() < 1e-15 * max(1.0, cost):
                    return mu, r, it, "stationary (zero gradient)"
                it += 1
                step = np.clip(mu + np.linalg.solve(A + lam * eye, g), -latent_bound, latent_bound) - mu
                r_new, jac_new = residual(mu + step)
                c_new = float((r_new ** 2).sum())
                predicted = float(step @ (lam * step + g))  # = cost − ‖r − Jδ‖² (> 0)
                rho = min((cost - c_new) / max(predicted, 1e-300), 1.0)  # > 1 only lowers λ by the cap
                if c_new < cost:
                    mu, r, cost = mu + step, r_new, c_new
                    J = jac_new.reshape(-1, self.latent_dim)
                    A, g = J.T @ J, J.T @ r.reshape(-1)
                    lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                    nu = 2.0
                else:
                    lam *= nu
                    nu *= 2.0
                    if lam > 1e8 * max(float(np.diag(A).max()), 1e-12):
                        record(mu, r)
                        return mu, r, it, "stationary (no descent step)"
                record(mu, r)
            return mu, r, it, "budget"

        def solve_from(mu0, budget):
            """1) LM on the exact decoder from mu0 (enough when mu0 lies in the basin).
            2) Otherwise continuation in the decoder's smoothness: the exact decoder is piecewise
               linear (ReLU), so the squared error has kinks where LM stalls far from a solution.
               LM runs on smooth surrogates (softplus of increasing sharpness β), then polishes on
               the exact decoder — the trajectory that is executed. The better fit is kept."""
            mu, r, it, reason = levenberg_marquardt(mu0, max(1, budget // 4))
            if np.abs(r).max() > tol and budget - it > len(smoothing_schedule) and smoothing_schedule:
                mu2 = mu0
                for beta in smoothing_schedule:
                    smoothing[0] = beta
                    mu2, _, used, _ = levenberg_marquardt(mu2, max(1, (budget // 4) // len(smoothing_schedule)))
                    it += used
                smoothing[0] = None
                mu2, r2, used, reason2 = levenberg_marquardt(mu2, budget - it)
                it += used
                if np.abs(r2).max() < np.abs(r).max():
                    mu, r, reason = mu2, r2, reason2
            return mu, r, it, reason

        # Restarts (exact LM only) from small seeded perturbations of the best point while the
        # shared iteration budget lasts; the best fit over all runs is kept.
        mu, r, it, reason = solve_from(np.clip(latent.mean, -latent_bound, latent_bound).astype(np.float64),
                                       max_iterations)
        restarts = 0
        while np.abs(r).max() > tol and it < max_iterations and restarts < max_restarts:
            restarts += 1
            start = mu + rng.standard_normal(self.latent_dim) * 0.05 * np.sqrt(latent.var)
            mu2, r2, it2, reason2 = levenberg_marquardt(start, max_iterations - it)
            it += it2
            if np.abs(r2).max() < np.abs(r).max():
                mu, r, reason = mu2, r2, reason2
        if best[1] < float(np.abs(r).max()):  # an intermediate iterate (e.g. of the continuation) fit better
            mu = best[0]
            r = residual(mu)[0]
        max_err = float(np.abs(r).max())
        if history and max_err < history[-1]:  # a restart that started (and stopped) on a better point
            history[-1] = max_err
        if max_err <= tol:
            reason = "converged"
        elif restarts:
            reason += f" after {restarts} restarts"

        # Stage 2: σ̃ with fixed ε (paper objective in σ̃ at the refined mean).
        eps = np.random.default_rng(seed).standard_normal((n_samples, self.latent_dim))
        s_target = np.sqrt(latent.var) if sigma_target is None else np.asarray(sigma_target, dtype=np.float64)
        s = s_target.copy()

        def s_residual(s):
            # residual [y − ȳ(σ̃); σ* − σ̃] and the Jacobian of the model part [∂ȳ/∂σ̃; I]
            ys, js = self.decoder_jacobian(mu[None] + eps * s[None], x)  # (K, n, d), (K, n, d, k)
            r_y = ((y - ys.mean(0)) * mf).reshape(-1)
            j_y = (js * eps[:, None, None, :]).mean(0) * mf[:, :, None]
            return (np.concatenate([r_y, s_target - s]),
                    np.concatenate([j_y.reshape(-1, s.size), np.eye(s.size)]))

        if sigma_iterations > 0:
            rs, jm = s_residual(s)
            c = float(rs @ rs)
            lam_s = 1e-3
            for _ in range(sigma_iterations):
                step = np.linalg.solve(jm.T @ jm + lam_s * np.eye(s.size), jm.T @ rs)
                s_new = np.maximum(s + step, 1e-6)
                rs_new, jm_new = s_residual(s_new)
                c_new = float(rs_new @ rs_new)
                if c_new < c:
                    s, rs, jm, c, lam_s = s_new, rs_new, jm_new, c_new, lam_s / 5
                else:
                    lam_s *= 4
                    if lam_s > 1e8:
                        break
        y_bar = self.decode(mu[None] + eps * s[None], x).mean(0)
        return RefinementResult(
            latent=LatentGaussian(mu, s ** 2), max_error=max_err, errors=r, iterations=it,
            sample_mean_error=float(np.abs((y - y_bar) * mf).max()), reachable=max_err <= tol, reason=reason,
            error_history=np.array(history))
