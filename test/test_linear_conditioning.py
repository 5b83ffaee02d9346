"""Conditioning a split latent (ModelConfig.latent_linear): z_lin exactly on the via-points, z_nl
candidates weighted by the marginal likelihood (primitive.linear_conditioning), on small models built
here — the linear part the PPCA of synthetic demonstrations (training.basis.pca_basis), the MLP random
or built by hand to make two modes. Also: partial via-points and MAP refinement of plain latents,
and a plain latent's numbers unchanged on the shipped reach model."""
import pathlib
import pickle
import time

import numpy as np
import pytest
import torch

from deepprompt_ros.baselines.promp import ProMP
from deepprompt_ros.common.results import Code, RequestError
from deepprompt_ros.model.checkpoint import Normalization, save_checkpoint
from deepprompt_ros.model.network import DeepProMPNet, ModelConfig
from deepprompt_ros.model.phase import phase_basis
from deepprompt_ros.primitive.deep_promp import DeepProMP
from deepprompt_ros.primitive.latent import LatentGaussian
from deepprompt_ros.primitive.linear_conditioning import _cholesky, _lower_solve, whitened_posterior
from deepprompt_ros.robots.spec import load_robot
from deepprompt_ros.server.config import ServerConfig, robot_limits
from deepprompt_ros.server.primitives_file import PrimitiveEntry, load_primitive
from deepprompt_ros.server.requests import BlendRequest, ConditionRequest, SampleRequest, ViaPointIn
from deepprompt_ros.server.service import PrimitiveServerCore
from deepprompt_ros.training.basis import pca_basis

torch.set_num_threads(1)
REPO = pathlib.Path(__file__).resolve().parent.parent
#: a trained Gen3 lite reach primitive with a plain latent (latent_linear 0, latent 16, context
#: 'object' (3)), trained with auto_select off
PLAIN_REACH = REPO / "test" / "data" / "gen3_lite_reach_plain.safetensors"


def demos(n=30, t=50, d=3, seed=0, y_mean=None):
    """n smooth demonstrations (t phases, d joints, rad): a base motion plus random linear, sine and
    quadratic terms. Returns x (t,), Y (n, t, d)."""
    rng = np.random.default_rng(seed)
    x = np.linspace(0, 1, t)
    base = np.stack([np.sin(np.pi * x * (j % 3 + 1)) * (j % 3 + 1) * 0.3 for j in range(d)], 1)
    if y_mean is not None:
        base = base + np.asarray(y_mean)
    a = rng.normal(0, 0.2, (n, 3, d))
    return x, base + a[:, 0, None] * x[:, None] + a[:, 1, None] * np.sin(2 * np.pi * x)[:, None] + \
        a[:, 2, None] * x[:, None] ** 2


def split_model(k_l=30, k_n=4, nb=10, d=3, rs=0.2, hidden=32, seed=0, contexts=(), names=None, y_mean=None, **cfg):
    """A split-latent DeepProMP whose linear part is the PPCA (λ = 0.05) of :func:`demos` and whose MLP
    and encoders are random. Returns (prim, x, Y)."""
    x, Y = demos(d=d, seed=seed, y_mean=y_mean)
    ym, ys = Y.reshape(-1, d).mean(0), Y.reshape(-1, d).std(0)
    norm = Normalization(ym, ys, {n: np.zeros(c) for n, c in contexts}, {n: np.ones(c) for n, c in contexts})
    mean, a, _ = pca_basis(phase_basis(x, nb, 1.0, False), (Y - ym) / ys, k_l, 0.05)
    torch.manual_seed(seed)
    net = DeepProMPNet(ModelConfig(n_joints=d, latent_dim=k_l + k_n, hidden=hidden, decoder_basis=nb,
                                   latent_linear=k_l, residual_scale=rs, context_dims=tuple(contexts), **cfg))
    with torch.no_grad():
        net.basis.bias.copy_(torch.as_tensor(mean))
        net.basis.weight.copy_(torch.as_tensor(a))
    return DeepProMP(net, norm, names or [f"j{i}" for i in range(d)]), x, Y


def random_via_points(rng, x, Y, n):
    """n via-points at distinct demo phases, each joint uniform between the demos' min and max there."""
    idx = np.sort(rng.choice(len(x), n, replace=False))
    return x[idx], rng.uniform(Y.min(0)[idx], Y.max(0)[idx])


# ------------------------------------------------------------------------------------------------
# the exact conditioning
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("n_via", [2, 8])  # 6 rows <= k_l = 12: observation form; 24 rows: information form
def test_the_linear_block_is_textbook_gaussian_conditioning(n_via):
    """With s = 0 the decoder is Φ(x)(b + A z_lin): the latent's z_lin mean and full covariance are
    those of dense Gaussian conditioning N(m, S) on y = H z + ε, computed here independently."""
    prim, x, Y = split_model(k_l=12, k_n=2, nb=6, rs=0.0)
    rng = np.random.default_rng(3)
    xv, yv = random_via_points(rng, x, Y, n_via)
    w = rng.uniform(0.5, 2.0, n_via)
    noise = 0.05
    lat = prim.condition(xv, yv, via_weights=w, via_noise=noise)
    assert lat.linear.form == ("observation" if 3 * n_via <= 12 else "information")
    lin_b, lin_a = prim._np.linear_design(xv)
    h = lin_a.reshape(-1, 12)
    r = (yv - prim._np.decode_nonlinear(np.zeros(2), xv) - lin_b).reshape(-1)
    R = np.diag((noise * np.tile(prim.norm.y_std, n_via) / np.repeat(np.sqrt(w), 3)) ** 2)
    S = np.eye(12)  # no context: the prior of z_lin is N(0, I)
    K = np.linalg.solve(h @ S @ h.T + R, h @ S).T
    np.testing.assert_allclose(lat.mean[:12], K @ r, atol=1e-9)
    np.testing.assert_allclose(lat.linear.cov(), S - K @ h @ S, atol=1e-9)
    np.testing.assert_allclose(lat.var[:12], np.diag(S - K @ h @ S), atol=1e-9)
    # sampling draws from that covariance (z_lin around the mean of the one candidate)
    z = lat.linear.draw(np.random.default_rng(0), 20000)[:, :12]
    np.testing.assert_allclose(np.cov(z.T), lat.linear.cov(), atol=0.03 * lat.linear.cov().diagonal().max())


def test_a_split_latent_computes_its_variance_when_read_and_stays_immutable():
    """The conditioning keeps the covariance as its factor; ``var`` read later is the diagonal of the
    full covariance, then z_nl's proposal variance; the latent cannot be changed and survives pickling."""
    prim, x, Y = split_model(k_l=12, k_n=2, nb=6, rs=0.2)
    xv, yv = random_via_points(np.random.default_rng(5), x, Y, 2)
    lat = prim.condition(xv, yv, via_noise=0.05)
    assert lat._var is None  # not computed by the conditioning
    agg = prim.aggregate(*prim.encode_via_points(xv, yv), np.ones(2))  # q_all: the z_nl proposal
    np.testing.assert_allclose(lat.var, np.concatenate([np.diag(lat.linear.cov()), agg.var[12:]]), rtol=1e-10,
                               atol=1e-14)
    assert lat.var is lat.var  # computed once
    with pytest.raises(AttributeError, match="immutable"):
        lat.mean = np.zeros(14)
    back = pickle.loads(pickle.dumps(lat))
    np.testing.assert_array_equal(back.var, lat.var)
    np.testing.assert_array_equal(back.mean, lat.mean)
    with pytest.raises(ValueError, match="needs its variance"):
        LatentGaussian(np.zeros(3))


@pytest.mark.parametrize("rs", [0.0, 0.2], ids=["no_mlp", "mlp"])
def test_no_weights_and_no_mask_give_the_latent_of_weights_1_and_every_joint(rs):
    """Without weights or a mask the conditioning skips weighing and selecting rows: the same numbers as
    weights of 1 and a mask of every joint, with one candidate (no MLP) or several."""
    prim, x, Y = split_model(rs=rs)
    rng = np.random.default_rng(6)
    for n_via in (2, 12):  # observation form (6 rows <= k_l = 30), information form (36 rows)
        xv, yv = random_via_points(rng, x, Y, n_via)
        a = prim.condition(xv, yv, via_noise=1e-6)
        b = prim.condition(xv, yv, np.ones(n_via), np.ones((n_via, 3), dtype=bool), via_noise=1e-6)
        assert a.linear.candidates.shape[0] == (1 if rs == 0 else 33)
        for got, want in ((a.mean, b.mean), (a.var, b.var), (a.linear.weights, b.linear.weights),
                          (a.linear.chol, b.linear.chol), (a.linear.via_error, b.linear.via_error)):
            np.testing.assert_array_equal(got, want)


def test_the_factorizations_are_numpys_and_a_matrix_not_positive_definite_is_refused():
    """The LAPACK gufuncs called directly give np.linalg's arrays; a matrix that is not positive
    definite raises LinAlgError as np.linalg.cholesky does; without the marginal likelihood the
    posterior is the same."""
    rng = np.random.default_rng(7)
    for m, k in ((6, 12), (24, 12)):  # observation and information form
        g, d = rng.normal(0, 3.0, (m, k)), rng.normal(0, 3.0, (3, m))
        form, chol, u, loglik = whitened_posterior(g, d)
        a = g @ g.T + np.eye(m) if form == "observation" else g.T @ g + np.eye(k)
        # u = (I + GᵀG)⁻¹ Gᵀ d directly
        np.testing.assert_allclose(u, np.linalg.solve(g.T @ g + np.eye(k), g.T @ d.T).T, rtol=1e-10, atol=1e-12)
        np.testing.assert_array_equal(chol, np.linalg.cholesky(a))
        b = rng.normal(size=(a.shape[0], 5))
        np.testing.assert_array_equal(_lower_solve(chol, b), np.linalg.solve(chol, b))
        np.testing.assert_allclose(chol @ _lower_solve(chol, b), b, rtol=0, atol=1e-9 * np.abs(b).max())
        # −½ dᵀ(I + GGᵀ)⁻¹d directly
        direct = -0.5 * np.einsum("cm,cm->c", d, np.linalg.solve(g @ g.T + np.eye(m), d.T).T)
        np.testing.assert_allclose(loglik, direct, rtol=1e-12)
        without = whitened_posterior(g, d, with_loglik=False)
        assert without[3] is None
        for got, want in zip(without[1:3], (chol, u)):
            np.testing.assert_array_equal(got, want)
    with np.errstate(invalid="ignore"), pytest.raises(np.linalg.LinAlgError, match="not positive definite"):
        _cholesky(np.array([[1.0, 2.0], [2.0, 1.0]]))


def test_weights_scale_a_via_point_precision_and_zero_removes_it():
    prim, x, Y = split_model()
    lin, _, _ = split_model(rs=0.0)  # (no MLP: the via-points' weights in the z_nl aggregation do not matter)
    rng = np.random.default_rng(4)
    xv, yv = random_via_points(rng, x, Y, 3)
    a = lin.condition(xv, yv, via_weights=[4.0, 4.0, 4.0], via_noise=1e-2)
    b = lin.condition(xv, yv, via_noise=0.5e-2)  # ω = 4 is the noise halved
    np.testing.assert_allclose(a.mean, b.mean, atol=1e-10)
    np.testing.assert_allclose(a.linear.cov(), b.linear.cov(), atol=1e-12)
    a = prim.condition(xv, yv, via_weights=[4.0, 4.0, 4.0], via_noise=1e-2)
    np.testing.assert_allclose(a.linear.cov(), b.linear.cov(), atol=1e-12)  # the covariance is z_nl's alone
    c = prim.condition(xv[:2], yv[:2])
    d = prim.condition(xv, yv, via_weights=[1.0, 1.0, 0.0])  # a weight-0 via-point is not there
    np.testing.assert_allclose(d.mean[:30], c.mean[:30], atol=1e-12)
    np.testing.assert_allclose(d.linear.cov(), c.linear.cov(), atol=1e-12)
    assert np.abs(prim.mean_trajectory(d, xv[2:]) - yv[2:]).max() > 1e-2  # it does not pull the mean


@pytest.mark.parametrize("n_via", [1, 2, 3, 4, 5])
def test_via_points_inside_the_demos_range_are_met_to_1e6_rad(n_via):
    """Random via-points within the demonstrations' range: the mean of the conditioning meets them
    (after refine(), which re-conditions z_lin with a smaller noise only when needed), and with a
    noise small enough the conditioning alone meets them."""
    prim, x, Y = split_model()
    rng = np.random.default_rng(10 + n_via)
    for _ in range(4):
        xv, yv = random_via_points(rng, x, Y, n_via)
        lat = prim.condition(xv, yv)
        res = prim.refine(lat, xv, yv)
        err = np.abs(prim.mean_trajectory(res.latent, xv) - yv).max()
        assert res.reachable and err <= 1e-6 and res.latent.linear is not None, (res.reason, err)
        if np.abs(prim.mean_trajectory(lat, xv) - yv).max() <= 1e-6:
            assert res.iterations == 0 and res.latent is lat
        small = prim.condition(xv, yv, via_noise=1e-7)
        assert np.abs(prim.mean_trajectory(small, xv) - yv).max() <= 1e-6


@pytest.mark.parametrize("n_via", [1, 5, 50])
def test_samples_pass_the_via_points_within_the_noise(n_via):
    """Every sample is a draw of the exact posterior: at each via-point (points of a demonstration the
    model was not built from) its spread is at most the stated noise (ν · the joint's std), the
    executed mean meets the via-point within it, and the mean of the samples as closely as the
    spread allows. 50 via-points (150 rows, z_lin has 30 directions) cannot all be met: the spread
    still stays within the noise."""
    prim, x, Y = split_model(k_l=30)
    _, held_out = demos(n=1, d=3, seed=99)
    idx = np.sort(np.random.default_rng(n_via).choice(len(x), n_via, replace=False))
    xv, yv = x[idx], held_out[0, idx]
    lat = prim.condition(xv, yv)
    s = prim.sample(lat, xv, 400, rng=0)
    noise_rad = prim.cfg.via_noise * prim.norm.y_std
    spread = s.std(0)  # (n, d)
    mean_err = np.abs(prim.mean_trajectory(lat, xv) - yv)
    sample_mean_err = np.abs(s.mean(0) - yv)
    assert np.all(spread <= 1.15 * noise_rad), spread / noise_rad
    assert np.all(sample_mean_err <= mean_err + 5 * spread / np.sqrt(400) + 1e-12)
    if n_via < 50:
        assert np.all(mean_err <= noise_rad), mean_err / noise_rad
        assert np.all(np.abs(s - yv) <= mean_err + 5 * noise_rad)  # every sample passes every via-point
        assert np.all(spread >= 0.5 * noise_rad)  # and the samples are spread (not collapsed onto the mean)
    # the same draws from the diagonal summary alone would miss by far more than the noise
    diag = prim.sample(LatentGaussian(lat.mean, lat.var), xv, 400, rng=0)
    assert diag.std(0).max() > 10 * noise_rad.max()


def test_a_partial_via_point_leaves_the_free_joints_wide():
    prim, x, Y = split_model()
    xv, yv = x[[25]], Y[2, [25]]
    mask = np.array([True, False, False])
    full = prim.condition(xv, yv)
    part = prim.condition(xv, yv, via_mask=mask)
    none = prim.condition()
    sd_full, sd_part, sd_none = (prim.linearized_std(lat, xv)[0] for lat in (full, part, none))
    noise_rad = prim.cfg.via_noise * prim.norm.y_std
    assert np.all(sd_full <= 1.01 * noise_rad)  # every joint pinned
    assert sd_part[0] <= 1.01 * noise_rad[0]  # the constrained joint pinned
    assert np.all(sd_part[1:] > 100 * noise_rad[1:]) and np.all(sd_part[1:] <= sd_none[1:] + 1e-12)
    mc = prim.sample(part, xv, 400, rng=1)[:, 0]  # the samples agree with the linearized std
    np.testing.assert_allclose(mc.std(0)[1:], sd_part[1:], rtol=0.15)


# ------------------------------------------------------------------------------------------------
# modes: a residual MLP that switches between two offsets with the sign of z_nl
# ------------------------------------------------------------------------------------------------
def bimodal_model():
    """Two joints, k_l = 16, z_nl scalar. s·MLP(z_nl, x) = ±sin(πx)·(1, 0.5) (normalized = rad here):
    hidden units ReLU(K z + sin πx), ReLU(K z − sin πx), ReLU(sin πx) with the output their
    difference, so the two modes meet at x = 0 and x = 1. The via-point encoder says nothing about
    z_nl (variance ~1e3), so q(z_nl) ≈ N(0.0005, 1) proposes both signs. The linear part is the PPCA
    of small variations (std ≈ 0.05) around a ramp."""
    rng = np.random.default_rng(0)
    x = np.linspace(0, 1, 50)
    Y = 0.3 * x[None, :, None] * np.array([1.0, 0.5]) + rng.normal(0, 0.05, (40, 3, 2))[:, None, 0] * x[None, :, None] \
        + rng.normal(0, 0.05, (40, 2))[:, None] * (x ** 2)[None, :, None]
    norm = Normalization(np.zeros(2), np.ones(2))
    mean, a, _ = pca_basis(phase_basis(x, 8, 1.0, False), Y, 16, 0.05)
    torch.manual_seed(0)
    cfg = ModelConfig(n_joints=2, latent_dim=17, hidden=8, decoder_basis=8, latent_linear=16, residual_scale=1.0,
                      phase_harmonics=1)  # phase features [x, sin πx, cos πx]
    net = DeepProMPNet(cfg)
    K = 1e4
    with torch.no_grad():
        net.basis.bias.copy_(torch.as_tensor(mean))
        net.basis.weight.copy_(torch.as_tensor(a))
        l1, l2, l3 = (m for m in net.decoder if isinstance(m, torch.nn.Linear))
        for layer in (l1, l2, l3):
            layer.weight.zero_()
            layer.bias.zero_()
        l1.weight[0, 0], l1.weight[0, 2] = K, 1.0  # input [z_nl, x, sin πx, cos πx]
        l1.weight[1, 0], l1.weight[1, 2] = K, -1.0
        l1.weight[2, 2] = 1.0
        l2.weight[:3, :3] = torch.eye(3)
        l3.weight[:, :3] = torch.tensor([[1.0, -1.0, -1.0], [0.5, -0.5, -0.5]])
        net.head.weight[16].zero_()  # μ of z_nl from every encoder: 0.5, with variance softplus(1000) ≈ 1e3
        net.head.bias[16] = 0.5
        net.head.weight[17 + 16].zero_()
        net.head.bias[17 + 16] = 1000.0
    return DeepProMP(net, norm, ["a", "b"]), x


def _modes(prim, traj_at_half):
    """+1 / −1 per sample by the residual's sign at x = 0.5 (±(1, 0.5) there, the linear part's spread ~0.05),
    0 for a sample between the modes."""
    off = traj_at_half[:, 0] - 0.3 * 0.5  # the ramp's value of joint a at x = 0.5
    return np.where(off > 0.5, 1, np.where(off < -0.5, -1, 0))


def test_distinguishing_via_points_select_the_right_mode():
    prim, x = bimodal_model()
    for sign in (1.0, -1.0):
        xv = np.array([0.5])
        yv = np.array([[0.15 + sign * 1.0, 0.075 + sign * 0.5]])  # the ramp plus one mode's offset
        lat = prim.condition(xv, yv)
        modes = _modes(prim, prim.sample(lat, np.array([0.5]), 1000, rng=2)[:, 0])
        assert np.mean(modes == sign) >= 0.98, np.mean(modes == sign)
        assert _modes(prim, prim.mean_trajectory(lat, xv))[0] == sign
        assert np.abs(prim.mean_trajectory(lat, xv) - yv).max() <= 1e-6
        # the other mode would have to bend the linear part by 2 (40 of its std): weight ~0
        assert lat.linear.weights[np.sign(lat.linear.candidates[:, 16]) != sign].sum() < 1e-6


def test_ambiguous_via_points_keep_both_modes():
    prim, x = bimodal_model()
    xv = np.array([0.0, 1.0])  # where the two modes meet
    yv = np.array([[0.0, 0.0], [0.3, 0.15]])
    lat = prim.condition(xv, yv)
    s = prim.sample(lat, np.array([0.0, 0.5, 1.0]), 1000, rng=3)
    modes = _modes(prim, s[:, 1])
    assert np.mean(modes != 0) >= 0.9 and np.mean(modes == 1) >= 0.25 and np.mean(modes == -1) >= 0.25, \
        (np.mean(modes == 1), np.mean(modes == -1))
    assert np.abs(s[:, [0, 2]] - yv).max() <= 5 * prim.cfg.via_noise  # every sample passes both via-points


def decoder_modes_model(shares=(0.3, 1.0), encoder_z_nl=(0.5, 1000.0), context_dims=(),
                        shape=lambda x: np.sin(np.pi * x)):
    """The two modes of :func:`bimodal_model` held by the decoder (``decoder_modes`` 2, no MLP): the
    modes' offsets m_k the basis weights of ±shape(x)·(1, 0.5) (sin πx: the modes meet at x = 0 and 1),
    chosen by z_nl below / above the normal
    quantile of ``shares[0]``. ``encoder_z_nl`` (μ, softplus⁻¹ σ²) is what every encoder says of z_nl;
    ``context_dims`` adds (random) context encoders."""
    prim, x = bimodal_model()
    cfg = ModelConfig(n_joints=2, latent_dim=17, hidden=8, decoder_basis=8, latent_linear=16, residual_scale=0.0,
                      phase_harmonics=1, decoder_modes=2, context_dims=tuple(context_dims))
    net = DeepProMPNet(cfg)
    net.load_state_dict(prim.net.state_dict(), strict=False)  # the modes' buffers and context encoders: below / random
    phi = phase_basis(x, 8, 1.0, False)
    w = np.linalg.lstsq(phi, shape(x)[:, None] * np.array([1.0, 0.5]), rcond=None)[0].reshape(-1)
    with torch.no_grad():
        net.mode_offsets.copy_(torch.as_tensor(np.stack([-w, w])))
        net.mode_cumulative_shares.copy_(torch.as_tensor(shares))
        net.head.bias[16] = encoder_z_nl[0]
        net.head.bias[17 + 16] = encoder_z_nl[1]
    return DeepProMP(net.eval(), prim.norm, ["a", "b"]), x


def test_decoder_modes_decode_alike_in_torch_and_numpy_and_the_threshold_is_the_shares_quantile():
    prim, x = decoder_modes_model()
    import statistics
    t = statistics.NormalDist().inv_cdf(0.3)
    z = np.zeros((4, 17))
    z[:, 16] = [t - 1e-6, t + 1e-6, -3.0, 3.0]
    z[:, :16] = np.random.default_rng(1).standard_normal(16)  # the same z_lin: the rows differ in the mode alone
    np.testing.assert_array_equal(prim.mode_of(z), [0, 1, 0, 1])
    with torch.no_grad():
        ref = prim.net.decode(torch.as_tensor(z, dtype=torch.float32), torch.as_tensor(x, dtype=torch.float32))
        np.testing.assert_array_equal(prim.net.mode_of(torch.as_tensor(z, dtype=torch.float32)).numpy(), [0, 1, 0, 1])
    np.testing.assert_allclose(prim.decode(z, x), ref.numpy(), atol=1e-5)
    # the two modes differ by the offsets' trajectories ±sin(πx)·(1, 0.5): 2 at x = 0.5 on joint a
    both = prim.decode(z[:2], np.array([0.5]))
    assert both[1, 0, 0] - both[0, 0, 0] == pytest.approx(2.0, abs=0.02)
    y, jac = prim._np.decoder_jacobian(z[0], x)
    np.testing.assert_allclose(y, prim.decode(z[0], x), atol=1e-12)
    assert np.abs(jac[..., 16]).max() == 0.0  # the mode is constant between the thresholds


def test_decoder_modes_are_weighed_by_the_exact_likelihood_whatever_the_encoders_say():
    # every encoder puts z_nl at +3 (mode 1) with variance 1e-3: the mode is still the via-points' to choose
    prim, x = decoder_modes_model(encoder_z_nl=(3.0, -5.0))
    assert prim.encode_via_points(np.array([0.5]), np.zeros((1, 2)))[1][0, 16] < 0.01
    xv = np.array([0.0, 1.0])  # where the modes meet: each mode in its share, 0.3 / 0.7
    yv = np.array([[0.0, 0.0], [0.3, 0.15]])
    modes = _modes(prim, prim.sample(prim.condition(xv, yv), np.array([0.5]), 2000, rng=4)[:, 0])
    assert np.mean(modes != 0) == 1.0
    assert np.mean(modes == -1) == pytest.approx(0.3, abs=0.05) and np.mean(modes == 1) == pytest.approx(0.7, abs=0.05)
    for sign in (1.0, -1.0):  # one via-point on a mode: that mode, met exactly
        yv = np.array([[0.15 + sign * 1.0, 0.075 + sign * 0.5]])
        lat = prim.condition(np.array([0.5]), yv)
        assert np.mean(_modes(prim, prim.sample(lat, np.array([0.5]), 1000, rng=2)[:, 0]) == sign) == 1.0
        assert np.abs(prim.mean_trajectory(lat, np.array([0.5])) - yv).max() <= 1e-6


def test_the_executed_mean_weighs_the_modes_by_their_posterior_probabilities():
    """Via-points the modes share (where they meet) leave each mode its prior share: the executed mean is the
    posterior mean of the trajectory, Σ_k P(k | via-points) × mode k's conditioned mean, which meets the
    via-points as each mode's mean does; one via-point on a mode makes the weights one-hot."""
    from deepprompt_ros.training.selection import with_via_noise
    model, x = decoder_modes_model(shares=(0.3, 1.0))
    xv = np.array([0.0, 1.0])
    yv = np.array([[0.0, 0.0], [0.3, 0.15]])
    for planner, mode_noise in ((False, 0.0), (True, 0.0), (False, 0.3), (True, 0.3)):
        # mode_noise: the modes' weights at that noise whatever the request's (0: the model's via_noise)
        prim = DeepProMP(with_via_noise(model.net, model.cfg.via_noise, mode_noise), model.norm, ["a", "b"])
        lat = prim.condition_planner(xv, yv).latent if planner else prim.condition(xv, yv)
        block = lat.linear
        np.testing.assert_allclose(lat.mode_weights, block.weights[np.argsort(prim.mode_of(block.candidates))],
                                   atol=1e-15)
        # each mode's share times the marginal likelihood N(y; Φ(b + m_k) + mean, H Hᵀ + ν²σ²I) of the
        # via-points under the prior N(0, I) of z_lin, written out densely
        _, h = prim._np.linear_design(xv)
        h = h.reshape(-1, 16)
        assert block.weight_noise == (prim.mode_noise if planner or mode_noise else None)
        assert prim.mode_noise == (mode_noise or model.cfg.via_noise)
        cov = h @ h.T + np.diag(np.tile((prim.mode_noise * prim._np.y_std) ** 2, 2))
        loglik = []
        for z_nl in prim._np.mode_medians:
            z = np.zeros(17)
            z[16] = z_nl
            r = (yv - prim.decode(z, xv)).reshape(-1)
            loglik.append(-0.5 * r @ np.linalg.solve(cov, r))
        expected = np.array([0.3, 0.7]) * np.exp(np.array(loglik) - max(loglik))
        np.testing.assert_allclose(lat.mode_weights, expected / expected.sum(), rtol=1e-6)
        assert 0.25 < lat.mode_weights[0] < 0.4  # (near the prior shares: the modes barely differ there)
        assert abs(lat.mode_weights[0] - 0.3) < (0.001 if mode_noise else 0.1)
        per_mode = prim.decode(block.candidates, x)  # (2, T, d): each mode's conditioned mean
        np.testing.assert_allclose(prim.mean_trajectory(lat, x), np.einsum("c,ctd->td", block.weights, per_mode),
                                   atol=1e-9)
        # between the modes at x = 0.5 (they are 2 apart on joint a there), at 0.3·(−) + 0.7·(+)
        mid = prim.mean_trajectory(lat, np.array([0.5]))[0, 0]
        lo, hi = sorted(prim.decode(block.candidates, np.array([0.5]))[:, 0, 0])
        assert mid == pytest.approx(lo + lat.mode_weights[1] * (hi - lo), abs=1e-9) and hi - lo > 1.9
        assert np.abs(prim.mean_trajectory(lat, xv) - yv).max() <= 1e-6
        assert block.via_error == pytest.approx(np.abs(prim.mean_trajectory(lat, xv) - yv).max(), abs=1e-12)
    # at a large noise the weighted mean misses the via-points, by what via_error records
    lat = model.condition(xv, yv + np.array([0.3, 0.0]), via_noise=3.0)
    miss = np.abs(model.mean_trajectory(lat, xv) - yv - np.array([0.3, 0.0])).max()
    assert miss > 1e-3 and lat.linear.via_error == pytest.approx(miss, rel=1e-9)
    lat = model.condition(np.array([0.5]), np.array([[0.15 + 1.0, 0.075 + 0.5]]))
    np.testing.assert_array_equal(lat.mode_weights, [0.0, 1.0])
    np.testing.assert_allclose(model.mean_trajectory(lat, x), model.decode(lat.mean, x), atol=1e-12)


def test_a_blend_between_two_modes_moves_from_one_offset_to_the_other_without_a_jump():
    from deepprompt_ros.server.handles import BlendedLatent, ConditionedLatent, Schedule
    prim, x = decoder_modes_model(shares=(0.5, 1.0))
    a = prim.condition(np.array([0.5]), np.array([[0.15 + 1.0, 0.075 + 0.5]]))  # the + mode
    b = prim.condition(np.array([0.5]), np.array([[0.15 - 1.0, 0.075 - 0.5]]))  # the − mode
    assert prim.mode_of(a.mean) == 1 and prim.mode_of(b.mean) == 0
    np.testing.assert_array_equal(prim.mode_weights(a), [0.0, 1.0])
    grid = np.linspace(0.0, 1.0, 201)
    omega = np.clip((0.55 - grid) / 0.1, 0.0, 1.0)  # a up to x = 0.45, b from x = 0.55, where the modes are 2 apart
    traj = prim.blend(a, b, omega, grid)
    np.testing.assert_allclose(traj[0], prim.mean_trajectory(a, grid[:1])[0], atol=1e-9)
    np.testing.assert_allclose(traj[-1], prim.mean_trajectory(b, grid[-1:])[0], atol=1e-9)
    # the blended latent's z_nl crosses the modes' threshold inside [0.45, 0.55]: the gate alone would jump by
    # the modes' distance (2 on joint a) in one step; the weighted offsets spread it over the 20 steps
    mean, _ = prim.blend_latent(a, b, omega)
    assert np.abs(np.diff(prim.decode_per_phase(mean, grid), axis=0)).max() > 1.5
    assert np.abs(np.diff(traj, axis=0)).max() <= 2.0 / 20 + 0.02
    # the server's blended handle weighs the modes alike (ω from a's to b's)
    blended = BlendedLatent("p", ConditionedLatent("p", a), ConditionedLatent("p", b),
                            Schedule(np.array([0.45, 0.55]), np.array([1.0, 0.0])))
    w = blended.mode_weights_at(grid, prim.mode_weights)
    np.testing.assert_allclose(w, np.stack([1.0 - omega, omega], 1), atol=1e-12)
    mean, _ = blended.latent_at(grid)
    np.testing.assert_allclose(prim.decode_per_phase(mean, grid, w), traj, atol=1e-9)


def test_a_context_modelled_per_mode_chooses_the_mode():
    from deepprompt_ros.primitive.linear_context import fit_linear_context
    prim, x = decoder_modes_model(shares=(0.5, 1.0), context_dims=(("side", 1),))
    rng = np.random.default_rng(5)
    labels = np.arange(40) % 2
    scores = rng.standard_normal((40, 16))
    model = fit_linear_context({"side": (2.0 * labels - 1.0)[:, None] + 0.01 * rng.standard_normal((40, 1))},
                               scores, labels, 2)
    np.testing.assert_allclose(model.mode_means[:, 0], [-1.0, 1.0], atol=0.02)
    norm = Normalization(np.zeros(2), np.ones(2), {"side": np.zeros(1)}, {"side": np.ones(1)})
    prim = DeepProMP(prim.net, norm, ["a", "b"], metadata={"selection": {"context": {"linear": model.to_json()}}})
    for side, sign in ((-1.0, -1), (1.0, 1)):
        lat = prim.condition(np.array([0.0]), np.zeros((1, 2)), contexts={"side": np.array([[side]])})
        assert np.mean(_modes(prim, prim.sample(lat, np.array([0.5]), 500, rng=6)[:, 0]) == sign) == 1.0
        lat = prim.condition(contexts={"side": np.array([[side]])})  # the context alone
        assert _modes(prim, prim.mean_trajectory(lat, np.array([0.5])))[0] == sign
        # a via-point where the modes meet, at a noise the mean misses it by: the refinement conditions again
        # on the via-point alone and keeps the modes' weights the context gave
        xv, yv = np.array([0.0]), np.array([[0.1, 0.05]])
        lat = prim.condition(xv, yv, contexts={"side": np.array([[side]])}, via_noise=1.0)
        assert lat.mode_weights[(sign + 1) // 2] > 0.999 and lat.linear.via_error > 1e-3
        res = prim.refine_linear(lat, xv, yv, tol=1e-6)
        assert res.max_error <= 1e-6 and np.abs(prim.mean_trajectory(res.latent, xv) - yv).max() <= 1e-6
        np.testing.assert_array_equal(res.latent.mode_weights, lat.mode_weights)
        import pickle
        again = pickle.loads(pickle.dumps(res.latent))
        np.testing.assert_array_equal(prim.mean_trajectory(again, x), prim.mean_trajectory(res.latent, x))


def tight_encoder_model(shares=(0.3, 1.0), context_dims=(("obj", 1),), linear=None):
    """:func:`decoder_modes_model` whose encoders (the contexts' and the via-points') all say z_lin = μ with variance
    softplus(−12) ~ 6e-6 per coordinate; ``linear`` (a fitted linear context model) decides z_lin for its
    modalities. Returns (prim, μ, grid (21,), the trajectory the encodings describe on the grid,
    b + Σ_k π_k m_k + A μ: the training decodes each draw with the mode it chooses)."""
    prim, _ = decoder_modes_model(shares=shares, context_dims=context_dims)
    mu = 0.3 * np.random.default_rng(7).standard_normal(16)
    with torch.no_grad():
        prim.net.head.weight[:16] = 0.0
        prim.net.head.bias[:16] = torch.as_tensor(mu, dtype=torch.float32)
        prim.net.head.weight[17:33] = 0.0
        prim.net.head.bias[17:33] = -12.0
    names = [name for name, _ in context_dims]
    norm = Normalization(np.zeros(2), np.ones(2), {n: np.zeros(1) for n in names}, {n: np.ones(1) for n in names})
    prim = DeepProMP(prim.net, norm, ["a", "b"],
                     metadata=None if linear is None else {"selection": {"context": {"linear": linear.to_json()}}})
    grid = np.linspace(0.0, 1.0, 21)
    shares_k = np.diff([0.0, *shares])
    said = prim.decode_per_phase(np.tile(np.r_[mu, 0.0], (21, 1)).astype(np.float32).astype(np.float64), grid,
                                 np.tile(shares_k, (21, 1)))
    return prim, mu, grid, said


def test_the_encodings_of_z_lin_are_moved_to_each_mode():
    """A context encoder that says z_lin = μ with variance ~6e-6: it describes the trajectory b + Σ_k π_k m_k + A μ
    (the training decodes each draw with the mode it chooses). A via-point on that trajectory where the modes
    differ (x = 0.5) leaves it as it is: each mode's candidate has the prior m − (1 − σ²) u_k, not μ beside its
    own offset, which would put the executed mean on the nearer mode's shape."""
    prim, mu, grid, said = tight_encoder_model()
    assert prim.encode_context("obj", np.zeros((1, 1)))[1][0, :16].max() < 2e-4
    per_mode = [prim.decode_per_phase(np.zeros((21, 17)), grid, np.tile(np.eye(2)[k], (21, 1))) for k in range(2)]
    assert np.abs(per_mode[1] - per_mode[0]).max() > 1.9  # the modes' offsets differ by up to 2
    lat = prim.condition(grid[10:11], said[10:11], contexts={"obj": np.zeros((1, 1))})
    assert lat.linear.move_prior
    assert np.abs(prim.mean_trajectory(lat, grid) - said).max() < 1e-3
    s = prim.sample(lat, grid, 200, rng=8)
    assert np.abs(s.mean(0) - said).max() < 1e-3
    # the same through the rows of a partial via-point (joint a alone) and the planner's smoothed path
    partial = prim.condition(grid[10:11], said[10:11], via_mask=np.array([[True, False]]),
                             contexts={"obj": np.zeros((1, 1))})
    planner = prim.condition_planner(grid[10:11], said[10:11], contexts={"obj": np.zeros((1, 1))})
    for other in (partial, planner.latent):
        assert np.abs(prim.mean_trajectory(other, grid) - said).max() < 1e-3
    # a smoothed mean records the move as well: a refinement conditions again as from the plain posterior, also
    # where the smallest change cannot be made (two via-points at one phase)
    xv, yv = grid[[10, 10]], said[[10, 10]] + np.array([[0.05, 0.0], [0.06, 0.0]])
    refined = []
    for smooth in (1e-2, None):
        lat = prim.condition(xv, yv, contexts={"obj": np.zeros((1, 1))}, via_noise=1e-4, smooth_noise=smooth)
        assert lat.linear.move_prior is True
        refined.append(prim.refine_linear(lat, xv, yv, tol=1e-3, max_iterations=30).latent.linear.candidates)
    np.testing.assert_allclose(refined[0], refined[1], rtol=0, atol=1e-9)


def test_a_linear_contexts_model_alone_moves_nothing(monkeypatch):
    """The contexts' linear model decides z_lin (its encodings unused): no move to the modes in the conditioning,
    and none when the refinement conditions again from the recorded prior and the model's rows."""
    from deepprompt_ros.primitive.linear_context import fit_linear_context
    from deepprompt_ros.primitive.numpy_net import NumpyNet
    prim, x = decoder_modes_model(shares=(0.5, 1.0), context_dims=(("side", 1),))
    rng = np.random.default_rng(5)
    labels = np.arange(40) % 2
    model = fit_linear_context({"side": (2.0 * labels - 1.0)[:, None] + 0.3 * rng.standard_normal((40, 1))},
                               rng.standard_normal((40, 16)), labels, 2)
    norm = Normalization(np.zeros(2), np.ones(2), {"side": np.zeros(1)}, {"side": np.ones(1)})
    prim = DeepProMP(prim.net, norm, ["a", "b"], metadata={"selection": {"context": {"linear": model.to_json()}}})
    xv, yv = np.array([0.2, 0.7]), np.array([[0.4, 0.2], [0.9, 0.5]])

    def refined():
        lat = prim.condition(xv, yv, contexts={"side": np.array([[0.5]])}, via_noise=1.0)
        assert lat.context_var[:16].max() < 1.0 and not lat.linear.move_prior
        res = prim.refine_linear(lat, xv, yv, tol=1e-6)
        assert res.max_error <= 1e-6
        return prim.mean_trajectory(res.latent, x)

    with_offsets = refined()
    assert np.abs(prim._np.mode_latent_offsets()).max() > 0.1
    monkeypatch.setattr(NumpyNet, "mode_latent_offsets", lambda self: np.zeros((2, 16)))
    np.testing.assert_array_equal(refined(), with_offsets)


def test_a_refinement_conditions_again_from_the_encodings_and_the_linear_contexts_rows():
    """A context through a tight encoder (z_lin = μ) beside one the linear model decides: each mode's candidate
    has its own moved prior and rows; the refinement, conditioning again at smaller noises, keeps both for every
    candidate and ends where a conditioning asked at a small noise begins (the via-point 0.05 off the encoder's
    trajectory at x = 1, where the modes meet: every candidate 0.05 off it)."""
    from deepprompt_ros.primitive.linear_context import fit_linear_context
    # the linear model's demos' z_lin carry nothing along the modes' offset u_1 − u_0: its direction depends on
    # the test basis's regularized (equal-eigenvalue) directions, which differ with the BLAS kernels, and a
    # model that read it would weigh the modes differently on every machine (0.007 to 0.99)
    u = tight_encoder_model(shares=(0.5, 1.0))[0]._np.mode_latent_offsets()
    v = (u[1] - u[0]) / np.linalg.norm(u[1] - u[0])
    rng = np.random.default_rng(5)
    side, scores = rng.standard_normal((40, 1)), rng.standard_normal((40, 16))
    model = fit_linear_context({"side": side}, scores - np.outer(scores @ v, v), np.arange(40) % 2, 2)
    prim, mu, grid, said = tight_encoder_model(shares=(0.5, 1.0), context_dims=(("obj", 1), ("side", 1)),
                                               linear=model)
    ctx = {"obj": np.zeros((1, 1)), "side": np.array([[0.3]])}
    xv, yv = grid[20:], said[20:] + np.array([[0.05, 0.0]])
    lat = prim.condition(xv, yv, contexts=ctx, via_noise=0.5)
    assert lat.linear.move_prior and lat.linear.context_rows is not None and lat.linear.weights.min() > 0.1
    res = prim.refine_linear(lat, xv, yv, tol=1e-6)
    assert res.max_error <= 1e-6
    direct = prim.condition(xv, yv, contexts=ctx, via_noise=1e-7)
    refined, asked = (prim.decode(lt.linear.candidates, grid) for lt in (res.latent, direct))
    np.testing.assert_allclose(res.latent.linear.weights, direct.linear.weights, rtol=1e-9)
    assert np.abs(refined - asked).max() < 1e-6
    np.testing.assert_allclose(np.abs(refined - said).max((1, 2)), 0.05, atol=1e-6)
    # the refined latent still records the linear model's posterior as its q_c (refine_map's prior)
    np.testing.assert_array_equal(res.latent.context_mean, lat.context_mean)


def test_an_aggregation_with_modes_spreads_refines_and_serves_as_its_samples_fall(tmp_path):
    """The prior and a context through a tight encoder (no via-point): their samples fall in either mode, so the
    linearized std holds the spread of the modes' offsets; the server's Sample draws each trajectory in the mode
    its z chooses as the model does; a refinement starts by conditioning every mode exactly and leaves an
    executed mean that meets the via-point already as it is."""
    from deepprompt_ros.execution.limits import JointLimits
    prim, mu, grid, said = tight_encoder_model(shares=(0.5, 1.0))
    ctx = {"obj": np.zeros((1, 1))}
    xs = grid[[5, 10]]
    for lat in (prim.prior(), prim.condition(contexts=ctx)):
        assert lat.linear is None and lat.mode_weights.min() > 0.4
        drawn = prim.sample(lat, xs, 20000, rng=3).std(0)
        assert drawn[1, 0] > 0.9  # the modes' offsets differ by 2 at x = 0.5 on joint a
        np.testing.assert_allclose(prim.linearized_std(lat, xs), drawn, rtol=0.02)
    path = save_checkpoint(tmp_path / "modes.safetensors", prim.net, prim.norm, prim.joint_names)
    limits = JointLimits(lower=np.full(2, -10.0), upper=np.full(2, 10.0), max_velocity=np.ones(2),
                         max_acceleration=np.ones(2), max_jerk=np.ones(2))
    core = PrimitiveServerCore({"modes": load_primitive(PrimitiveEntry("modes", str(path)), ["a", "b"],
                                                        pathlib.Path)}, ServerConfig(), limits)
    served = core.sample(SampleRequest(primitive="modes", n_samples=500, n_points=21, seed=4)).samples
    np.testing.assert_array_equal(served, core.primitives["modes"].model.sample(prim.prior(), grid, 500, 4))
    assert served[:, 10, 0].std() > 0.9
    # refinement from the context's aggregation: a via-point its executed mean meets leaves it as it is; one off it
    # is met in the most probable mode, starting from that mode's move of the encodings: the executed mean's
    # trajectory, 0.05 from the via-point (unmoved, the mode's offset would put the start ~1 from it)
    lat = prim.condition(contexts=ctx)
    on = prim.mean_trajectory(lat, grid[10:11])
    res = prim.refine(lat, grid[10:11], on)
    assert res.iterations == 0 and res.latent is lat and res.max_error <= 1e-6
    top = int(np.argmax(lat.mode_weights))
    res = prim.refine(lat, grid[10:11], on + np.array([[0.05, 0.0]]), latent_bound=1000.0)
    assert res.max_error <= 1e-6 and res.latent.mode_weights is None and int(prim.mode_of(res.latent.mean)) == top
    assert f"in mode {top}" in res.reason and res.error_history[0] == pytest.approx(0.05, abs=1e-3)


def test_a_map_refinement_with_modes_stays_in_the_most_probable_mode_from_its_moved_prior():
    """refine_map from a conditioning whose prior was moved to each mode: the MAP latent of the most probable mode,
    its prior the moved one, so a via-point on the encoder's trajectory is kept there (the tight prior holds it
    within the prior trajectory's own 4e-4 of it; unmoved, the mode's offset put it 0.6 off)."""
    prim, mu, grid, said = tight_encoder_model()
    lat = prim.condition(grid[10:11], said[10:11], contexts={"obj": np.zeros((1, 1))})
    assert lat.linear.move_prior and lat.mode_weights[0] > 0.5
    res = prim.refine_map(lat, grid[10:11], said[10:11], latent_bound=1000.0)  # (the test basis needs |z| ~ 100)
    assert int(prim.mode_of(res.latent.mean)) == 0
    assert res.max_error < 1e-3 and np.abs(prim.mean_trajectory(res.latent, grid) - said).max() < 1e-3
    # the standard prior holds the mode as well (nothing else pulls its coordinate: it would drift to 0, mode 1)
    std = prim.refine_map(lat, grid[10:11], said[10:11], prior="standard", latent_bound=1000.0).latent
    assert int(prim.mode_of(std.mean)) == 0 and std.var[16] <= 1e-4


def test_a_refinement_weighs_the_candidates_as_a_conditioning_at_its_noise():
    """With an MLP residual the candidates of z_nl are points of q_all; the re-conditioning at a smaller noise
    weighs them by the via-points' likelihood times q_c / q_all, q_all centred where the candidates were drawn
    (not at the best candidate's z_nl): the weights a conditioning asked at that noise gives."""
    prim, x, Y = split_model(k_l=12, k_n=4, rs=1.0)
    rng = np.random.default_rng(3)
    for _ in range(3):
        xv, yv = random_via_points(rng, x, Y, 3)
        lat = prim.condition(xv, yv)
        res = prim.refine_linear(lat, xv, yv, tol=1e-6)
        assert res.iterations >= 1 and res.max_error <= 1e-6
        direct = prim.condition(xv, yv, via_noise=lat.linear.noise / 10 ** res.iterations)
        np.testing.assert_allclose(res.latent.linear.weights, direct.linear.weights, rtol=0, atol=1e-9)


def test_the_modes_probabilities_of_a_degenerate_or_overflowed_aggregation():
    prim, _ = decoder_modes_model(shares=(0.3, 1.0), encoder_z_nl=(3.0, -5.0), context_dims=(("obj", 1),))
    net = prim._np
    np.testing.assert_array_equal(net.mode_probabilities(3.0, 0.0), [0.0, 1.0])
    np.testing.assert_array_equal(net.mode_probabilities(-3.0, 0.0), [1.0, 0.0])
    np.testing.assert_allclose(net.mode_probabilities(0.0, 1.0), [0.3, 0.7], rtol=1e-6)
    assert np.isnan(net.mode_probabilities(np.nan, 1.0)).all() and np.isnan(net.mode_probabilities(0.0, np.inf)).all()
    norm = Normalization(np.zeros(2), np.ones(2), {"obj": np.zeros(1)}, {"obj": np.ones(1)})
    encoders = DeepProMP(prim.net, norm, ["a", "b"])
    for via in ({}, {"via_x": np.array([0.5]), "via_y": np.zeros((1, 2))}):
        with pytest.raises(ValueError, match="NaN or inf"):
            encoders.condition(**via, contexts={"obj": np.zeros((1, 1))}, context_weights={"obj": [1e308]})


# ------------------------------------------------------------------------------------------------
# refinement
# ------------------------------------------------------------------------------------------------
def test_refine_returns_at_once_when_the_conditioning_meets_the_via_points():
    prim, x, Y = split_model()
    xv, yv = x[[10, 30]], Y[5, [10, 30]]
    lat = prim.condition(xv, yv, via_noise=1e-6)
    res = prim.refine(lat, xv, yv)
    assert res.iterations == 0 and res.latent is lat and res.reachable and res.max_error <= 1e-6
    assert res.sample_mean_error <= 1e-5  # K = 16 samples of the exact posterior, each within ~1e-6 rad


def test_refine_map_with_the_posterior_prior_counts_the_via_points_once():
    """The prior of MAP refinement is what the latent knows without the via-points (q_c): with no
    context it is N(0, I), for a plain latent of a trained reach model and for a split latent; with a
    context, the context's aggregation. The Laplace variance of a linear decoder is then exactly the
    Gaussian posterior's (counting the via-points twice would make it smaller)."""
    prim, x, Y = split_model(rs=0.0, contexts=(("obj", 2),))
    xv, yv = x[[10, 30]], Y[5, [10, 30]]
    lat = prim.condition(xv, yv)
    a = prim.refine_map(lat, xv, yv, prior="posterior")
    b = prim.refine_map(lat, xv, yv, prior="standard")
    np.testing.assert_allclose(a.latent.mean, b.latent.mean, atol=1e-9)
    np.testing.assert_allclose(a.latent.var, b.latent.var, atol=1e-12)
    # the Laplace variance of z_lin is the exact posterior's at the same noise (σ_y · joint std)
    exact = prim.condition(xv, yv, via_noise=prim.cfg.sigma_y)
    np.testing.assert_allclose(a.latent.var[:30], exact.var[:30], rtol=1e-6)
    obj = np.array([0.3, -0.2])
    lat_c = prim.condition(xv, yv, contexts={"obj": obj})
    q_c = prim.condition(contexts={"obj": obj})
    c = prim.refine_map(lat_c, xv, yv, prior="posterior")
    d = prim.refine_map(LatentGaussian(lat_c.mean, q_c.var), xv, yv, prior="standard")  # same start
    d2 = prim.refine_map(LatentGaussian(q_c.mean, q_c.var), xv, yv)  # a latent that records no q_c is the prior
    np.testing.assert_allclose(c.latent.mean, d2.latent.mean, atol=1e-8)
    assert not np.allclose(c.latent.mean, d.latent.mean, atol=1e-6)  # the context's prior does count
    trained = DeepProMP.from_checkpoint(PLAIN_REACH)
    xs, ys = np.array([0.5]), np.array([[-0.2, -0.3, 1.4, 1.5, 1.3, 0.0]])
    plain = trained.condition(xs, ys)
    e = trained.refine_map(plain, xs, ys, prior="posterior", max_iterations=5)
    f = trained.refine_map(plain, xs, ys, prior="standard", max_iterations=5)
    np.testing.assert_allclose(e.latent.mean, f.latent.mean, atol=1e-12)


# ------------------------------------------------------------------------------------------------
# plain latents: a partial via-point, and the numbers of before
# ------------------------------------------------------------------------------------------------
def test_a_partial_via_point_on_the_shipped_model_leaves_the_free_joints_wider_than_a_full_one():
    """The unconstrained joints of a partial via-point are filled with the mean; their encoding counts
    with the share of joints constrained (2 of 6), so the free joints stay wider than under the full
    via-point (filling and encoding them as observed made them narrower)."""
    prim = DeepProMP.from_checkpoint(REPO / "models" / "gen3_lite_reach.safetensors")
    x = np.linspace(0, 1, 50)
    ctx = {"object": [0.1, -0.2, 0.05]}
    xv, yv = np.array([0.5]), np.array([[-0.2, -0.3, 1.4, 1.5, 1.3, 0.0]])
    mask = np.array([True, True, False, False, False, False])
    full, part, none = (prim.condition(xv, yv, contexts=ctx), prim.condition(xv, yv, via_mask=mask, contexts=ctx),
                        prim.condition(contexts=ctx))
    for std in (lambda lat: prim.trajectory_std(lat, x, 256), lambda lat: prim.linearized_std(lat, x)):
        sd_full, sd_part, sd_none = (std(lat)[:, 2:].mean() for lat in (full, part, none))
        assert sd_part > 1.05 * sd_full and sd_part <= sd_none, (sd_part, sd_full, sd_none)


def test_a_plain_latent_gives_its_recorded_numbers():
    """latent_linear 0: a trained plain-latent reach model conditions, decodes, samples and refines to
    the recorded values (the aggregation of every element, paper Eq. 1 and 3)."""
    p = DeepProMP.from_checkpoint(PLAIN_REACH)
    xv = np.array([0.0, 0.4, 1.0])
    yv = np.array([[0.0, -0.3, 1.2, 1.5, 1.2, 0.0], [-0.2, -0.3, 1.4, 1.5, 1.3, 0.0], [-0.5, 0.2, 1.7, 1.4, 1.0, 0.1]])
    lat = p.condition(xv, yv, via_weights=[1.0, 0.5, 2.0], contexts={"object": [0.1, -0.2, 0.05]})
    np.testing.assert_allclose(lat.mean[:6], [-1.2813312593694772, -0.5863039306147826, 3.3302127964783343,
                                              0.2946539171823265, 1.2899469059524369, 2.5455033697133476], rtol=1e-12)
    np.testing.assert_allclose(lat.var[:6], [0.00011837138315284812, 0.008636088020507695, 0.0013140014060464558,
                                             0.0007610055991347698, 0.0023007686555853255, 0.000655265361818924],
                               rtol=1e-12)
    xs = np.array([0.1, 0.5, 0.9])
    np.testing.assert_allclose(p.mean_trajectory(lat, xs)[:, :3], [
        [-0.2143277674678469, -0.10916183641748942, 1.534490735283217],
        [-0.329565244365039, 0.013846314640751561, 1.5196830444636251],
        [-0.40318864998600196, -0.12856466698857172, 1.599291046018895]], rtol=1e-12)
    np.testing.assert_allclose(p.sample(lat, xs, 2, 3)[:, 1, :3], [
        [-0.3316231103301681, 0.035427800941761706, 1.5080204108145585],
        [-0.3286518686998462, 0.016072687539075564, 1.5207324201825252]], rtol=1e-12)
    res = p.refine(lat, xv[1:2], yv[1:2], max_iterations=50)
    assert res.iterations == 50
    np.testing.assert_allclose(res.max_error, 0.03532625300850101, rtol=1e-9)
    np.testing.assert_allclose(res.latent.mean[:4], [-1.6831646000369558, -0.9832936646787098, 4.234780435409478,
                                                     0.6235264948927373], rtol=1e-9)
    lat0 = p.condition(xv[:1], yv[:1])
    np.testing.assert_allclose(lat0.mean[:4], [-1.2912444514041224, -0.48610579658541403, -0.44435548414919446,
                                               0.1516109966006855], rtol=1e-12)
    assert lat.linear is None


# ------------------------------------------------------------------------------------------------
# speed, and the server's handlers
# ------------------------------------------------------------------------------------------------
def test_conditioning_140_linear_dimensions_on_50_via_points_is_faster_than_promp():
    """k_l = 140 (20 basis functions x 7 joints), 50 via-points x 7 joints: DeepProMP.condition plus the
    100-point mean against ProMP's conditioning and mean on the same via-points, interleaved."""
    prim, x, Y = split_model(k_l=140, k_n=8, nb=20, d=7, rs=0.2, hidden=128, contexts=(("obj", 3),))
    promp = ProMP(7, n_basis=20).fit(Y, x)
    idx = np.arange(0, 50)
    xv, yv, x100, obj = x[idx], Y[3, idx] + 0.01, np.linspace(0, 1, 100), np.array([0.1, 0.2, 0.0])
    lat = prim.condition(xv, yv, contexts={"obj": obj})
    assert lat.linear.form == "information" and np.all(np.isfinite(lat.mean))
    deep, pro = [], []
    for i in range(16):  # the first round warms both up (caches, BLAS buffers) and is not counted
        for fn, out in ((lambda: prim.mean_trajectory(prim.condition(xv, yv, contexts={"obj": obj}), x100), deep),
                        (lambda: promp.condition(xv, yv, noise_var=1e-6).mean_trajectory(x100), pro)):
            t0 = time.perf_counter()
            fn()
            if i:
                out.append(time.perf_counter() - t0)
    assert np.median(deep) < np.median(pro), (np.median(deep), np.median(pro))


SPEC = load_robot("gen3_lite")


@pytest.fixture(scope="module")
def split_core(tmp_path_factory):
    """The server core serving a 6-joint split-latent primitive of the Gen3 lite (demos around home)."""
    prim, x, Y = split_model(k_l=30, k_n=4, nb=8, d=6, names=list(SPEC.joint_names), y_mean=SPEC.home)
    path = save_checkpoint(tmp_path_factory.mktemp("split") / "split.safetensors", prim.net, prim.norm,
                           prim.joint_names)
    cfg = ServerConfig(preview_std_points=50)  # the std at every preview point (no interpolation)
    core = PrimitiveServerCore({"split": load_primitive(PrimitiveEntry("split", str(path)), SPEC.joint_names,
                                                        pathlib.Path)}, cfg, robot_limits(SPEC, cfg))
    return core, x, Y


def test_the_server_conditions_a_split_latent_exactly_and_samples_its_posterior(split_core):
    core, x, Y = split_core
    vps = [ViaPointIn(float(x[i]), Y[4, i], np.zeros(0, bool)) for i in (10, 35)]
    r = core.condition(ConditionRequest("split", vps, preview_points=50))
    assert r.code == Code.SUCCESS and r.refine_max_error <= 1e-6, r.message
    # the preview's std pinches to the noise at the via-points (the full z_lin covariance), wide between
    i = np.argmin(np.abs(r.preview.phases - x[10]))
    assert r.preview.std[i].max() < 1e-3 and r.preview.std[25].max() > 1e-2
    s = core.sample(SampleRequest(r.handle, n_samples=64, n_points=50, seed=1)).samples  # grid = the demos' phases
    assert np.abs(s[:, [10, 35]] - Y[4, [10, 35]]).max() < 1e-3
    assert s[:, 25].std(0).max() > 1e-2


def test_the_server_refuses_an_overflowing_request_and_blends_split_latents(split_core):
    core, x, Y = split_core
    huge = [ViaPointIn(0.5, np.full(6, 1e300), np.zeros(0, bool))]
    with pytest.raises(RequestError) as info:
        core.condition(ConditionRequest("split", huge))
    assert info.value.code == Code.INVALID_REQUEST and "NaN or inf (an overflow)" in info.value.message
    a = core.condition(ConditionRequest("split", [ViaPointIn(0.2, Y[1, 10], np.zeros(0, bool))]))
    b = core.condition(ConditionRequest("split", [ViaPointIn(0.8, Y[2, 40], np.zeros(0, bool))]))
    blended = core.blend(BlendRequest(a.handle, b.handle, preview_points=20))  # on the diagonal summaries (Eq. 4)
    assert np.all(np.isfinite(blended.preview.mean)) and np.all(blended.preview.std > 0)


def test_the_candidates_of_z_nl_cover_the_normal_distribution_evenly_and_reproducibly():
    from deepprompt_ros.primitive.linear_conditioning import normal_points
    p = normal_points(32, 3, 0)
    np.testing.assert_array_equal(p, normal_points(32, 3, 0))  # the same request, the same candidates
    assert not np.allclose(p, normal_points(32, 3, 1))  # the seed shifts them
    # the 32 points of a coordinate fall in at least 31 of the 32 equal-probability bins (the radical inverse in
    # base 2 of 1 … 31 visits k/32, that of 32 is 1/64: a shift modulo 1 may put it in the bin of another);
    # 32 independent draws fill about 20 of them
    from statistics import NormalDist
    cdf = np.vectorize(NormalDist().cdf)
    for seed in range(5):
        assert len(set(np.floor(cdf(normal_points(32, 3, seed)[:, 0]) * 32).astype(int))) >= 31
    assert len(set(np.floor(cdf(np.random.default_rng(0).standard_normal(32)) * 32).astype(int))) < 26
