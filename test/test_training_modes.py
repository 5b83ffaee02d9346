"""The modes of the demonstrations in the model selection (``TrainConfig.linear_modes``,
deepprompt_ros.training.basis.weight_modes): how many are found, the linear part taken within them,
a trained split model that keeps them, and the fallback to one Gaussian when its residual is dropped."""
import dataclasses
import math

import numpy as np
import pytest
import torch

from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.data.demonstration import Demonstration, demo_from_arrays
from deepprompt_ros.data.synthetic import bimodal_sine
from deepprompt_ros.model.checkpoint import load_checkpoint
from deepprompt_ros.model.network import DeepProMPNet, ModelConfig
from deepprompt_ros.primitive.deep_promp import DeepProMP
from deepprompt_ros.model.phase import phase_basis
from deepprompt_ros.training.basis import (MODE_DIP, MODE_MEAN_MARGIN, basis_weights, cv_modes, mode_dip,
                                          pca_basis, weight_modes)
from deepprompt_ros.training.config import TrainConfig
from deepprompt_ros.training.distributed import Runtime
from deepprompt_ros.training.loop import judge_with_fallback, selection_line, train
from deepprompt_ros.training.selection import (MODE_NOISES, choose_mode_noise, compare_modes, select_linear_part,
                                               with_via_noise)
from deepprompt_ros.training.tensors import fit_normalization

torch.set_num_threads(1)
T = 50
X = np.linspace(0.0, 1.0, T)


def curves(n: int, seed: int, amplitude) -> DemoDataset:
    """3 joints: offset + amplitude · sin πx (per joint) + drift; ``amplitude(rng)`` (3,) per demo."""
    rng = np.random.default_rng(seed)
    demos = []
    for i in range(n):
        a, o, dr = amplitude(rng), rng.normal(0.0, 0.2, 3), rng.normal(0.0, 0.3, 3)
        q = o + a * np.sin(np.pi * X)[:, None] * [1.0, 0.5, -0.7] + dr * X[:, None] ** 2
        demos.append(Demonstration(f"d{i}", X * 2.0, q, ("a", "b", "c")))
    return DemoDataset(tuple(demos), f"curves(seed={seed})")


def weights(ds: DemoDataset, n_b: int = 10) -> np.ndarray:
    norm = fit_normalization(ds, T)
    y = (np.stack([d.resampled(T) for d in ds.demos]) - norm.y_mean) / norm.y_std
    return basis_weights(phase_basis(X, n_b, 1.0, False), y)


# ----------------------------------------------------------------------------- how many modes
def test_mode_dip_is_one_without_a_dip_and_falls_with_the_separation():
    assert mode_dip(0.0, 0.5, 0.5) == pytest.approx(1.0)
    assert mode_dip(2.0, 0.5, 0.5) == pytest.approx(1.0, abs=1e-9)  # equal halves: bimodal beyond Δ = 2
    # the two halves of a uniform spread (means 1/4 and 3/4, std 1/√48 each: Δ = √12) dip to 2φ(√3)/(φ(0) + φ(√12))
    phi = lambda u: math.exp(-0.5 * u * u)  # noqa: E731
    assert mode_dip(math.sqrt(12), 0.5, 0.5) == pytest.approx(2 * phi(math.sqrt(3)) / (1 + phi(math.sqrt(12))),
                                                             rel=1e-3)
    assert mode_dip(4.9, 0.5, 0.5) == pytest.approx(MODE_DIP, abs=0.01)
    assert mode_dip(6.0, 0.9, 0.1) < mode_dip(5.0, 0.9, 0.1) < mode_dip(4.0, 0.9, 0.1)


@pytest.mark.parametrize("kind", ["gaussian", "uniform", "outliers"])
def test_one_mode_on_unimodal_demos(kind):
    if kind == "outliers":  # 2 of 40 demos far out: outlying demos, no mode
        ds = curves(40, 5, lambda rng: rng.normal(1.0, 0.2, 3))
        far = [dataclasses.replace(d, q=d.q + 3.0 * np.sin(np.pi * X)[:, None]) for d in ds.demos[:2]]
        ds = DemoDataset(tuple(far) + ds.demos[2:], "outliers")
    else:  # amplitudes spread evenly over [0.5, 1.5] (one mode that a single Gaussian fits badly) or Gaussian
        draw = (lambda rng: rng.normal(1.0, 0.2, 3)) if kind == "gaussian" else (lambda rng: rng.uniform(0.5, 1.5, 3))
        ds = curves(120, 5, draw)
    modes = weight_modes(weights(ds), seed=0)
    assert modes.n_modes == 1 and np.all(modes.labels == 0), modes.record
    rows = modes.record["mixtures"]
    assert rows["1"]["admissible"] and set(rows) == {"1", "2", "3", "4"}
    if kind == "outliers":  # BIC alone prefers a second group: the 2 outlying demos
        assert rows["2"]["bic"] < rows["1"]["bic"] and min(rows["2"]["sizes"]) == 2 and not rows["2"]["admissible"]


def test_two_modes_on_bimodal_demos_and_each_demo_on_its_own():
    ds = bimodal_sine(40, n_points=T, n_joints=2, seed=1)
    modes = weight_modes(weights(ds), seed=0)
    sign = np.array([d.contexts["mode"][0, 0] for d in ds.demos])
    assert modes.n_modes == 2
    assert len({(m, s) for m, s in zip(modes.labels, sign)}) == 2  # the labels are the demos' modes
    rows = modes.record["mixtures"]
    assert rows["2"]["admissible"] and rows["2"]["dip"] < 1e-6 and rows["2"]["bic"] < rows["1"]["bic"]
    assert weight_modes(weights(ds), seed=0).labels.tolist() == modes.labels.tolist()  # seeded
    fixed = weight_modes(weights(ds), seed=0, n_modes=2)
    assert fixed.labels.tolist() == modes.labels.tolist()
    assert weight_modes(weights(ds), seed=0, n_modes=1).n_modes == 1
    with pytest.raises(ValueError, match="n_modes = 0"):
        weight_modes(weights(ds), n_modes=0)


def test_the_pca_within_modes_spans_the_variation_inside_a_mode():
    ds = bimodal_sine(40, n_points=T, n_joints=2, seed=1)
    norm = fit_normalization(ds, T)
    y = (np.stack([d.resampled(T) for d in ds.demos]) - norm.y_mean) / norm.y_std
    phi = phase_basis(X, 10, 1.0, False)
    w = basis_weights(phi, y)
    labels = weight_modes(w, seed=0).labels
    mean, a, _ = pca_basis(phi, y, 20, 0.0, labels=labels)
    np.testing.assert_allclose(mean, w.mean(0), atol=1e-12)  # b: the mean of all demos
    dev = w - np.stack([w[labels == g].mean(0) for g in (0, 1)])[labels]
    np.testing.assert_allclose(a @ a.T, dev.T @ dev / (len(w) - 2), atol=1e-10)
    _, a_all, _ = pca_basis(phi, y, 20, 0.0)
    # the between-mode offset (the sine's ±A) dominates one Gaussian; within the modes only the amplitudes vary
    assert np.trace(a @ a.T) < 0.05 * np.trace(a_all @ a_all.T)


def test_the_selection_records_the_modes_it_chose():
    out, rec = select_linear_part(bimodal_sine(30, n_points=T, seed=2), TrainConfig(n_points=T, cv_folds=3), 1)
    assert out.linear_modes == 2 and rec["linear_modes"] == 2 and rec["modes"]["n_modes"] == 2
    assert "BIC" in rec["modes"]["criterion"] and rec["modes"]["mixtures"]["2"]["admissible"]
    out, rec = select_linear_part(curves(30, 3, lambda rng: rng.normal(1.0, 0.2, 3)), TrainConfig(n_points=T,
                                                                                                 cv_folds=3), 3)
    assert out.linear_modes == 1 and rec["modes"]["n_modes"] == 1


def _two_amplitudes(rng):
    return (1.0 if rng.random() < 0.5 else -1.0) + rng.normal(0.0, 0.1, 3)


def test_the_cross_validation_admits_modes_whose_means_are_not_worse():
    # amplitudes ±1: two modes, which the start point cannot tell apart and 5 via-points can
    cfg = TrainConfig(n_points=T, cv_folds=3)
    out, rec = select_linear_part(curves(60, 1, _two_amplitudes), cfg, 3)
    r = rec["modes"]["cross_validation"]
    assert out.linear_modes == 2 and r["admitted"] and r["better"] and r["worse"] == [False] * 3
    diff, se = np.array(r["relative_difference"]), np.array(r["standard_error"])
    assert diff[2] < -0.3 and diff[2] + 2 * se[2] < 0  # the via-points' means much better with the modes
    assert np.all(diff <= 2 * se)
    # one Gaussian's errors are the linear part's cross-validation's at the chosen row (same folds and sets)
    np.testing.assert_allclose(r["mse_one_mode"], rec["cross_validation"]["cv_mse_parts"][:3], rtol=1e-9)
    # one Gaussian of amplitudes split into two modes: the within-mode covariance from half the demos each
    # makes the means from the start and from start + end worse by more than two standard errors
    ds = curves(60, 1, lambda rng: rng.normal(1.0, 0.3, 3))
    _, rec = select_linear_part(ds, cfg, 3)
    assert rec["modes"]["n_modes"] == 1  # BIC keeps one; the cross-validation is asked of two
    r = cv_modes(ds, T, rec, 2, folds=3, seed=0)
    diff, se = np.array(r["relative_difference"]), np.array(r["standard_error"])
    assert not r["admitted"] and not r["better"] and np.any((diff > 2 * se) & (diff > MODE_MEAN_MARGIN))
    assert r == cv_modes(ds, T, rec, 2, folds=3, seed=0)  # deterministic
    with pytest.raises(ValueError, match="n_modes >= 2"):
        cv_modes(ds, T, rec, 1)


def test_the_selection_drops_modes_the_cross_validation_does_not_admit(monkeypatch):
    import deepprompt_ros.training.selection as selection
    ds, cfg = curves(60, 1, _two_amplitudes), TrainConfig(n_points=T, cv_folds=3)
    real = selection.cv_modes
    monkeypatch.setattr(selection, "cv_modes", lambda *a, **k: {**real(*a, **k), "admitted": False, "better": False,
                                                               "worse": [False, True, False]})
    out, rec = select_linear_part(ds, cfg, 3)
    assert out.linear_modes == 1 and rec["linear_modes"] == 1 and rec["modes"]["n_modes"] == 2
    assert not rec["modes"]["cross_validation"]["admitted"]
    line = selection_line({"linear_part": rec, "residual": {"kept": False, "reason": "none"}})
    assert "2 modes of the basis weights not admitted (their executed mean from start+end: MSE" in line
    assert line.endswith("linear_modes 1; residual: none")


# ----------------------------------------------------------------------------- training with the modes
def test_the_decoder_holds_the_modes_beside_a_dropped_residual(tmp_path):
    # one update at a learning rate of 1 leaves the MLP residual garbage: the energy score drops it; the modes
    # are in the decoder (b + m_k + A z_lin), kept (judge_modes false): the samples from the zero crossings
    # lie on the modes
    ds = bimodal_sine(40, n_points=T, seed=4)
    cfg = TrainConfig(n_points=T, cv_folds=3, latent_nonlinear=2, hidden=8, steps=1, val_every=1, batch_size=4,
                      lr=1.0, threads=1, max_via_points=5, judge_modes=False)
    info = {}
    net, norm, _ = train(ds, cfg, out_path=tmp_path / "m.safetensors", info=info, log=lambda s: None)
    sel = info["selection"]
    assert sel["linear_part"]["linear_modes"] == 2
    assert not sel["residual"]["kept"] and sel["modes_fallback"]["kept_modes"], sel
    assert info["train_config"]["linear_modes"] == 2 and net.cfg.decoder_modes == 2 and net.cfg.residual_scale == 0.0
    assert sel["modes_fallback"]["noise"]["via_noise"] == net.cfg.via_noise
    # the served linear part: the PPCA within the modes, each mode's offset the mean of its demos' weights
    train_ds, _ = ds.split(4, seed=0)
    y = (np.stack([d.resampled(T) for d in train_ds.demos]) - norm.y_mean) / norm.y_std
    phi = phase_basis(X, net.cfg.decoder_basis, 1.0, False)
    w = basis_weights(phi, y)
    labels = weight_modes(w, seed=cfg.seed, n_modes=2).labels
    offsets = np.stack([w[labels == g].mean(0) for g in (0, 1)]) - w.mean(0)
    np.testing.assert_allclose(net.mode_offsets.numpy(), offsets, atol=1e-5)
    np.testing.assert_allclose(net.mode_cumulative_shares.numpy(), [np.mean(labels == 0), 1.0], atol=1e-7)
    loaded = load_checkpoint(tmp_path / "m.safetensors")
    assert loaded.metadata["selection"]["modes_fallback"]["kept_modes"]
    from deepprompt_ros.primitive.deep_promp import DeepProMP
    prim = DeepProMP.from_checkpoint(str(tmp_path / "m.safetensors"))
    np.testing.assert_array_equal(prim.net.mode_offsets.numpy(), net.mode_offsets.numpy())
    x = np.linspace(0.0, 1.0, 101)
    s = prim.sample(prim.condition(x[[0, 50, 100]], np.zeros((3, 1))), x, 200, np.random.default_rng(0))
    pos, neg = float((s[:, 25, 0] > 0.6).mean()), float((s[:, 25, 0] < -0.6).mean())
    assert pos + neg >= 0.95 and min(pos, neg) >= 0.2, (pos, neg)


# ----------------------------------------------------------------------------- modes against one mode
def _bimodal_demos(n, seed, shape=lambda x: np.sin(np.pi * x)):
    """Demos of the hand-built two-mode models of test_linear_conditioning: a ramp with small variations
    plus ±shape(x)·(1, 0.5), half of each sign."""
    rng = np.random.default_rng(seed)
    x = np.linspace(0, 1, 50)
    sign = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    y = (0.3 * x[None, :, None] * np.array([1.0, 0.5]) + rng.normal(0, 0.05, (n, 1, 2)) * x[None, :, None]
         + rng.normal(0, 0.05, (n, 1, 2)) * (x ** 2)[None, :, None]
         + sign[:, None, None] * shape(x)[None, :, None] * np.array([1.0, 0.5]))
    return x, y


def _one_gaussian(x, shape) -> DeepProMPNet:
    """One Gaussian (the PPCA of 40 demos of :func:`_bimodal_demos`, no residual) of the modes ±shape(x)."""
    _, y_tr = _bimodal_demos(40, 1, shape)
    mean, a, _ = pca_basis(phase_basis(x, 8, 1.0, False), y_tr, 16, 0.05)
    net = DeepProMPNet(ModelConfig(n_joints=2, latent_dim=17, hidden=8, decoder_basis=8, latent_linear=16,
                                   residual_scale=0.0))
    with torch.no_grad():
        net.basis.bias.copy_(torch.as_tensor(mean))
        net.basis.weight.copy_(torch.as_tensor(a))
    return net.eval()


@pytest.mark.parametrize("apart_at_start", [False, True])
def test_modes_are_kept_over_one_mode_only_where_they_score_better_and_no_mean_is_worse(apart_at_start):
    """Two modes ±shape(x) against one Gaussian of the same demos (its PPCA). Where the modes meet at the
    start (sin πx) the start point alone cannot tell them apart: the executed mean weighs the modes by their
    posterior probabilities (about one half each), as good as the Gaussian's mean between them, where one
    mode's mean would miss every demo of the other (1.5x the Gaussian's error before the weighting). Where
    they are apart there (0.5 + sin πx) the start tells them apart and the mean is better. The modes are
    kept on 40 validation demos, whose samples score better by more than two standard errors (measured
    0.15 ± 0.05 where the modes meet at the start); on 12 demos of those the samples are better by less than
    one standard error (0.09 ± 0.10) and one Gaussian is kept."""
    from test_linear_conditioning import decoder_modes_model
    shape = (lambda x: 0.5 + np.sin(np.pi * x)) if apart_at_start else (lambda x: np.sin(np.pi * x))
    several, x = decoder_modes_model(shares=(0.5, 1.0), shape=shape)
    one = (_one_gaussian(x, shape), several.norm)
    cfg = TrainConfig(n_points=50)
    for n_val in (12, 40):
        _, y_val = _bimodal_demos(n_val, 2, shape)
        val = DemoDataset(tuple(demo_from_arrays(f"v{i}", x * 4.0, y_val[i], ["a", "b"])
                                for i in range(len(y_val))))
        keep, rec = compare_modes((several.net, several.norm), one, ["a", "b"], val, cfg)
        start_modes, start_one = rec["mse_modes"][0], rec["mse_one_mode"][0]
        assert rec["means_not_worse"], rec
        if apart_at_start:
            assert start_modes < 0.5 * start_one, rec
        else:  # the weighted mean: within 5 % of the Gaussian's (measured 1.5 %)
            assert abs(start_modes / start_one - 1.0) < 0.05, rec
        better = rec["relative_difference"] + 2.0 * rec["standard_error"] < 0
        assert keep == better, rec
        assert keep == (apart_at_start or n_val == 40), rec
    keep, rec = compare_modes(one, (several.net, several.norm), ["a", "b"], val, cfg)
    assert not keep and rec["relative_difference"] > 0, rec


@pytest.mark.parametrize("judge_modes, cv_better", [(False, False), (True, False), (True, True)])
def test_judge_modes_false_keeps_the_modes_at_their_chosen_noise_without_the_training_with_one_mode(judge_modes,
                                                                                                    cv_better):
    """With ``judge_modes`` false, or where the selection's cross-validation found the modes' executed means
    better, the two-mode model is served with the via-point noise that fits the validation demos best: no
    training with one mode runs and the record says why; else that training runs."""
    from test_linear_conditioning import decoder_modes_model
    several, x = decoder_modes_model(shares=(0.5, 1.0))
    _, y_val = _bimodal_demos(12, 2)
    val = DemoDataset(tuple(demo_from_arrays(f"v{i}", x * 4.0, y_val[i], ["a", "b"]) for i in range(len(y_val))))
    cfg = TrainConfig(n_points=50, linear_modes=2, judge_modes=judge_modes, latent_dim=17, decoder_basis=8,
                      latent_linear=16, via_noise=1.0)
    selection = {"linear_part": {"decoder_basis": 8, "latent_linear": 16, "latent_dim": 17, "basis_cov_reg": 0.05,
                                 "basis_cov_reg_units": "normalized", "via_noise": 1.0, "method": "by hand",
                                 "linear_modes": 2, "modes": {"n_modes": 2, "cross_validation": {
                                     "admitted": True, "better": cv_better}}}}
    calls, lines = [], []

    def fit_again(c):
        calls.append(c.linear_modes)
        raise RuntimeError("the training with one mode")

    def run():
        return judge_with_fallback(cfg, (several.net, several.norm, [], 0.0), selection, lines.append, fit_again,
                                   Runtime(), ["a", "b"], val, None)

    if judge_modes and not cv_better:
        with pytest.raises(RuntimeError, match="one mode"):
            run()
        assert calls == [1]
        return
    out_cfg, (net, _, _, _) = run()
    record = selection["modes_fallback"]
    assert calls == [] and out_cfg.linear_modes == 2 and net.cfg.decoder_modes == 2
    mse = record["noise"]["mse_random_via_points"]
    assert net.cfg.via_noise == out_cfg.via_noise == record["noise"]["via_noise"] == float(min(mse, key=mse.get))
    from deepprompt_ros.training.basis import CV_VIA_NOISES
    assert sorted(mse) == sorted(f"{v:g}" for v in CV_VIA_NOISES) and max(mse.values()) > min(mse.values())
    rel = record["noise"]["mode_noise_relative_mse_start_plus_random"]
    assert net.cfg.mode_noise == out_cfg.mode_noise == record["noise"]["mode_noise"] == float(min(rel, key=rel.get))
    assert sorted(rel, key=float) == [f"{v:g}" for v in MODE_NOISES if v >= net.cfg.via_noise]
    why = "the cross-validation's executed means better with the modes" if cv_better else "judge_modes false"
    assert record["kept_modes"] and record["reason"] == f"{why}: kept without the training with one mode"
    assert f"linear_modes 2 ({why}" in lines[-1]


def test_the_modes_weights_noise_is_chosen_where_the_modes_offsets_differ_by_their_estimation_error():
    """Two modes that meet at the start in the demos (the start 0 in every demo) but whose offsets differ
    there by 0.02 rad (an estimate's error): at the model's small via-point noise the start alone weighs the
    modes by that difference (1 − 2e-6 on the nearer), and the mean from the start follows one mode; the noise of the
    modes' weights chosen on the validation demos is larger, the weights near the shares and the mean
    between the modes, with a lower MSE."""
    from test_linear_conditioning import decoder_modes_model
    several, x = decoder_modes_model(shares=(0.5, 1.0))
    phi = phase_basis(x, 8, 1.0, False)
    with torch.no_grad():  # mode 1's offset 0.02 rad higher at x = 0 (a bump of the first basis function)
        bump = np.linalg.lstsq(phi, np.exp(-(x / 0.1) ** 2)[:, None] * np.array([0.02, 0.01]), rcond=None)[0]
        several.net.mode_offsets[1] += torch.as_tensor((bump / np.asarray(several.norm.y_std)).reshape(-1),
                                                       dtype=several.net.mode_offsets.dtype)
    net = with_via_noise(several.net, 1e-3)
    _, y_val = _bimodal_demos(12, 2)
    val = DemoDataset(tuple(demo_from_arrays(f"v{i}", x * 4.0, y_val[i], ["a", "b"]) for i in range(len(y_val))))
    chosen, record = choose_mode_noise(net, several.norm, ["a", "b"], val, TrainConfig(n_points=50))
    assert chosen.cfg.mode_noise > chosen.cfg.via_noise, record

    def start(n):
        prim = DeepProMP(n, several.norm, ["a", "b"])
        lats = [prim.condition(x[:1], y[:1]) for y in y_val]
        return (np.array([lat.mode_weights for lat in lats]),
                np.mean([((prim.mean_trajectory(lat, x) - y) ** 2).mean() for lat, y in zip(lats, y_val)]))
    w_small, mse_small = start(with_via_noise(chosen, chosen.cfg.via_noise, 0.0))
    w_chosen, mse_chosen = start(chosen)
    assert w_small[:, 0].min() > 0.99 and np.abs(w_chosen - 0.5).max() < 0.01, (w_small, w_chosen)
    assert mse_chosen < 0.6 * mse_small, (mse_chosen, mse_small)  # (measured 0.50)
    # against one Gaussian: the means from the start weighed by the offsets' error are worse over the
    # conditionings, and the modes are not kept; with the chosen noise they are not worse
    one = (_one_gaussian(x, lambda x: np.sin(np.pi * x)), several.norm)
    _, y_val = _bimodal_demos(40, 2)
    val = DemoDataset(tuple(demo_from_arrays(f"v{i}", x * 4.0, y_val[i], ["a", "b"]) for i in range(len(y_val))))
    cfg = TrainConfig(n_points=50)
    keep, rec = compare_modes((with_via_noise(chosen, chosen.cfg.via_noise, 0.0), several.norm), one, ["a", "b"],
                              val, cfg)
    assert not keep and not rec["means_not_worse"], rec
    keep, rec = compare_modes((chosen, several.norm), one, ["a", "b"], val, cfg)
    assert rec["means_not_worse"], rec
