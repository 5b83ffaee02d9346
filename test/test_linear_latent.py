"""A latent split into a linear and a nonlinear block (ModelConfig.latent_linear):
μ_y(z, x) = Φ(x)(b + A z_lin) + s·MLP(z_nl, x). The rules of the split, the network and its float64
numpy twin (decode, Jacobian, per-phase decode), checkpoints."""
import numpy as np
import pytest
import torch

from deepprompt_ros.common.params import ConfigError
from deepprompt_ros.model.checkpoint import Normalization, load_checkpoint, save_checkpoint
from deepprompt_ros.model.network import DeepProMPNet, ModelConfig
from deepprompt_ros.model.phase import phase_basis
from deepprompt_ros.primitive.deep_promp import DeepProMP

torch.set_num_threads(1)
NORM = Normalization(np.array([0.1, -0.2, 0.3]), np.array([0.5, 1.5, 2.0]))


def _split_prim(phase_type="linear", nb=6, k=7, k_l=4, rs=0.7, seed=0):
    torch.manual_seed(seed)
    net = DeepProMPNet(ModelConfig(n_joints=3, latent_dim=k, hidden=16, decoder_basis=nb, residual_scale=rs,
                                   latent_linear=k_l, phase_type=phase_type))
    torch.nn.init.normal_(net.basis.bias)
    return net, DeepProMP(net, NORM, ["a", "b", "c"])


@pytest.mark.parametrize("change, message", [
    (dict(latent_linear=2), "latent_linear = 2 needs a linear basis: expected decoder_basis >= 2, got 0"),
    (dict(latent_linear=9, decoder_basis=4), "latent_linear = 9: expected at most latent_dim = 8"),
    (dict(latent_linear=7, decoder_basis=2), r"latent_linear = 7: expected at most decoder_basis x n_joints = 2 x 3 = 6"),
    (dict(latent_linear=-1, decoder_basis=4), r"latent_linear = -1: expected a value in \[0, inf\]"),
    (dict(via_noise=0.0), r"via_noise = 0.0 normalized: expected a value in \(0, inf\)"),
])
def test_the_rules_of_the_split_are_refused_with_what_is_expected(change, message):
    with pytest.raises(ConfigError, match=message):
        ModelConfig(n_joints=3, latent_dim=8, **change)


def test_the_split_is_accepted_up_to_its_limits():
    assert ModelConfig(n_joints=3, latent_dim=6, decoder_basis=2, latent_linear=6).latent_nonlinear == 0
    assert ModelConfig(n_joints=3, latent_dim=8, decoder_basis=4, latent_linear=3).latent_nonlinear == 5
    assert ModelConfig(n_joints=3, latent_dim=8).latent_nonlinear == 8  # no split: the MLP reads all of z


@pytest.mark.parametrize("phase_type", ["linear", "rhythmic"])
@pytest.mark.parametrize("k_l", [4, 7])
def test_numpy_twin_matches_torch_and_its_jacobian_finite_differences(phase_type, k_l):
    net, prim = _split_prim(phase_type, k_l=k_l)
    rng = np.random.default_rng(0)
    z, x = rng.standard_normal((4, 7)), np.linspace(0, 1, 23)
    with torch.no_grad():
        yt = net.decode(torch.tensor(z).float(), torch.tensor(x).float()).double().numpy() * NORM.y_std + NORM.y_mean
    y = prim.decode(z, x)
    np.testing.assert_allclose(y, yt, atol=2e-6)
    np.testing.assert_allclose(prim.decode(z[2], x), y[2], atol=1e-12)
    y0, jac = prim.decoder_jacobian(z[0], x)
    np.testing.assert_allclose(y0, y[0], atol=1e-12)
    eps = 1e-6
    fd = np.stack([(prim.decode(z[0] + eps * e, x) - prim.decode(z[0] - eps * e, x)) / (2 * eps) for e in np.eye(7)], -1)
    np.testing.assert_allclose(jac, fd, atol=1e-7)
    yk, jk = prim.decoder_jacobian(z, x)
    np.testing.assert_allclose(yk, y, atol=1e-12)
    np.testing.assert_allclose(jk[3], prim.decoder_jacobian(z[3], x)[1], atol=1e-12)
    zx = rng.standard_normal((23, 7))
    ref = np.stack([prim.decode(zx[t], x[t:t + 1])[0] for t in range(23)])
    np.testing.assert_allclose(prim.decode_per_phase(zx, x), ref, atol=1e-12)


def test_the_mlp_never_sees_z_lin_and_the_basis_never_sees_z_nl():
    net, prim = _split_prim()
    x = np.linspace(0, 1, 31)
    rng = np.random.default_rng(1)
    z = rng.standard_normal(7)
    dz_lin = np.r_[rng.standard_normal(4), np.zeros(3)]
    a = net.basis.weight.detach().double().numpy().reshape(6, 3, 4) * NORM.y_std[None, :, None]
    phi = phase_basis(x, 6, 1.0, False)
    # moving z_lin changes the trajectory by exactly Φ(x) A Δz_lin, whatever z_nl is
    for z_nl in (z[4:], -2 * z[4:]):
        zz = np.r_[z[:4], z_nl]
        np.testing.assert_allclose(prim.decode(zz + dz_lin, x) - prim.decode(zz, x),
                                   np.einsum("tb,bdk,k->td", phi, a, dz_lin[:4]), atol=1e-12)
    # the Jacobian in z_lin is the linear part's, the same at every z
    jac_a = prim.decoder_jacobian(z, x)[1][..., :4]
    jac_b = prim.decoder_jacobian(rng.standard_normal(7) * 3, x)[1][..., :4]
    np.testing.assert_allclose(jac_a, jac_b, atol=1e-12)
    np.testing.assert_allclose(jac_a, np.einsum("tb,bdk->tdk", phi, a), atol=1e-12)
    # with s = 0 the MLP is gone: z_nl changes nothing
    _, lin = _split_prim(rs=0.0)
    np.testing.assert_allclose(lin.decode(np.r_[z[:4], 5 * z[4:]], x), lin.decode(z, x), atol=1e-12)


def test_a_split_latent_survives_a_checkpoint_round_trip(tmp_path):
    net, prim = _split_prim()
    f = save_checkpoint(tmp_path / "split.safetensors", net, NORM, ["a", "b", "c"])
    ck = load_checkpoint(f)
    assert (ck.config.latent_linear, ck.config.via_noise) == (4, 1e-4)
    x, z = np.linspace(0, 1, 9), np.linspace(-1, 1, 7)
    np.testing.assert_allclose(DeepProMP.from_checkpoint(ck).decode(z, x), prim.decode(z, x), atol=1e-12)


def test_a_linear_block_factors_when_its_covariance_is_read_and_refuses_a_factor_rounding_breaks():
    """The planner's conditioning leaves the factor of I + G Gᵀ to the block: computed on the first read, kept,
    and equal to the factor of the same matrix; two rows equal in floating point at a noise so small that I is
    lost beside G Gᵀ (entries 1e18, spacing 128) make it singular: a ValueError that says so, not numpy's."""
    from deepprompt_ros.primitive.latent import LinearBlock

    def block(design):
        return LinearBlock(scale=np.ones(2), candidates=np.zeros((1, 3)), weights=np.ones(1), factor=None,
                           design=design, form="observation", noise=1e-7, via_error=0.0, nl_var=np.ones(1))

    g = np.array([[0.5, 2.0], [1.0, -0.3]])
    b = block(g)
    assert b.factor is None and b.is_finite()
    np.testing.assert_array_equal(b.chol, np.linalg.cholesky(g @ g.T + np.eye(2)))
    assert b.factor is b.chol  # kept
    np.testing.assert_allclose(b.variance()[:2], np.diag(np.linalg.inv(np.eye(2) + g.T @ g)), rtol=1e-12)
    with pytest.raises(ValueError, match="cannot be factored with via-point noise 1e-07"):
        block(np.array([[1e9, 0.0], [1e9, 0.0]])).chol
