"""Training: both objectives learn, the CLI writes a self-describing checkpoint, bad configs are refused."""
import dataclasses
import json
import math
import subprocess
import sys
import time

import numpy as np
import pytest

from deepprompt_ros.model.checkpoint import load_checkpoint
from deepprompt_ros.data.synthetic import bimodal_sine
from deepprompt_ros.training.config import TrainConfig
from deepprompt_ros.training.loop import train


@pytest.mark.parametrize("objective", ["np", "paper"])
def test_training_reduces_validation_error(objective):
    ds = bimodal_sine(60, n_points=50, seed=1)
    cfg = TrainConfig(objective=objective, steps=240, val_every=60, n_points=50, hidden=64, latent_dim=8,
                      threads=1, consistency_weight=1.0 if objective == "np" else 0.0, auto_select=False)
    t0 = time.perf_counter()
    net, norm, hist = train(ds, cfg, log=lambda s: None)
    wall = time.perf_counter() - t0
    first, best = hist[0]["val"]["mean"], min(h["val"]["mean"] for h in hist)
    assert [h["step"] for h in hist] == [60, 120, 180, 240]
    for h in hist:  # the reported parts are the loss's: negative ELBO (nll + β KL) + weighted consistency
        assert all(math.isfinite(h[k]) for k in ("loss", "nll", "kl", "consistency")), h
        assert h["loss"] == pytest.approx(h["nll"] + h["beta"] * h["kl"] + cfg.consistency_weight * h["consistency"],
                                          rel=1e-4), h
    assert best < 0.7 * first, (first, best)
    # the loop runs inside the call: its reported throughput is at least the trajectories over the call's wall time
    assert hist[-1]["samples_per_s"] >= 240 * cfg.batch_size / wall


def test_train_cli_writes_checkpoint_with_provenance(tmp_path):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("steps: 30\nval_every: 15\nhidden: 32\nlatent_dim: 4\nthreads: 1\nn_points: 40\nauto_select: false\n")
    out = tmp_path / "m.safetensors"
    proc = subprocess.run([sys.executable, "-m", "deepprompt_ros.training.cli", "--builtin", "bimodal_sine",
                           "--config", str(cfg), "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert str(out.resolve()) in proc.stdout
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    ck = load_checkpoint(out)
    assert ck.joint_names == ("joint_1",) and ck.config.phase_type == "linear"
    assert ck.config.context_dims == (("mode", 1),)
    prov = ck.metadata["provenance"]
    assert prov["dataset"].startswith("bimodal_sine") and prov["n_train"] + prov["n_val"] == 200
    assert ck.metadata["train_config"]["steps"] == 30
    assert ck.metadata["metrics"]["best_val_mse_rad2"] == pytest.approx(summary["best_val_mse_rad2"])
    assert np.all(ck.normalization.y_std > 0)


@pytest.mark.parametrize("text, message", [
    ("steps: -1\n", "steps = -1 updates: expected a value in [1, inf]"),
    ("lr: fast\n", "lr = 'fast': expected a number"),
    ("lr: 0\n", "lr = 0: expected a value in (0, inf)"),
    ("learning_rate: 0.1\n", "unknown parameter 'learning_rate'"),
    ("objective: magic\n", "objective = 'magic': expected one of 'paper', 'np'"),
    ("decoder_basis: 1\n", "decoder_basis = 1: expected 0 (no linear basis) or >= 2"),
    ("[1, 2\n", "not valid YAML"),
])
def test_bad_training_config_is_refused(tmp_path, text, message):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(text)
    proc = subprocess.run([sys.executable, "-m", "deepprompt_ros.training.cli", "--builtin", "bimodal_sine",
                           "--config", str(cfg), "--out", str(tmp_path / "x.safetensors")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and message in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "x.safetensors").exists()


def test_bad_dataset_folder_is_refused(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "deepprompt_ros.training.cli", "--data", str(tmp_path / "none"),
                           "--out", str(tmp_path / "x.safetensors")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "does not exist" in proc.stderr and "Traceback" not in proc.stderr


def test_low_information_subsets_come_from_the_phases_where_demos_agree():
    import torch

    from deepprompt_ros.training.objectives import sample_subset_weights
    from deepprompt_ros.training.tensors import fit_normalization, to_tensors

    ds = bimodal_sine(64, n_points=100, seed=3)
    cfg = TrainConfig(n_points=100, max_via_points=10, p_via_points=1.0, p_empty=0.0, p_context=0.0,
                      p_low_info=1.0, low_info_fraction=0.2)
    data = to_tensors(ds, fit_normalization(ds, 100), 100)
    idx = torch.arange(64)
    kinds = [("via", slice(0, 100)), ("mode", slice(100, 101))]
    w_sub, _ = sample_subset_weights(cfg, data, idx, kinds, torch.Generator().manual_seed(0))
    chosen = np.flatnonzero(w_sub[:, :100].sum(0).numpy())
    x = np.linspace(0, 1, 100)[chosen]
    # the 20 % of phases with the least spread across the demos are those around the zero crossings
    assert np.all(np.min(np.abs(x[:, None] - np.array([0.0, 0.5, 1.0])), 1) < 0.12), x
    counts = w_sub[:, :100].sum(1).numpy()
    assert counts.min() >= 1 and counts.max() >= 6  # up to max_via_points, not only single points
    w_plain, _ = sample_subset_weights(dataclasses.replace(cfg, p_low_info=0.0), data, idx, kinds,
                                       torch.Generator().manual_seed(0))
    far = np.min(np.abs(np.linspace(0, 1, 100)[:, None] - np.array([0.0, 0.5, 1.0])), 1) > 0.15
    assert w_plain[:, :100].numpy()[:, far].sum() > 0  # without it, points fall anywhere


def test_exp_variance_head_numpy_matches_torch_and_reaches_tiny_precision():
    import torch

    from deepprompt_ros.model.checkpoint import Normalization
    from deepprompt_ros.model.network import LOGVAR_MAX, DeepProMPNet, ModelConfig
    from deepprompt_ros.primitive.deep_promp import DeepProMP

    torch.manual_seed(0)
    net = DeepProMPNet(ModelConfig(n_joints=2, latent_dim=4, hidden=16, variance_head="exp")).double()
    with torch.no_grad():
        net.head.bias[4:] = torch.tensor([0.0, 3.0, 8.0, 30.0])  # last one beyond the clamp
    norm = Normalization(y_mean=np.zeros(2), y_std=np.ones(2), ctx_mean={}, ctx_std={})
    p = DeepProMP(net.float(), norm, ["a", "b"])
    x, y = np.array([0.2, 0.7]), np.array([[0.1, -0.3], [0.4, 0.2]])
    mu_np, var_np = p.encode_via_points(x, y)
    with torch.no_grad():
        mu_t, var_t = net.encode_via_points(torch.tensor(x, dtype=torch.float32)[None],
                                            torch.tensor(y, dtype=torch.float32)[None])
    np.testing.assert_allclose(mu_np, mu_t[0].numpy(), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(var_np, var_t[0].numpy(), rtol=1e-5)
    assert np.all(var_np[:, 3] == pytest.approx(np.exp(LOGVAR_MAX) + 1e-4, rel=1e-6))  # clamped, not inf
    assert np.all(1.0 / var_np[:, 2] < 1e-2)  # a moderate output already says almost nothing
    with pytest.raises(ValueError, match="variance_head"):
        ModelConfig(n_joints=1, variance_head="relu")


def test_consistency_coverage_reaches_the_encoder_only_when_asked():
    import torch

    from deepprompt_ros.model.network import DeepProMPNet, ModelConfig
    from deepprompt_ros.training.objectives import loss_fn
    from deepprompt_ros.training.tensors import fit_normalization, to_tensors

    ds = bimodal_sine(16, n_points=30, seed=0)
    data = to_tensors(ds, fit_normalization(ds, 30), 30)
    idx = torch.arange(16)
    grads = {}
    for mode in ("none", "coverage", "all"):
        cfg = TrainConfig(n_points=30, latent_dim=4, hidden=16, consistency_weight=1.0, consistency_encoder=mode,
                          p_empty=0.0, p_via_points=1.0, p_context=0.0)
        torch.manual_seed(0)
        net = DeepProMPNet(ModelConfig(n_joints=1, latent_dim=4, hidden=16, context_dims=(("mode", 1),)))
        # the same draws with and without the term: the difference is the consistency part alone
        with_term, _, _, _ = loss_fn(net, cfg, data, idx, torch.Generator().manual_seed(1), beta=0.0)
        cfg0 = dataclasses.replace(cfg, consistency_weight=0.0)
        without, _, _, _ = loss_fn(net, cfg0, data, idx, torch.Generator().manual_seed(1), beta=0.0)
        (with_term - without).backward()
        grads[mode] = (net.via_encoder[0].weight.grad.abs().sum().item(), net.decoder[0].weight.grad.abs().sum().item())
    assert grads["none"][0] == 0.0 and grads["none"][1] > 0  # a decoder term only
    assert grads["coverage"][0] > 0 and grads["all"][0] > 0  # z carries the term into the encoder
    assert grads["coverage"][0] != pytest.approx(grads["all"][0])  # precision part stays out of it
    with pytest.raises(ValueError, match="consistency_encoder"):
        TrainConfig(consistency_encoder="both")


def test_architecture_parameters_are_declared_once_in_the_model_config():
    from deepprompt_ros.baselines.concat_net import ConcatNetConfig
    from deepprompt_ros.common.params import ConfigError, specs_of
    from deepprompt_ros.model.network import ModelConfig

    model = {s.name: s for s in specs_of(ModelConfig)}
    shared = [s for s in specs_of(TrainConfig) + specs_of(ConcatNetConfig) if s.name in model]
    assert len(shared) == 12 + 7 and all(s == model[s.name] for s in shared)
    for make in (lambda: TrainConfig(decoder_basis=1), lambda: ModelConfig(n_joints=1, decoder_basis=1)):
        with pytest.raises(ConfigError, match=r"decoder_basis = 1: expected 0 \(no linear basis\) or >= 2"):
            make()
    with pytest.raises(ValueError, match=r"sigma_y = 0.0 normalized: expected a value in \(0, inf\)"):
        ConcatNetConfig("cnmp", 1, sigma_y=0.0)


def test_auto_select_refuses_a_grid_too_short_for_its_smallest_basis():
    """The automatic selection tries at least 10 basis functions per joint, which need 20 phases: a
    shorter n_points is refused naming both keys and the way out, before any data is read."""
    from deepprompt_ros.common.params import ConfigError
    with pytest.raises(ConfigError, match=r"n_points = 10 with auto_select.*n_points >= 20.*auto_select: false"):
        TrainConfig(n_points=10)
    assert TrainConfig(n_points=10, auto_select=False, max_via_points=5).n_points == 10
