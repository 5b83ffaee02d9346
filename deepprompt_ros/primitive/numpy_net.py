"""The float64 numpy twin of a trained :class:`deepprompt_ros.model.network.DeepProMPNet`, used by
every deployment-time operation of :class:`deepprompt_ros.primitive.deep_promp.DeepProMP`.

Small MLPs are dominated by per-call overhead in torch, and refinement needs float64 to reach
1e-6 rad, so the weights are exported once into numpy: the via-point and context encoders with
the shared head, and the decoder in joint units (the de-normalization folded into its output
layer, the phase part of its first layer cached per phase grid), its exact Jacobian with respect
to z and a smooth (softplus) surrogate of it for refinement's continuation. Images keep going
through the torch CNN.

Units: x phases in [0, 1]; y joint positions in joint units (rad); contexts raw. Shapes use
T = phases, d = joints, k = latent dimension, h = hidden width, n_b = basis functions.
"""
from __future__ import annotations

import math
import statistics
from typing import Callable

import numpy as np
import torch

from deepprompt_ros.model.checkpoint import Normalization
from deepprompt_ros.model.network import LOGVAR_MAX, DeepProMPNet, mode_thresholds
from deepprompt_ros.model.phase import phase_basis, phase_features

__all__ = ["NumpyMLP", "NumpyNet", "METRIC_PHASES"]

#: Phases (equally spaced on [0, 1]) on which :meth:`NumpyNet.trajectory_metric_inverse` measures a
#: change of the trajectory.
METRIC_PHASES = 101


class NumpyMLP:
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


class NumpyNet:
    """Encoders, head and decoder of ``net`` in float64 numpy, in joint units (``normalization``).

    Nothing here validates its inputs: :class:`deepprompt_ros.primitive.deep_promp.DeepProMP` does.
    The per-phase-grid caches are safe to share between threads (replaced atomically).
    """

    def __init__(self, net: DeepProMPNet, normalization: Normalization):
        self.cfg = net.cfg
        self.norm = normalization
        self._via = NumpyMLP(net.via_encoder)
        self._ctx = {n: NumpyMLP(m) for n, m in net.context_encoders.items()}
        self._head_W = net.head.weight.detach().double().numpy().copy()
        self._head_b = net.head.bias.detach().double().numpy().copy()
        self._head_WT = np.ascontiguousarray(self._head_W.T)
        self._dec = NumpyMLP(net.decoder)
        k, k_l = self.cfg.latent_dim, self.cfg.latent_linear
        self.k_lin = k_l  # z[:k_l] drives the linear part alone, z[k_l:] the MLP (0: both read all of z)
        nb, d = self.cfg.decoder_basis, self.cfg.n_joints
        if nb:  # residual decoder: the MLP's output layer carries the factor s, the linear part is separate
            self._dec.W[-1] = self._dec.W[-1] * self.cfg.residual_scale
            self._dec.b[-1] = self._dec.b[-1] * self.cfg.residual_scale
            self._dec.WT[-1] = np.ascontiguousarray(self._dec.W[-1].T)
            ystd = np.asarray(normalization.y_std, dtype=np.float64)
            # Φ(x)(b + A z) in joint units: b (n_b, d), A as (k_a, n_b·d) for z @ A and (n_b, d, k_a) for the
            # Jacobian, k_a = k_l or k
            k_a = k_l or k
            bw = net.basis.weight.detach().double().numpy().reshape(nb, d, k_a) * ystd[None, :, None]
            self._basis_b = net.basis.bias.detach().double().numpy().reshape(nb, d) * ystd[None, :]
            self._basis_A = np.ascontiguousarray(bw)
            self._basis_A_rows = self._basis_A.reshape(nb, d * k_a)  # Φ(x) @ this: Φ(x) A as (T, d·k_a)
            self._basis_AT = np.ascontiguousarray(bw.reshape(nb * d, k_a).T)
        self._modes = None  # decoder_modes K >= 2: the offsets m_k (K, n_b, d) in joint units and the thresholds
        if self.cfg.decoder_modes:
            ystd = np.asarray(normalization.y_std, dtype=np.float64)
            self._modes = net.mode_offsets.detach().double().numpy().reshape(-1, nb, d) * ystd
            cumulative = [0.0] + [float(v) for v in net.mode_cumulative_shares.tolist()]
            self._mode_thresholds = np.asarray(mode_thresholds(cumulative[1:]))
            inv = statistics.NormalDist().inv_cdf
            #: the median of each mode's interval of the first z_nl coordinate, and log π_k
            self.mode_medians = np.array([inv(0.5 * (a + b)) for a, b in zip(cumulative[:-1], cumulative[1:])])
            self.mode_log_shares = np.log(np.maximum(np.diff(cumulative), 1e-300))
            self._mode_cache: dict[bytes, np.ndarray] = {}
        self._phi_cache: dict[bytes, np.ndarray] = {}
        k_n = self.cfg.latent_nonlinear
        self._dec_W1z = self._dec.W[0][:, :k_n]  # the MLP's first layer: z_nl part, phase part
        self._dec_W1x = self._dec.W[0][:, k_n:]
        self.y_mean = np.asarray(normalization.y_mean, dtype=np.float64)
        self.y_std = np.asarray(normalization.y_std, dtype=np.float64)
        # decode() fast path: contiguous transposed weights, the output layer with the
        # de-normalization folded in, and the phase part of layer 1 cached per phase grid
        self._W1zT = np.ascontiguousarray(self._dec_W1z.T)
        self._W3T = np.ascontiguousarray(self._dec.W[2].T * self.y_std)
        self._b3 = self._dec.b[2] * self.y_std + self.y_mean
        self._no_mlp = bool(nb) and self.cfg.residual_scale == 0.0  # s·MLP ≡ 0: skipped in decode_nonlinear
        self._pre_x_cache: dict[bytes, np.ndarray] = {}

    def trajectory_metric_inverse(self) -> np.ndarray:
        """(k_l, k_l) M⁻¹, M = Σ_t (Φ(x_t) A)ᵀ Φ(x_t) A over :data:`METRIC_PHASES` equally spaced phases
        (joint units, all joints; a ridge of 1e-9 of its mean diagonal): ‖Φ A Δ‖² ≈ Δᵀ M Δ is the
        squared change of the linear part's trajectory for a change Δ of z_lin. Computed once."""
        mi = self.__dict__.get("_metric_inverse")
        if mi is None:
            rows = self.trajectory_rows()
            m = rows.T @ rows
            m.flat[::self.k_lin + 1] += 1e-9 * max(float(np.trace(m)) / max(self.k_lin, 1), 1e-300)
            mi = np.linalg.inv(m)
            mi.flags.writeable = False
            self._metric_inverse = mi
        return mi

    def mode_latent_offsets(self) -> np.ndarray:
        """(K, k_l) u_k: each mode's offset Φ m_k in the coordinates of z_lin, the Δ that minimizes
        ‖Φ(x_t)(A Δ − m_k)‖² over the :data:`METRIC_PHASES` phases (joint units), M⁻¹ (Φ A)ᵀ Φ m_k
        (:meth:`trajectory_metric_inverse`). ``decoder_modes`` only; computed once."""
        u = self.__dict__.get("_mode_latent_offsets")
        if u is None:
            per_mode = self._per_mode(np.linspace(0.0, 1.0, METRIC_PHASES)).reshape(self._modes.shape[0], -1)
            u = per_mode @ self.trajectory_rows() @ self.trajectory_metric_inverse()
            u.flags.writeable = False
            self._mode_latent_offsets = u
        return u

    def mode_probabilities(self, mean: float, var: float) -> np.ndarray:
        """(K,) the probability of each mode's interval of z_nl's first coordinate under N(mean, var)
        (``decoder_modes``; the shares under N(0, 1)); one-hot where var is 0, NaN where mean or var is not
        finite or var < 0 (an overflow, which the callers' finiteness checks refuse)."""
        mean, var = float(mean), float(var)
        k = self._mode_thresholds.shape[0] + 1
        if not (math.isfinite(mean) and math.isfinite(var) and var >= 0.0):
            return np.full(k, np.nan)
        if var == 0.0:
            return np.eye(k)[int(self.mode_of(np.array([mean])))]
        gate = statistics.NormalDist(mean, math.sqrt(var))
        return np.diff([0.0, *(gate.cdf(float(t)) for t in self._mode_thresholds), 1.0])

    def metric_design(self, x: np.ndarray) -> np.ndarray:
        """Φ(x) A M⁻¹ at phases x (n,), shape (n, d, k_l): :meth:`linear_design`'s matrix times
        :meth:`trajectory_metric_inverse`, from Φ(x) and A M⁻¹ (computed once)."""
        am = self.__dict__.get("_metric_rows")
        if am is None:
            am = np.ascontiguousarray((self._basis_A @ self.trajectory_metric_inverse()).reshape(
                self._basis_A.shape[0], -1))
            am.flags.writeable = False
            self._metric_rows = am
        return (self._phi(x) @ am).reshape(-1, *self._basis_A.shape[1:])

    def trajectory_rows(self) -> np.ndarray:
        """(METRIC_PHASES · d, k_l) Φ(x_t) A at the :data:`METRIC_PHASES` phases, rows (phase, joint): the
        change of the linear part's trajectory for a change of z_lin (joint units). Computed once."""
        rows = self.__dict__.get("_trajectory_rows")
        if rows is None:
            rows = np.ascontiguousarray(self.linear_design(np.linspace(0.0, 1.0, METRIC_PHASES))[1]
                                        .reshape(-1, self.k_lin))
            rows.flags.writeable = False
            self._trajectory_rows = rows
        return rows

    @property
    def decoder_reads_z_nl(self) -> bool:
        """Whether the decoder's output depends on z_nl = z[k_l:]: through the MLP (not when z_nl is
        empty or the residual's factor s is 0) or through the mode it chooses (``decoder_modes``)."""
        return self.cfg.latent_nonlinear > 0 and (not self._no_mlp or self._modes is not None)

    @property
    def mlp_active(self) -> bool:
        """Whether the decoder's MLP residual is on (a residual factor s > 0, or no linear basis)."""
        return not self._no_mlp

    @property
    def has_modes(self) -> bool:
        """Whether the decoder has several modes chosen by z_nl (``decoder_modes``)."""
        return self._modes is not None

    def mode_of(self, z_nl: np.ndarray) -> np.ndarray | int:
        """The mode each z_nl (..., k − k_l) chooses (``decoder_modes``; :func:`mode_of_latent`)."""
        return np.searchsorted(self._mode_thresholds, np.asarray(z_nl)[..., 0], side="right")

    def _mode_part(self, z_nl: np.ndarray, x) -> np.ndarray:
        """Φ(x) m_k of the mode each z_nl chooses, joint units: z_nl (k − k_l,) → (T, d), (n, k − k_l) → (n, T, d)."""
        return self._per_mode(x)[self.mode_of(z_nl)]

    def mode_offsets(self, x) -> np.ndarray:
        """Φ(x) m_k of every mode of the decoder at phases x (T,), joint units, (K, T, d) (read-only)."""
        return self._per_mode(x)

    def _per_mode(self, x) -> np.ndarray:
        """Φ(x) m_k of every mode, joint units, (K, T, d); cached per phase grid (read-only)."""
        return self._per_grid(self._mode_cache, x, lambda x: np.einsum("tb,kbd->ktd", self._phi(x), self._modes))

    @property
    def context_names(self) -> list[str]:
        """The low-dimensional context modalities that have an encoder."""
        return list(self._ctx)

    # ------------------------------------------------------------------ encoders
    def _head(self, feat: np.ndarray):
        out = feat @ self._head_WT
        out += self._head_b
        k = self.cfg.latent_dim
        raw = out[..., k:]
        if self.cfg.variance_head == "exp":  # as in the network (DeepProMPNet._head)
            var = np.exp(np.minimum(raw, LOGVAR_MAX)) + self.cfg.var_floor
        else:
            var = np.logaddexp(0.0, raw) + self.cfg.var_floor  # softplus + floor
        return out[..., :k], var

    def _phase_feats(self, x: np.ndarray) -> np.ndarray:
        return phase_features(x, self.cfg.phase_type, self.cfg.phase_harmonics)

    def encode_via_points(self, x: np.ndarray, y: np.ndarray):
        """Per-element q(z | a_i): x (n,), y (n, d) rad → μ_i, σ²_i (n, k)."""
        yn = (y - self.y_mean) / self.y_std
        return self._head(self._via(np.concatenate([self._phase_feats(x), yn], 1)))

    def encode_context(self, name: str, c: np.ndarray):
        """q(z | c_i): c (m, c_dim) raw units → μ_i, σ²_i (m, k)."""
        cn = (c - self.norm.ctx_mean[name]) / self.norm.ctx_std[name]
        return self._head(self._ctx[name](cn))

    # ------------------------------------------------------------------ decoder
    def decode(self, z, x) -> np.ndarray:
        """μ_y(z, x) in joint units: z (k,) → (T, d), z (n, k) → (n, T, d); x (T,)."""
        z = np.asarray(z, dtype=np.float64)
        out = self._decode_shared(z, x)
        if self._modes is not None:
            out += self._mode_part(z[..., self.k_lin:], x)
        return out

    def decode_weighted(self, z: np.ndarray, x, mode_weights: np.ndarray | None) -> np.ndarray:
        """μ_y(z, x) with the modes' offsets weighted by ``mode_weights`` (K,) instead of the one z's
        z_nl chooses (:attr:`LatentGaussian.mode_weights`), joint units: z (k,) → (T, d). None, or a
        decoder of one mode: :meth:`decode`."""
        if mode_weights is None or self._modes is None:
            return self.decode(z, x)
        out = self._decode_shared(np.asarray(z, dtype=np.float64), x)
        out += np.einsum("k,ktd->td", np.asarray(mode_weights, dtype=np.float64), self._per_mode(x))
        return out

    def _decode_shared(self, z: np.ndarray, x) -> np.ndarray:
        """μ_y(z, x) without the modes' offsets (the part every mode shares), joint units: z (k,) → (T, d),
        (n, k) → (n, T, d); x (T,)."""
        if self._no_mlp:  # the linear part and the joints' mean alone
            out = self._linear_part(z, x)
            out += self._b3
            return out
        out = self._mlp_part(z[..., self.k_lin:], x)
        if self.cfg.decoder_basis:
            out += self._linear_part(z, x)
        return out

    def decode_nonlinear(self, z_nl: np.ndarray, x: np.ndarray) -> np.ndarray:
        """The decoder without its linear part, s·MLP(z_nl, x) plus the joints' mean, joint units:
        z_nl (k − k_l,) → (T, d), (n, k − k_l) → (n, T, d); x (T,). (The whole decoder when there is no
        linear basis; with ``latent_linear`` 0, z_nl is all of z.) A residual decoder with s = 0 has no
        MLP part (its output layer is 0): the MLP is not evaluated. With ``decoder_modes`` the offset
        Φ(x) m_k of the mode z_nl chooses is part of it."""
        if self._no_mlp:
            out = np.empty((*z_nl.shape[:-1], np.shape(x)[0], self._b3.shape[0]))
            out[...] = self._b3
        else:
            out = self._mlp_part(z_nl, x)
        if self._modes is not None:
            out += self._mode_part(z_nl, x)
        return out

    def _mlp_part(self, z_nl: np.ndarray, x) -> np.ndarray:
        """s·MLP(z_nl, x) plus the joints' mean (the output layer's bias), joint units: z_nl (k − k_l,) →
        (T, d), (n, k − k_l) → (n, T, d); x (T,)."""
        pre_x = self._layer1_phase(x)  # (T, h)
        if z_nl.ndim == 1:
            h = pre_x + z_nl @ self._W1zT
        else:
            h = pre_x[None] + (z_nl @ self._W1zT)[:, None, :]
        np.maximum(h, 0.0, out=h)
        return self._decode_hidden(h)

    def linear_design(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The linear part at phases x (n,) in joint units: Φ(x) b (n, d) and its matrix in z_lin,
        Φ(x) A (n, d, k_l), so the part is Φ(x) b + Φ(x) A z_lin (``latent_linear`` > 0 only)."""
        phi = self._phi(x)
        return phi @ self._basis_b, (phi @ self._basis_A_rows).reshape(-1, *self._basis_A.shape[1:])

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
        z (n, k) → (n, T, d); reads z_lin = z[..., :k_l] only when ``latent_linear`` k_l > 0."""
        nb, d = self.cfg.decoder_basis, self.cfg.n_joints
        if self.k_lin:
            z = z[..., :self.k_lin]
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

    def decode_per_phase(self, z_x: np.ndarray, x: np.ndarray, mode_weights: np.ndarray | None = None) -> np.ndarray:
        """Decode a latent that varies with phase (blending): z_x (T, k), x (T,) → (T, d); with
        ``decoder_modes``, ``mode_weights`` (T, K) (rows summing to 1) weighs the modes' offsets instead of
        the mode each row of z_x chooses."""
        h = self._layer1_phase(x) + z_x[:, self.k_lin:] @ self._W1zT
        np.maximum(h, 0.0, out=h)
        out = self._decode_hidden(h)
        if self.cfg.decoder_basis:  # Σ_b φ_b(x_t)(b_b + A_b z_t), one z per phase
            w = ((z_x[:, :self.k_lin] if self.k_lin else z_x) @ self._basis_AT).reshape(z_x.shape[0], self.cfg.decoder_basis, self.cfg.n_joints) + self._basis_b
            if self._modes is not None and mode_weights is None:
                w = w + self._modes[self.mode_of(z_x[:, self.k_lin:])]
            elif self._modes is not None:
                w = w + np.einsum("tk,kbd->tbd", np.asarray(mode_weights, dtype=np.float64), self._modes)
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
        k_l = self.k_lin
        zw = z[..., k_l:] @ self._W1zT  # (h,) or (K, h)
        pre1 = self._layer1_phase(x) + zw[..., None, :]  # (..., n, h)
        pre2 = act(pre1) @ self._dec.WT[1] + self._dec.b[1]
        y = act(pre2) @ self._W3T + self._b3
        # chain rule multiplied from the output side (d < k < h): per phase d·h² + d·h·k flops
        # instead of h²·k + d·h·k
        c = self._dec.W[2][..., None, :, :] * dact(pre2)[..., None, :]  # (..., n, d, h)
        c = np.matmul(c, self._dec.W[1]) * dact(pre1)[..., None, :]  # batched BLAS, (..., n, d, h)
        jac = np.matmul(c, self._dec_W1z) * self.y_std[:, None]  # (..., n, d, k − k_l)
        if self.cfg.decoder_basis:  # the linear part: its Jacobian Σ_b φ_b(x) A_b is the same for every z
            y = y + self._linear_part(z, x)
            if self._modes is not None:  # the mode's offset: constant between the modes' thresholds
                y = y + self._mode_part(z[..., k_l:], x)
            jac_lin = np.einsum("nb,bdk->ndk", self._phi(x), self._basis_A)
            if k_l:  # ∂/∂z_lin is the linear part's alone, ∂/∂z_nl the MLP's alone
                jac = np.concatenate([np.broadcast_to(jac_lin, (*jac.shape[:-1], k_l)), jac], -1)
            else:
                jac = jac + jac_lin
        return y, jac
