"""The model selection of ``TrainConfig.auto_select`` (deepprompt_ros.training.selection and the
cross-validation of the linear part in deepprompt_ros.training.basis) and the share of prior-only
training subsets (p_empty)."""
import dataclasses

import numpy as np
import pytest
import torch

from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.data.demonstration import Demonstration
from deepprompt_ros.data.synthetic import bimodal_sine
from deepprompt_ros.model.network import DeepProMPNet, ModelConfig
from deepprompt_ros.model.phase import phase_basis
from deepprompt_ros.primitive.deep_promp import DeepProMP
from deepprompt_ros.primitive.latent import PLANNER_VIA_NOISE
from deepprompt_ros.training.basis import (CV_VIA_NOISES, _departs, cv_basis_hyperparameters, cv_score, cv_via_sets,
                                           fold_assignment, init_basis_pca, pca_basis)
from deepprompt_ros.training.config import TrainConfig
from deepprompt_ros.training.objectives import sample_subset_weights
from deepprompt_ros.training.selection import (RESIDUAL_SAMPLES, energy_score, judge_residual, keep_residual,
                                               select_linear_part, without_residual)
from deepprompt_ros.training.tensors import fit_normalization, to_tensors

torch.set_num_threads(1)
T = 50
X = np.linspace(0.0, 1.0, T)


def smooth_demos(n: int, seed: int = 0, extra=None) -> DemoDataset:
    """3 joints, smooth curves varying by amplitude, offset and a drift (+ ``extra`` (T,) on joint 1)."""
    rng = np.random.default_rng(seed)
    demos = []
    for i in range(n):
        a, o, dr = rng.normal(1.0, 0.2, 3), rng.normal(0.0, 0.2, 3), rng.normal(0.0, 0.3, 3)
        q = o + a * np.sin(np.pi * X)[:, None] * [1.0, 0.5, -0.7] + dr * X[:, None] ** 2
        if extra is not None:
            q[:, 0] += extra
        demos.append(Demonstration(f"d{i}", X * 2.0, q, ("a", "b", "c")))
    return DemoDataset(tuple(demos), f"smooth(seed={seed})")


# ----------------------------------------------------------------------------- p_empty
@pytest.mark.parametrize("contexts", [0, 1])
def test_the_share_of_prior_only_subsets_is_p_empty(contexts):
    ds = bimodal_sine(40, n_points=30, seed=0)
    if not contexts:
        ds = DemoDataset(tuple(dataclasses.replace(d, contexts={}) for d in ds.demos), "no contexts")
    data = to_tensors(ds, fit_normalization(ds, 30), 30)
    kinds = [("via", slice(0, 30))] + ([("mode", slice(30, 31))] if contexts else [])
    cfg = TrainConfig(n_points=30, p_empty=0.1, p_via_points=0.7, p_context=0.5)
    idx = torch.randint(0, 40, (40000,), generator=torch.Generator().manual_seed(1))
    w_sub, _ = sample_subset_weights(cfg, data, idx, kinds, torch.Generator().manual_seed(2))
    given = w_sub.sum(1) > 0
    # binomial standard error of a share over 40 000 rows: 0.0015; 4 of them
    assert abs(1.0 - given.float().mean().item() - 0.1) < 0.006
    if contexts:  # among the others the kinds are independent draws conditioned on something given
        via, ctx = w_sub[given, :30].sum(1) > 0, w_sub[given, 30] > 0
        p_any = 1 - 0.3 * 0.5
        assert abs(via.float().mean().item() - 0.7 / p_any) < 0.01 and abs(ctx.float().mean().item() - 0.5 / p_any) < 0.01
        assert abs((via & ctx).float().mean().item() - 0.35 / p_any) < 0.01
    else:
        assert torch.all(w_sub[given, :30].sum(1) >= 1)


def test_subsets_that_can_give_nothing_are_refused():
    with pytest.raises(ValueError, match="p_via_points = 0 and p_context = 0 give every trajectory nothing"):
        TrainConfig(p_via_points=0.0, p_context=0.0)
    TrainConfig(p_via_points=0.0, p_context=0.0, p_empty=1.0)


# ----------------------------------------------------------------------------- the linear part's CV
def test_the_cross_validation_scores_held_out_exact_conditioning_and_picks_the_minimum():
    ds = smooth_demos(9, seed=1)
    cv = cv_basis_hyperparameters(ds, T, decoder_bases=(6, 10, 40), latent_linears=(4, 100), cov_regs=(0.0, 0.1),
                                  via_noises=(1e-3, 0.3), cov_reg_units=("normalized", "raw"), folds=3, seed=4,
                                  reach_via_points=1)
    # n_b up to n_points / 2; per n_b, k_l below n_b·d and n_b·d itself
    assert {(r[0], r[1]) for r in cv["table"]} == {(6, 4), (6, 18), (10, 4), (10, 30)}
    assert len(cv["table"]) == 4 * 2 * 2 * 2 and cv["folds"] == 3 and cv["n_demos"] == 9
    best = min(cv["table"], key=lambda r: r[5])
    assert [cv[k] for k in ("decoder_basis", "latent_linear", "basis_cov_reg", "basis_cov_reg_units", "via_noise",
                            "cv_mse")] == best[:6]
    # one entry recomputed independently: z_lin ~ N(0, I), A Aᵀ = the PPCA covariance, exact Gaussian
    # conditioning in weight space on the held-out demo's sets (start, start + end, 2 random sets)
    nb, k, c, s = 10, 30, 0.1, 1e-3
    fold_of = fold_assignment(9, 3, 4)
    sets = cv_via_sets(T, 9, 5, 2, 4)
    phi = phase_basis(X, nb, 1.0, False)
    y = np.stack([d.resampled(T) for d in ds.demos])
    errs = np.zeros((9, 4))
    for f in range(3):
        tr = np.flatnonzero(fold_of != f)
        norm = fit_normalization(DemoDataset(tuple(ds.demos[i] for i in tr), "t"), T)
        yn = (y - norm.y_mean) / norm.y_std
        mean, a, _ = pca_basis(phi, yn[tr], k, c, joint_std=np.asarray(norm.y_std))
        cov = a @ a.T
        for i in np.flatnonzero(fold_of == f):
            for j, sel in enumerate(sets[i]):
                H = np.kron(phi[sel], np.eye(3))  # rows (via, joint), weights b·d + j
                w = mean + cov @ H.T @ np.linalg.solve(H @ cov @ H.T + s * s * np.eye(H.shape[0]),
                                                       yn[i, sel].reshape(-1) - H @ mean)
                pred = (phi @ w.reshape(nb, 3)) * norm.y_std + norm.y_mean
                errs[i, j] = ((pred - y[i]) ** 2).mean()
    entry = [r for r in cv["table"] if r[:5] == [nb, k, c, "raw", s]][0]
    score, parts = cv_score(errs)
    assert entry[5] == pytest.approx(score, rel=1e-6) and entry[6:] == pytest.approx(list(parts), rel=1e-6)
    loose = [r for r in cv["table"] if r[:5] == [nb, k, c, "raw", 0.3]][0]
    assert loose[5] > entry[5]  # a noise far above the demos' spread ignores the via-points
    with pytest.raises(ValueError, match=">= 3 demonstrations, got 2"):
        cv_basis_hyperparameters(smooth_demos(2), T)
    with pytest.raises(ValueError, match="cov_reg_units"):
        cv_basis_hyperparameters(ds, T, cov_reg_units=("metres",))


def test_the_cross_validation_with_meet_scores_the_mean_moved_onto_the_via_points_by_the_smallest_change():
    ds = smooth_demos(9, seed=1)
    kw = dict(decoder_bases=(10,), latent_linears=(16,), cov_regs=(0.1,), via_noises=(1e-3, 0.3),
              cov_reg_units=("raw",), folds=3, seed=4, reach_via_points=1)
    soft = cv_basis_hyperparameters(ds, T, **kw)
    met = cv_basis_hyperparameters(ds, T, meet=True, whole_noise=1e-7, **kw)
    assert met["meet"] and not soft["meet"] and [r[:5] for r in met["table"]] == [r[:5] for r in soft["table"]]
    assert len(met["table"][0]) == 10 and len(soft["table"][0]) == 9  # the whole trajectory: a fourth conditioning
    # two entries recomputed independently in the latent (k_l = 16 < n_b·d and the whole weight space 30): the
    # posterior mean z at noise s, then z + Δ with Δ = argmin Σ_t Σ_j std_j² (Φ(x_t) (A Δ)_j)² s.t. H A (z + Δ) =
    # y_via − H b, the KKT system of that constrained least squares; every phase: the least-squares fit of z
    nb, c, s = 10, 0.1, 0.3
    fold_of, sets = fold_assignment(9, 3, 4), cv_via_sets(T, 9, 5, 2, 4)
    phi = phase_basis(X, nb, 1.0, False)
    y = np.stack([d.resampled(T) for d in ds.demos])
    for k in (16, 30):
        errs, whole, misses = np.zeros((9, 4)), np.zeros(9), []
        for f in range(3):
            tr = np.flatnonzero(fold_of != f)
            norm = fit_normalization(DemoDataset(tuple(ds.demos[i] for i in tr), "t"), T)
            std = np.asarray(norm.y_std, dtype=np.float64)
            yn = (y - norm.y_mean) / std
            mean, a, _ = pca_basis(phi, yn[tr], k, c, joint_std=std)
            m = a.T @ np.kron(phi.T @ phi, np.diag(std ** 2)) @ a  # squared trajectory change in rad, in z
            for i in np.flatnonzero(fold_of == f):
                z = np.linalg.lstsq(np.kron(phi, np.eye(3)) @ a, yn[i].reshape(-1) - np.kron(phi, np.eye(3)) @ mean,
                                    rcond=None)[0]
                whole[i] = ((((phi @ (mean + a @ z).reshape(nb, 3)) * std + norm.y_mean) - y[i]) ** 2).mean()
                for j, sel in enumerate(sets[i]):
                    J = np.kron(phi[sel], np.eye(3)) @ a
                    r = yn[i, sel].reshape(-1) - np.kron(phi[sel], np.eye(3)) @ mean
                    z = J.T @ np.linalg.solve(J @ J.T + s * s * np.eye(J.shape[0]), r)
                    kkt = np.block([[2 * m, J.T], [J, np.zeros((J.shape[0], J.shape[0]))]])
                    z = z + np.linalg.lstsq(kkt, np.concatenate([np.zeros(k), r - J @ z]), rcond=None)[0][:k]
                    misses.append(np.abs(J @ z - r).max())
                    pred = (phi @ (mean + a @ z).reshape(nb, 3)) * std + norm.y_mean
                    errs[i, j] = ((pred - y[i]) ** 2).mean()
        # the whole weight space meets every set; 16 PPCA directions do not reach every joint everywhere (then
        # the least-squares solution of the KKT system, as the cross-validation's pseudo-inverses)
        assert (max(misses) < 1e-9) == (k == 30)
        entry = [r for r in met["table"] if r[:5] == [nb, k, c, "raw", s]][0]
        score, parts = cv_score(errs, whole)
        assert len(parts) == 4 and parts[3] < parts[2]  # all points tell more than 5
        assert entry[5] == pytest.approx(score, rel=1e-6) and entry[6:] == pytest.approx(list(parts), rel=1e-6)
    # the soft posterior mean at a noise of 0.3 stays far from the via-points: meeting them changes the score
    loose = [r for r in soft["table"] if r[:5] == [nb, 30, c, "raw", s]][0]
    assert abs(loose[5] - entry[5]) > 0.1 * entry[5]


def test_the_linear_part_is_chosen_on_the_training_demos_with_a_nonlinear_block_beside_it():
    ds = smooth_demos(12, seed=2)
    cfg = TrainConfig(n_points=T, latent_nonlinear=6, seed=3, cv_folds=4)
    out, rec = select_linear_part(ds, cfg, 3)
    cv = cv_basis_hyperparameters(ds, T, folds=4, seed=3, meet=True, whole_noise=PLANNER_VIA_NOISE)  # the AUTO_* grids
    assert {k: getattr(out, k) for k in ("decoder_basis", "latent_linear", "basis_cov_reg", "basis_cov_reg_units",
                                         "via_noise")} == {k: cv[k] for k in ("decoder_basis", "latent_linear",
                                                                             "basis_cov_reg", "basis_cov_reg_units",
                                                                             "via_noise")}
    assert out.latent_dim == out.latent_linear + 6 and out.basis_init == "pca" and out.basis_lr_scale == 0.0
    assert rec["cross_validation"]["table"] == cv["table"] and rec["latent_dim"] == out.latent_dim
    assert {r[4] for r in cv["table"]} == set(CV_VIA_NOISES)
    # structure and noise chosen together, scored by the executed (met) mean: ProMP's form or the row that departs
    ref = cv["reference"]
    assert rec["cross_validation"]["meet"] and ref["best_row"] == min(cv["table"], key=lambda r: r[5])
    assert [cv[k] for k in ("decoder_basis", "latent_linear", "basis_cov_reg", "basis_cov_reg_units", "via_noise")] \
        == (ref["departure_row"] if ref["best_kept"] else ref["row"])[:5]
    few, rec = select_linear_part(smooth_demos(2), cfg, 3)
    assert "too few to cross-validate" in rec["method"] and few.latent_linear == few.decoder_basis * 3
    ModelConfig(n_joints=3, latent_dim=few.latent_dim, decoder_basis=few.decoder_basis,
                latent_linear=few.latent_linear)  # a valid architecture


# ----------------------------------------------------------------------------- the residual
def test_the_residual_is_kept_only_beyond_one_standard_error():
    off = np.array([[1.0, 2.0, 3.0, 4.0]] * 2)  # (sets, demos)
    keep, diff, se = keep_residual(off - 0.5, off)  # better on every demo by the same amount: SE 0
    assert keep and diff == pytest.approx(-0.5) and se == pytest.approx(0.0)
    noisy = off + np.array([-0.6, 0.4, -0.5, 0.5])  # mean -0.05, SE ≈ 0.29: within noise → the simpler model
    keep, diff, se = keep_residual(noisy, off)
    assert not keep and diff == pytest.approx(-0.05) and se == pytest.approx(np.std([-0.6, 0.4, -0.5, 0.5], ddof=1) / 2)
    assert not keep_residual(off + 0.1, off)[0]
    keep, _, se = keep_residual(np.array([[1.0], [2.0]]), np.array([[1.5], [2.5]]))  # one demo: SE over the sets
    assert keep and se == 0.0
    with pytest.raises(ValueError, match="equal"):
        keep_residual(off[:, :3], off)


def test_the_energy_score_is_the_sample_estimate_of_its_definition_and_rewards_the_modes():
    rng = np.random.default_rng(0)
    s, y = rng.standard_normal((6, 4, 2)), rng.standard_normal((4, 2))
    flat = s.reshape(6, -1)
    pairs = [np.linalg.norm(flat[i] - flat[j]) for i in range(6) for j in range(6) if i != j]
    expected = np.mean(np.linalg.norm(flat - y.reshape(-1), axis=1)) - 0.5 * np.mean(pairs)
    assert energy_score(s, y) == pytest.approx(expected, rel=1e-12)
    # one demo on the + mode of two (±1): samples of both modes score better than samples at their
    # average 0, though the average's mean is the closer one to half of such demos
    both = np.repeat([[1.0], [-1.0]], 100, 0) + 0.01 * rng.standard_normal((200, 1))
    middle = 0.01 * rng.standard_normal((200, 1))
    assert energy_score(both, np.ones(1)) == pytest.approx(0.5, abs=0.02)  # 1/2·2 − 1/2·(1/2·2)
    assert energy_score(middle, np.ones(1)) == pytest.approx(1.0, abs=0.02)
    with pytest.raises(ValueError, match=">= 2 samples"):
        energy_score(s[:1], y)


HARMONIC = 6  # phase feature sin(π·6·x): a wiggle the 8 RBFs per joint of the linear part cannot follow


def _net_with_residual(train: DemoDataset, sign: float) -> tuple[DeepProMPNet, object]:
    """A split-latent network whose linear part is the PPCA of ``train`` (exact, full weight space) and
    whose MLP outputs sign · 0.3 · sin(6πx) on joint 1 whatever z_nl (weights set by hand:
    ReLU(f) − ReLU(−f) through the two hidden layers)."""
    nb, k_l = 8, 24
    cfg = ModelConfig(n_joints=3, latent_dim=k_l + 2, hidden=4, decoder_basis=nb, latent_linear=k_l,
                      phase_harmonics=HARMONIC, residual_scale=1.0, via_noise=1e-4)
    net = DeepProMPNet(cfg)
    norm = fit_normalization(train, T)
    init_basis_pca(net, to_tensors(train, norm, T), 0.05)
    col = 2 + 1 + 2 * (HARMONIC - 1)  # input = [z_nl (2), x, sin πx, cos πx, ..., sin 6πx, cos 6πx]
    with torch.no_grad():
        for layer in net.decoder:
            if isinstance(layer, torch.nn.Linear):
                layer.weight.zero_(), layer.bias.zero_()
        net.decoder[0].weight[0, col], net.decoder[0].weight[1, col] = 1.0, -1.0
        net.decoder[2].weight[0, 0], net.decoder[2].weight[1, 1] = 1.0, 1.0
        amp = sign * 0.3 / float(norm.y_std[0])  # normalized units of joint 1
        net.decoder[4].weight[0, 0], net.decoder[4].weight[0, 1] = amp, -amp
    return net.eval(), norm


def test_a_residual_that_fits_what_the_linear_part_cannot_is_kept_a_harmful_one_dropped():
    wiggle = 0.3 * np.sin(np.pi * HARMONIC * X)
    train = smooth_demos(30, seed=5)
    val = smooth_demos(6, seed=6, extra=wiggle)  # the validation demos carry the wiggle
    cfg = TrainConfig(n_points=T, seed=0)
    net, norm = _net_with_residual(train, +1.0)
    kept, rec = judge_residual(net, norm, ("a", "b", "c"), val, cfg)
    assert rec["kept"] and kept is net and rec["relative_difference"] + rec["standard_error"] < 0
    assert rec["score"].startswith(f"energy score of {RESIDUAL_SAMPLES} samples")
    assert rec["energy_score_with"]["5 via-points"] < 0.5 * rec["energy_score_without"]["5 via-points"]
    assert rec["mse_with"]["5 via-points"] < 0.2 * rec["mse_without"]["5 via-points"]
    assert set(rec["energy_score_with"]) == set(rec["mse_with"]) == {"start", "5 via-points"}
    assert rec["n_val"] == 6 and rec["judged_on"] == "validation demos"
    net, norm = _net_with_residual(train, -1.0)  # the wrong sign: twice the error
    dropped, rec = judge_residual(net, norm, ("a", "b", "c"), val, cfg)
    assert not rec["kept"] and dropped.cfg.residual_scale == 0.0 and net.cfg.residual_scale == 1.0
    z, x = torch.randn(3, net.cfg.latent_dim), torch.as_tensor(X, dtype=torch.float32)
    torch.testing.assert_close(dropped.decode(z, x), without_residual(net).decode(z, x))
    torch.testing.assert_close(dropped.decode(z, x), net.decode_linear(z, x.expand(3, -1)))


def _net_with_two_modes(train: DemoDataset, amplitude: float) -> tuple[DeepProMPNet, object]:
    """A split-latent network (1 joint) whose linear part is the PPCA of ``train`` and whose MLP outputs
    ≈ sign(z_nl[0]) · ``amplitude`` · sin 2πx (rad): hidden units ReLU(20 z_0 ± s), ReLU(±s), s = sin 2πx,
    give ReLU(20 z_0 + s) − ReLU(20 z_0 − s) − s, which is ±s once |20 z_0| >= |s|. Every encoder gives
    mean 0 and variance 1 (head weights 0), so q(z_nl) is centred between the modes."""
    cfg = ModelConfig(n_joints=1, latent_dim=8 + 2, hidden=4, decoder_basis=8, latent_linear=8, phase_harmonics=2,
                      residual_scale=1.0, via_noise=1e-3, variance_head="exp")
    net = DeepProMPNet(cfg)
    norm = fit_normalization(train, T)
    init_basis_pca(net, to_tensors(train, norm, T), 0.05)
    col = 2 + 3  # input = [z_nl (2), x, sin πx, cos πx, sin 2πx, cos 2πx]
    with torch.no_grad():
        net.head.weight.zero_(), net.head.bias.zero_()
        for layer in net.decoder:
            if isinstance(layer, torch.nn.Linear):
                layer.weight.zero_(), layer.bias.zero_()
        first = net.decoder[0].weight
        first[0, 0], first[0, col], first[1, 0], first[1, col] = 20.0, 1.0, 20.0, -1.0
        first[2, col], first[3, col] = 1.0, -1.0
        net.decoder[2].weight.copy_(torch.eye(4))
        amp = amplitude / float(norm.y_std[0])
        net.decoder[4].weight.copy_(torch.tensor([[amp, -amp, -amp, amp]]))
    return net.eval(), norm


def test_a_residual_that_holds_two_modes_is_kept_where_the_error_of_the_mean_cannot_tell():
    rng = np.random.default_rng(3)
    train = DemoDataset(tuple(Demonstration(f"t{i}", X, 0.05 * rng.standard_normal() * np.sin(np.pi * X)[:, None],
                                            ("a",)) for i in range(20)), "near 0")
    # validation demos on the modes ±sin 2πx, both modes present (y = 0 at the start: the start point
    # cannot tell them apart)
    modes = [sign * np.sin(2 * np.pi * X) + 0.01 * np.sin(np.pi * X) for sign in [1, -1] * 4]
    val = DemoDataset(tuple(Demonstration(f"v{i}", X, y[:, None], ("a",)) for i, y in enumerate(modes)), "two modes")
    net, norm = _net_with_two_modes(train, 1.0)
    prim = DeepProMP(net, norm, ("a",))
    s = prim.sample(prim.condition(X[:1], np.zeros((1, 1))), X, 400, 0)[:, T // 4, 0]
    assert np.mean(s > 0.6) > 0.2 and np.mean(s < -0.6) > 0.2  # the network's samples hold both modes (33 candidates)
    kept, rec = judge_residual(net, norm, ("a",), val, TrainConfig(n_points=T, seed=0))
    assert rec["kept"] and kept is net
    # from the start point alone (where the MLP is 0 for every z_nl) the via-point's likelihood ties the
    # candidates and the prior picks the executed mean: the mean of q(z_nl), 0, between the modes; the mean's
    # error is the unimodal model's, while the samples of both modes score better than the unimodal model's
    latent = prim.condition(X[:1], np.zeros((1, 1)))
    assert latent.mean[8:].tolist() == latent.linear.candidates[0, 8:].tolist() == [0.0, 0.0]
    assert abs(rec["mse_with"]["start"] - rec["mse_without"]["start"]) < 1e-9 * rec["mse_without"]["start"]
    assert rec["energy_score_with"]["start"] < 0.75 * rec["energy_score_without"]["start"]


def test_the_residual_can_be_judged_by_cross_validation_of_the_whole_training():
    from deepprompt_ros.training.loop import train

    ds = smooth_demos(14, seed=8)
    cfg = TrainConfig(n_points=T, hidden=16, steps=20, val_every=20, batch_size=8, threads=1, residual_folds=2,
                      latent_nonlinear=2)
    info = {}
    net, _, _ = train(ds, cfg, log=lambda s: None, info=info)
    res = info["selection"]["residual"]
    # 13 training demos (1 validates), every one held out once by the 2 folds
    assert res["judged_on"] == "held-out demos of a 2-fold cross-validation on the training demos" and res["n_val"] == 13
    assert res["kept"] == (res["relative_difference"] + res["standard_error"] < 0 and res["via_mean_ok"])
    assert net.cfg.residual_scale == (1.0 if res["kept"] else 0.0) == info["train_config"]["residual_scale"]
    with pytest.raises(ValueError, match="residual_folds = 1: expected 0"):
        TrainConfig(residual_folds=1)


def _family(kind: str, n: int = 24, t: int = 100) -> DemoDataset:
    """2 joints: 'promp' — a ProMP of 20 RBFs per joint (full-rank Gaussian weights); 'wiggle' — sines of
    6 and 7 periods, which 20 RBFs per joint cannot follow."""
    x = np.linspace(0.0, 1.0, t)
    rng = np.random.default_rng(0)
    if kind == "promp":
        q, _ = np.linalg.qr(rng.standard_normal((40, 40)))
        root, phi = q * np.sqrt(np.geomspace(1.0, 1e-2, 40)), phase_basis(x, 20, 1.0, False)
        ys = [phi @ (root @ rng.standard_normal(40)).reshape(20, 2) for _ in range(n)]
    else:
        ys = [np.stack([a * np.sin(2 * np.pi * 7 * x), b * np.sin(2 * np.pi * 6 * x + 0.3)], 1)
              for a, b in rng.normal(1.0, 0.2, (n, 2))]
    return DemoDataset(tuple(Demonstration(f"{kind}{i}", x, y, ("a", "b")) for i, y in enumerate(ys)), kind)


def test_the_promp_form_is_left_only_on_evidence_beyond_one_standard_error():
    for kind in ("promp", "wiggle"):
        cv = cv_basis_hyperparameters(_family(kind), 100)
        ref = cv["reference"]
        assert ref["row"][:2] == [20, 40] and ref["row"][3] == "raw"  # 20 RBFs, the whole weight space, λ in rad
        assert ref["best_row"] == min(cv["table"], key=lambda r: r[5])
        assert ref["best_kept"] == (ref["departure_row"] is not None)
        chosen = ref["departure_row"] if ref["best_kept"] else ref["row"]
        assert [cv[k] for k in ("decoder_basis", "latent_linear", "basis_cov_reg", "basis_cov_reg_units",
                                "via_noise")] == chosen[:5]
        if kind == "promp":  # the data are a ProMP of that form: no evidence against it
            assert not ref["best_kept"] and cv["decoder_basis"] == 20 and cv["latent_linear"] == 40
        else:  # a finer basis follows the wiggles: far beyond one standard error
            assert ref["best_kept"] and cv["decoder_basis"] == 30 and ref["log_difference"] < -0.5
    no_ref = cv_basis_hyperparameters(_family("wiggle"), 100, reference=None)
    assert "reference" not in no_ref and no_ref["cv_mse"] == min(r[5] for r in no_ref["table"])


def test_a_departure_from_the_reference_must_not_be_worse_on_any_conditioning():
    rng = np.random.default_rng(0)
    ref = rng.normal(0.0, 1.0, (30, 4))  # per-demo log errors: start, start + end, random sets, whole trajectory
    noise = rng.normal(0.0, 0.02, (30, 4))
    better = ref - 0.3 + noise  # lower on every conditioning
    assert _departs(better, ref)
    trade = better.copy()
    trade[:, 3] = ref[:, 3] + 0.2 + noise[:, 3]  # lower overall (mean -0.175) but worse on the whole trajectory
    assert (trade - ref).mean() < -0.1 and not _departs(trade, ref)
    slight = better.copy()
    slight[:, 3] = ref[:, 3] + rng.normal(0.0, 0.05, 30)  # the whole trajectory within noise of the reference
    d = (slight - ref)[:, 3]
    assert _departs(slight, ref) == (d.mean() <= d.std(ddof=1) / np.sqrt(30))
    assert not _departs(ref + np.abs(noise), ref)  # worse overall: the reference stays
