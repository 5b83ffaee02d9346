"""The goals' measures (experiments/goal_metrics.py) on small models, without the experiment harness:
the ablation is what the trained parts start from, planner via-points lie where the protocol says,
the server path's error is the one the server reports, the mode and sample figures count what they
claim. The tables themselves are checked on the harness's tiny run (test_experiments.py)."""
import pathlib
import sys

import numpy as np
import pytest
import torch

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from deepprompt_ros.baselines.deep_promp_model import DeepProMPModel  # noqa: E402
from deepprompt_ros.baselines.promp_model import ProMPModel  # noqa: E402
from deepprompt_ros.model.network import DeepProMPNet  # noqa: E402
from deepprompt_ros.training.config import TrainConfig  # noqa: E402
from experiments import common, goal_metrics as gm  # noqa: E402

torch.set_num_threads(1)
TINY = common.SCALES["tiny"]


@pytest.fixture(scope="module")
def reach():
    return common.load_task("gen3_lite_reach", TINY, sizes=(24, 4, 6))


def _fit(data, **kw):
    cfg = TrainConfig(auto_select=False, steps=20, val_every=10, threads=1, latent_dim=12, hidden=32, **kw)
    return DeepProMPModel().fit(data.train, cfg, data.val)


def test_ablation_of_a_linear_part_decoder_is_the_linear_part_without_encoders(reach):
    model = _fit(reach, decoder_basis=5, latent_linear=8, basis_init="pca", basis_lr_scale=0.0, residual_scale=1.0)
    abl = gm.AblatedDeepProMP(model)
    assert abl.primitive.cfg.residual_scale == 0.0 and model.primitive.cfg.residual_scale == 1.0
    x = np.linspace(0, 1, 50)
    d0, d1 = reach.test.demos[:2]
    y = d0.resampled(50)
    # contexts are not read: two different objects give the same conditioned trajectory ...
    a = abl.mean_trajectory(abl.condition(x[:1], y[:1], contexts=d0.contexts), x)
    b = abl.mean_trajectory(abl.condition(x[:1], y[:1], contexts=d1.contexts), x)
    np.testing.assert_array_equal(a, b)
    # ... while the trained model's encoders move it
    m0 = model.mean_trajectory(model.condition(x[:1], y[:1], contexts=d0.contexts), x)
    m1 = model.mean_trajectory(model.condition(x[:1], y[:1], contexts=d1.contexts), x)
    assert np.abs(m0 - m1).max() > 1e-6
    # the decoder is the linear part alone: the executed mean is Φ(x)(b + A z), affine in z
    z0, z1 = np.zeros(12), np.random.default_rng(0).standard_normal(12)
    prim = abl.primitive
    np.testing.assert_allclose(prim.decode(0.5 * (z0 + z1), x), 0.5 * (prim.decode(z0, x) + prim.decode(z1, x)),
                               atol=1e-10)
    assert "linear part alone" in gm.model_label(abl)


def test_ablation_of_a_plain_decoder_is_the_network_at_its_initial_weights(reach):
    model = _fit(reach)
    abl = gm.AblatedDeepProMP(model)
    torch.manual_seed(0)  # the training's seed
    fresh = DeepProMPNet(model.primitive.cfg)
    for (k, v), (k2, w) in zip(abl.primitive.net.state_dict().items(), fresh.state_dict().items()):
        assert k == k2 and torch.equal(v, w), k
    trained = model.primitive.net.state_dict()
    assert any(not torch.equal(v, trained[k]) for k, v in fresh.state_dict().items())
    assert "untrained" in gm.model_label(abl)


def test_planner_via_sets_lie_in_the_widened_range_and_the_limits(reach):
    lower, upper = gm.joint_limits(reach.train.joint_names)
    assert lower is not None and lower.shape == (6,)
    sets = gm.planner_via_sets(reach.train, 40, 3, lower, upper, contexts_from=reach.test)
    Y = np.stack([d.resampled(101) for d in reach.train.demos])
    lo, hi = Y.min(0), Y.max(0)
    grid = np.linspace(0, 1, 101)
    counts = set()
    for s in sets:
        idx = np.rint(s["x"] * 100).astype(int)
        np.testing.assert_allclose(grid[idx], s["x"])  # on the grid
        assert np.all(np.diff(idx) > 0)  # distinct phases, sorted
        counts.add(len(idx))
        span = hi[idx] - lo[idx]
        assert np.all(s["y"] >= np.maximum(lo[idx] - 0.2 * span, lower) - 1e-12)
        assert np.all(s["y"] <= np.minimum(hi[idx] + 0.2 * span, upper) + 1e-12)
        assert any(np.array_equal(s["contexts"]["object"], d.contexts["object"]) for d in reach.test.demos)
    assert counts == {1, 2, 3, 4, 5}
    # limits that cut inside the range clip every value to them
    tight_lo, tight_hi = lo.mean(0), lo.mean(0) + 1e-3
    for s in gm.planner_via_sets(reach.train, 10, 4, tight_lo, np.maximum(tight_hi, hi.max(0))):
        assert np.all(s["y"] >= tight_lo - 1e-12)
    with pytest.raises(ValueError, match="outside the joint limits"):
        gm.planner_via_sets(reach.train, 1, 0, hi.max(0) + 1.0, hi.max(0) + 2.0)


def test_server_path_reports_the_error_the_stored_handle_has(reach):
    sets = gm.planner_via_sets(reach.train, 4, 1, *gm.joint_limits(reach.train.joint_names), contexts_from=reach.test)
    r = gm.server_via_met(ROOT / "models" / "gen3_lite_reach.safetensors", "gen3_lite", sets)
    assert r["n"] == 4 and not r["refused"]
    assert r["reported_agree"]  # the error measured on the stored handle is the server's refine_max_error
    assert r["share"] == np.mean(np.asarray(r["errors"]) <= gm.MET_TOL)
    assert r["refine"] == gm.server_default_refine()


def test_modes_and_samples_count_what_they_claim():
    bim = common.load_task("bimodal_sine", TINY, sizes=(40, 4, 6))
    promp = ProMPModel(log=lambda s: None).fit(bim.train, TrainConfig(n_points=101), bim.val)
    m = gm.mode_shares(promp, n_samples=100, n_held=4)
    amb = m["ambiguous"]
    assert amb["on_mode"] == pytest.approx(amb["on_pos"] + amb["on_neg"])
    assert all(round(v * 100) == pytest.approx(v * 100) for v in (amb["on_pos"], amb["on_neg"]))  # k of 100
    assert amb["both"] == (min(amb["on_pos"], amb["on_neg"]) >= gm.BOTH_MODES_MIN)
    assert m["12 via-points"] >= 0.9  # 12 points of a demonstration pick its mode
    # exact Gaussian conditioning: samples at a via-point scatter by at most the stated noise
    reach = common.load_task("gen3_lite_reach", TINY, sizes=(24, 4, 6))
    promp = ProMPModel(log=lambda s: None).fit(reach.train, TrainConfig(), reach.val)
    st = gm.sample_stats(promp, reach.test, n_vias=(1, 200), n_samples=200)
    assert set(st) == {"1", "100"}  # N is at most the grid's points
    one = st["1"]
    assert one["noise"] == pytest.approx(promp.via_noise * np.sqrt(np.mean(np.asarray(promp.norm.y_std) ** 2)))
    assert one["spread"] <= 1.1 * one["noise"] and one["mean_error"] < one["spread"]
    # the mean of 200 samples is within a few standard errors (spread / √200) of the conditioned mean
    assert one["sample_mean_error"] <= one["mean_error"] + 4 * one["spread"] / np.sqrt(200)


def test_subset_conditionings_use_the_start_and_the_end(reach):
    promp = ProMPModel(log=lambda s: None).fit(reach.train, TrainConfig(), reach.val)
    start, both = gm.subset_mse(promp, reach.test, "start"), gm.subset_mse(promp, reach.test, "start_end")
    assert both < start  # the end point of a reach says where it goes
    with pytest.raises(ValueError, match="subset"):
        gm.subset_mse(promp, reach.test, "middle")
    # the start-only figure is reconstruction_mse's via-point rule with the first point alone
    x = np.linspace(0, 1, 100)
    errs = [((promp.mean_trajectory(promp.condition(x[:1], d.resampled(100)[:1]), x) - d.resampled(100)) ** 2).mean()
            for d in reach.test.demos]
    assert start == pytest.approx(np.mean(errs), rel=1e-12)
