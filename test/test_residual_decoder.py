"""The decoder option "residual over a linear basis" (ModelConfig.decoder_basis), its PCA
initialization, and MAP refinement (DeepProMP.refine_map): numpy == torch, exact Jacobians,
checkpoints, and MAP == closed-form latent Gaussian conditioning for a linear decoder."""
import dataclasses
import json

import numpy as np
import pytest
import torch

from deepprompt_ros.model.checkpoint import Normalization, load_checkpoint, save_checkpoint
from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.data.demonstration import Demonstration
from deepprompt_ros.model.network import DeepProMPNet, ModelConfig
from deepprompt_ros.model.phase import phase_basis
from deepprompt_ros.primitive.deep_promp import DeepProMP
from deepprompt_ros.primitive.latent import LatentGaussian
from deepprompt_ros.baselines.promp import ProMP
from deepprompt_ros.training.basis import init_basis_pca, linear_map_condition, pca_basis
from deepprompt_ros.training.config import TrainConfig
from deepprompt_ros.training.loop import train
from deepprompt_ros.training.tensors import fit_normalization, to_tensors

torch.set_num_threads(1)
NORM = Normalization(np.array([0.1, -0.2, 0.3]), np.array([0.5, 1.5, 2.0]))


def _prim(phase_type="linear", nb=12, rs=0.3, k=5, seed=0):
    torch.manual_seed(seed)
    net = DeepProMPNet(ModelConfig(n_joints=3, latent_dim=k, hidden=16, decoder_basis=nb, residual_scale=rs,
                                   phase_type=phase_type))
    if nb:
        torch.nn.init.normal_(net.basis.bias)
    return net, DeepProMP(net, NORM, ["a", "b", "c"])


@pytest.mark.parametrize("phase_type", ["linear", "rhythmic"])
@pytest.mark.parametrize("rs", [0.0, 0.3, 1.0])
def test_numpy_decode_matches_torch_and_jacobian_matches_finite_differences(phase_type, rs):
    net, prim = _prim(phase_type, rs=rs)
    rng = np.random.default_rng(0)
    z, x = rng.standard_normal((4, 5)), np.linspace(0, 1, 37)
    with torch.no_grad():
        yt = net.decode(torch.tensor(z).float(), torch.tensor(x).float()).double().numpy() * NORM.y_std + NORM.y_mean
    y = prim.decode(z, x)
    np.testing.assert_allclose(y, yt, atol=2e-6)
    np.testing.assert_allclose(prim.decode(z[1], x), y[1], atol=1e-12)
    y0, jac = prim.decoder_jacobian(z[0], x)
    np.testing.assert_allclose(y0, y[0], atol=1e-12)
    eps = 1e-6
    fd = np.stack([(prim.decode(z[0] + eps * e, x) - prim.decode(z[0] - eps * e, x)) / (2 * eps) for e in np.eye(5)], -1)
    np.testing.assert_allclose(jac, fd, atol=1e-7)
    yk, jk = prim.decoder_jacobian(z, x)  # batched latents
    np.testing.assert_allclose(yk, y, atol=1e-12)
    np.testing.assert_allclose(jk[0], jac, atol=1e-12)
    zx = rng.standard_normal((37, 5))  # a latent per phase (blending)
    ref = np.stack([prim.decode(zx[t], x[t:t + 1])[0] for t in range(37)])
    np.testing.assert_allclose(prim.decode_per_phase(zx, x), ref, atol=1e-12)


def test_linear_part_alone_is_a_basis_expansion_in_z():
    net, prim = _prim(rs=0.0)
    x = np.linspace(0, 1, 20)
    phi = phase_basis(x, 12, 1.0, False)
    np.testing.assert_allclose(phi.sum(1), 1.0)
    np.testing.assert_allclose(phi, ProMP(3, 12).basis(x), atol=1e-12)  # the ProMP basis
    z = np.random.default_rng(1).standard_normal(5)
    w = (net.basis.weight.detach().double().numpy() @ z + net.basis.bias.detach().double().numpy()).reshape(12, 3)
    np.testing.assert_allclose(prim.decode(z, x), (phi @ w) * NORM.y_std + NORM.y_mean, atol=1e-6)


def test_checkpoint_round_trip_and_old_configs_default_to_the_plain_decoder(tmp_path):
    net, prim = _prim()
    f = save_checkpoint(tmp_path / "m.safetensors", net, NORM, ["a", "b", "c"])
    ck = load_checkpoint(f)
    assert ck.config.decoder_basis == 12 and ck.config.residual_scale == 0.3
    x, z = np.linspace(0, 1, 9), np.ones(5)
    np.testing.assert_allclose(DeepProMP.from_checkpoint(ck).decode(z, x), prim.decode(z, x), atol=1e-12)
    old = {k: v for k, v in ModelConfig(n_joints=3).to_json().items()
           if k not in ("decoder_basis", "basis_width", "residual_scale")}  # a checkpoint written before the option
    cfg = ModelConfig.from_json(json.loads(json.dumps(old)))
    assert cfg.decoder_basis == 0 and not hasattr(DeepProMPNet(cfg), "basis")
    with pytest.raises(ValueError, match="decoder_basis"):
        ModelConfig(n_joints=3, decoder_basis=1)


def test_map_refinement_of_a_linear_decoder_is_latent_gaussian_conditioning():
    _, prim = _prim(rs=0.0)  # μ_y(z, x) = c(x) + J(x) z exactly
    x = np.array([0.1, 0.45, 0.8])
    rng = np.random.default_rng(2)
    y = prim.decode(0.7 * rng.standard_normal(5), x) + 0.05 * rng.standard_normal((3, 3))  # inside the latent box
    s = 0.05
    c, J = prim.decoder_jacobian(np.zeros(5), x)
    J = J.reshape(-1, 5)
    z_star = np.linalg.solve(J.T @ J / s ** 2 + np.eye(5), J.T @ (y - c).reshape(-1) / s ** 2)
    post = LatentGaussian(np.full(5, 0.3), np.full(5, 0.5))
    res = prim.refine_map(post, x, y, prior="standard", noise_std=s)
    np.testing.assert_allclose(res.latent.mean, z_star, atol=1e-9)
    np.testing.assert_allclose(res.latent.var, np.diag(np.linalg.inv(J.T @ J / s ** 2 + np.eye(5))), atol=1e-12)
    # the posterior prior: Mahalanobis distance to q(z | via-points)
    P = 1.0 / post.var
    z_post = np.linalg.solve(J.T @ J / s ** 2 + np.diag(P), J.T @ (y - c).reshape(-1) / s ** 2 + P * post.mean)
    res_post = prim.refine_map(post, x, y, prior="posterior", noise_std=s)
    np.testing.assert_allclose(res_post.latent.mean, z_post, atol=1e-9)
    assert res_post.error_history[-1] == pytest.approx(res_post.max_error)
    with pytest.raises(ValueError, match="prior"):
        prim.refine_map(post, x, y, prior="nope")


def test_map_refinement_of_the_residual_decoder_lowers_its_objective():
    _, prim = _prim(rs=1.0)
    rng = np.random.default_rng(3)
    x = np.array([0.2, 0.7])
    y = prim.decode(0.7 * rng.standard_normal(5), x) + 0.05 * rng.standard_normal((2, 3))
    post = LatentGaussian(np.zeros(5), np.ones(5))
    res = prim.refine_map(post, x, y, prior="standard", noise_std=0.1)

    def cost(z):
        return float((((y - prim.decode(z, x)) / 0.1) ** 2).sum() + z @ z)

    assert cost(res.latent.mean) < cost(post.mean)
    c = cost(res.latent.mean)
    for e in np.eye(5) * 1e-4:  # near a (local) minimum: on a ReLU decoder LM creeps along kinks at the end
        assert c <= min(cost(res.latent.mean + e), cost(res.latent.mean - e)) + 1e-4 * c


def _demos(n=12, seed=0):
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, 50)
    out = []
    for _ in range(n):
        a, b = rng.standard_normal(2)
        y = np.stack([np.sin(2 * t) + 0.3 * a * t, np.cos(3 * t) * (1 + 0.2 * b), 0.5 * t + 0.1 * a * b], 1)
        out.append(Demonstration(f"d{len(out)}", t, y, ("a", "b", "c")))
    return DemoDataset(tuple(out), "synthetic")


def test_pca_init_reproduces_the_demos_weight_covariance():
    ds = _demos()
    norm = fit_normalization(ds, 50)
    data = to_tensors(ds, norm, 50)
    net = DeepProMPNet(ModelConfig(n_joints=3, latent_dim=30, hidden=8, decoder_basis=10, residual_scale=0.0))
    init_basis_pca(net, data, cov_reg=0.0)
    phi = net.basis_functions(data.x.double()).numpy()
    w = np.linalg.lstsq(phi, data.y.double().numpy().transpose(1, 0, 2).reshape(50, -1), rcond=None)[0]
    w = w.reshape(10, len(ds), 3).transpose(1, 0, 2).reshape(len(ds), -1)  # per demo, row b·d + j
    A = net.basis.weight.detach().double().numpy()
    # (the init's weights carry a 1e-6 relative ridge: agreement to ~1e-3 of the unit-variance data)
    np.testing.assert_allclose(net.basis.bias.detach().double().numpy(), w.mean(0), atol=2e-3)
    np.testing.assert_allclose(A @ A.T, np.cov(w, rowvar=False), atol=2e-3)
    init_basis_pca(net, data, cov_reg=0.05)  # every one of the 30 columns gets variance
    assert np.all(np.linalg.norm(net.basis.weight.detach().numpy(), axis=0) > 0)


def test_training_with_a_fixed_pca_basis_keeps_it_and_the_config_reaches_the_checkpoint(tmp_path):
    ds = _demos(16)
    cfg = TrainConfig(auto_select=False, latent_dim=8, hidden=16, steps=20, val_every=10, batch_size=8, threads=1,
                      decoder_basis=10, basis_init="pca", basis_lr_scale=0.0, residual_scale=0.1, basis_cov_reg=0.05)
    net, norm, _ = train(ds, cfg, out_path=tmp_path / "m.safetensors")
    train_ds, _ = ds.split(max(1, len(ds) // 10), seed=0)
    ref = DeepProMPNet(net.cfg)
    init_basis_pca(ref, to_tensors(train_ds, fit_normalization(train_ds, 100), 100), 0.05)
    torch.testing.assert_close(net.basis.weight, ref.basis.weight)
    ck = load_checkpoint(tmp_path / "m.safetensors")
    assert dataclasses.asdict(ck.config)["decoder_basis"] == 10 and ck.config.residual_scale == 0.1
    with pytest.raises(ValueError, match="basis_init"):
        TrainConfig(basis_init="zeros")


def _pca_prim(ds, k, cov_reg, n_points=50, nb=10):
    """A DeepProMP whose decoder is the PPCA linear part alone (residual 0), fitted to all of ``ds``."""
    norm = fit_normalization(ds, n_points)
    data = to_tensors(ds, norm, n_points)
    torch.manual_seed(0)
    net = DeepProMPNet(ModelConfig(n_joints=3, latent_dim=k, hidden=8, decoder_basis=nb, residual_scale=0.0))
    init_basis_pca(net, data, cov_reg=cov_reg)
    return DeepProMP(net, norm, ds.joint_names), norm


def test_closed_form_linear_map_is_the_deployed_map_refinement_in_joint_units():
    # the CV scores the model MAP refinement deploys: same PPCA, same noise in rad, same trajectory
    ds = _demos(12)
    # full rank (10 RBFs × 3 joints): A Aᵀ is unique (below it the λ-only directions kept are arbitrary)
    prim, norm = _pca_prim(ds, k=30, cov_reg=0.05)
    x = np.linspace(0, 1, 50)
    phi = phase_basis(x, 10, 1.0, False)
    yn = (np.stack([d.resampled(50) for d in ds.demos]) - norm.y_mean) / norm.y_std
    mean, a, _ = pca_basis(phi, yn, 30, 0.05)
    a_net = prim.net.basis.weight.detach().double().numpy()
    np.testing.assert_allclose(a @ a.T, a_net @ a_net.T, atol=1e-5)
    np.testing.assert_allclose(mean, prim.net.basis.bias.detach().double().numpy(), atol=1e-5)
    sel = np.array([3, 17, 30, 44])
    y_via = ds.demos[0].resampled(50)[sel] + 0.02
    s = 0.01  # rad
    res = prim.refine_map(LatentGaussian(np.zeros(30), np.ones(30)), x[sel], y_via, prior="standard", noise_std=s)
    closed = linear_map_condition(phi, mean, a, sel, ((y_via - norm.y_mean) / norm.y_std),
                                  s / np.asarray(norm.y_std)) * norm.y_std + norm.y_mean
    np.testing.assert_allclose(prim.mean_trajectory(res.latent, x), closed, atol=2e-5)
    # a noise in normalized units (not divided by the joint std) would be a different fit
    wrong = linear_map_condition(phi, mean, a, sel, ((y_via - norm.y_mean) / norm.y_std),
                                 np.full(3, s)) * norm.y_std + norm.y_mean
    assert np.abs(wrong - closed).max() > 1e-3


def test_with_residual_scale_switches_the_mlp_part_and_keeps_the_rest():
    net, prim = _prim(rs=0.3)
    x = np.linspace(0, 1, 7)
    z = np.random.default_rng(0).standard_normal(5)
    off = prim.with_residual_scale(0.0)
    lin = net.decode_linear(torch.as_tensor(z[None], dtype=torch.float32),
                            torch.as_tensor(x[None], dtype=torch.float32)).detach().double().numpy()[0]
    np.testing.assert_allclose(off.decode(z, x), lin * NORM.y_std + NORM.y_mean, atol=1e-5)
    np.testing.assert_allclose(prim.with_residual_scale(0.3).decode(z, x), prim.decode(z, x), atol=1e-12)
    assert np.abs(off.decode(z, x) - prim.decode(z, x)).max() > 1e-4
    assert prim.cfg.residual_scale == 0.3  # the original is unchanged
    with pytest.raises(ValueError, match="residual decoder"):
        _prim(nb=0)[1].with_residual_scale(0.0)


def test_pca_regularizer_in_rad_is_lambda_identity_in_joint_units():
    # basis_cov_reg_units "raw": the PPCA covariance is C + λ D⁻² in normalized units (D: each row's joint
    # std), i.e. C_rad + λI in rad — ProMP's regularizer; with equal joint stds it is the normalized one
    ds = _demos()
    norm = fit_normalization(ds, 50)
    phi = phase_basis(np.linspace(0, 1, 50), 10, 1.0, False)
    yn = (np.stack([d.resampled(50) for d in ds.demos]) - norm.y_mean) / norm.y_std
    mean0, a0, _ = pca_basis(phi, yn, 30, 0.0)
    std = np.array([0.2, 1.0, 3.0])
    mean, a, scale = pca_basis(phi, yn, 30, 0.05, joint_std=std)
    np.testing.assert_allclose(mean, mean0, atol=1e-12)
    c = a0 @ a0.T  # the demos' weight covariance (normalized units)
    d = np.tile(std, 10)
    lam = 0.05 * np.mean(np.diag(c) * d ** 2)
    np.testing.assert_allclose(a @ a.T, c + np.diag(lam / d ** 2), atol=1e-10)
    assert np.all(np.diff(scale) <= 1e-12)  # columns in decreasing variance, as the normalized PPCA's
    _, a_iso, _ = pca_basis(phi, yn, 30, 0.05)
    _, a_eq, _ = pca_basis(phi, yn, 30, 0.05, joint_std=np.full(3, 0.7))
    np.testing.assert_allclose(a_eq @ a_eq.T, a_iso @ a_iso.T, atol=1e-10)
    assert np.abs(a @ a.T - a_iso @ a_iso.T).max() > 1e-3


def test_training_with_the_regularizer_in_rad_initializes_from_the_joint_stds():
    ds = _demos(16)
    cfg = TrainConfig(auto_select=False, latent_dim=30, hidden=16, steps=5, val_every=5, batch_size=8, threads=1,
                      decoder_basis=10, basis_init="pca", basis_lr_scale=0.0, residual_scale=0.1, basis_cov_reg=0.05,
                      basis_cov_reg_units="raw")
    net, norm, _ = train(ds, cfg)
    train_ds, _ = ds.split(max(1, len(ds) // 10), seed=0)
    n = fit_normalization(train_ds, 100)
    phi = phase_basis(np.linspace(0, 1, 100), 10, 1.0, False)
    yn = (np.stack([d.resampled(100) for d in train_ds.demos]) - n.y_mean) / n.y_std
    _, a, _ = pca_basis(phi, yn, 30, 0.05, joint_std=np.asarray(n.y_std))
    w = net.basis.weight.detach().double().numpy()
    np.testing.assert_allclose(w @ w.T, a @ a.T, atol=1e-5)
    with pytest.raises(ValueError, match="basis_cov_reg_units"):
        TrainConfig(basis_cov_reg_units="rad")
