"""The server's default Condition on a trained split-latent primitive meets a planner's via-points:
exact conditioning of the linear block with the planner's via-point noise (ServerConfig.via_noise),
conditioned again with a smaller noise when a via-point is still missed; honest reports when the block
cannot meet them; overflowing or invalid conditioning arguments refused by the model itself."""
import pathlib
import sys
import time

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from deepprompt_ros.baselines.deep_promp_model import DeepProMPModel  # noqa: E402
from deepprompt_ros.common.results import Code  # noqa: E402
from deepprompt_ros.data.builtin import gen3_lite_reach  # noqa: E402
from deepprompt_ros.primitive.deep_promp import DeepProMP  # noqa: E402
from deepprompt_ros.primitive.latent import PLANNER_CHANGE_BOUND, PLANNER_VIA_NOISE  # noqa: E402
from deepprompt_ros.primitive.linear_conditioning import smallest_change  # noqa: E402
from deepprompt_ros.robots.spec import load_robot  # noqa: E402
from deepprompt_ros.server.config import ServerConfig, robot_limits  # noqa: E402
from deepprompt_ros.server.primitives_file import PrimitiveEntry, load_primitive  # noqa: E402
from deepprompt_ros.server.requests import ConditionRequest, ContextIn, ViaPointIn  # noqa: E402
from deepprompt_ros.server.service import PrimitiveServerCore  # noqa: E402
from experiments import goal_metrics as gm  # noqa: E402

SPLIT = ROOT / "test" / "data" / "gen3_lite_reach_split.safetensors"
PLAIN = ROOT / "test" / "data" / "gen3_lite_reach_plain.safetensors"
SPEC = load_robot("gen3_lite")


def core_for(path, **cfg_values):
    cfg = ServerConfig(**cfg_values)
    loaded = load_primitive(PrimitiveEntry("reach", str(path)), SPEC.joint_names, pathlib.Path)
    return PrimitiveServerCore({"reach": loaded}, cfg, robot_limits(SPEC, cfg)), loaded.model


@pytest.fixture(scope="module")
def planner_sets():
    """Goal 5's sets: 1-5 via-points, each joint uniform in the demos' range at that phase +-20 % of its
    span, inside the joint limits, with the object of another demonstration."""
    train = gen3_lite_reach(seed=0)
    lower, upper = gm.joint_limits(train.joint_names)
    return gm.planner_via_sets(train, 40, seed=3, lower=lower, upper=upper,
                               contexts_from=gen3_lite_reach(seed=1001, n_demos=20))


def request(s):
    vps = [ViaPointIn(float(a), np.asarray(b), np.zeros(0, dtype=bool)) for a, b in zip(s["x"], s["y"])]
    ctx = [ContextIn(k, np.asarray(v, dtype=np.float64).reshape(-1)) for k, v in s["contexts"].items()]
    return ConditionRequest("reach", vps, ctx)


def measured_error(core, model, res, s):
    lat = core.handles.get(res.handle).latent
    return float(np.abs(model.mean_trajectory(lat, s["x"]) - s["y"]).max())


def test_the_default_condition_meets_the_planner_sets_that_need_no_oscillation(planner_sets):
    """Goal 5's sets on the small trained split model (a 32-D linear block): met to 1e-6 rad, except those
    whose exact solution swings the trajectory more than PLANNER_CHANGE_BOUND times the smoothed
    posterior's miss — refused with that posterior and why, the swing measured here."""
    core, model = core_for(SPLIT)
    assert model.exact_conditioning and ServerConfig().via_noise == PLANNER_VIA_NOISE
    grid = np.linspace(0.0, 1.0, 101)
    errors, refused = [], 0
    for s in planner_sets:
        res = core.condition(request(s))
        assert res.code == Code.SUCCESS, res.message
        e = measured_error(core, model, res, s)
        assert abs(e - res.refine_max_error) <= 1e-12 + 1e-6 * e  # the report is the executed mean's error
        if res.reachable:
            errors.append(e)
            continue
        refused += 1
        assert "oscillation" in res.message, res.message
        soft = model.condition(s["x"], s["y"], contexts=s["contexts"])
        miss = np.abs(model.mean_trajectory(soft, s["x"]) - s["y"]).max()
        assert e == pytest.approx(miss, rel=1e-9)
        exact = model.condition(s["x"], s["y"], contexts=s["contexts"], via_noise=PLANNER_VIA_NOISE)
        swing = np.abs(model.mean_trajectory(exact, grid) - model.mean_trajectory(soft, grid)).max()
        assert swing > PLANNER_CHANGE_BOUND * miss, (swing, miss)
    assert max(errors) <= 1e-6, max(errors)
    assert refused <= 0.15 * len(planner_sets), refused  # 5 of 40 here, their swings 0.08 to 932 rad


def test_with_the_models_own_noise_the_linear_block_is_conditioned_again_until_met(planner_sets):
    core, model = core_for(SPLIT, via_noise=0.0)  # the noise training chose (1e-4): misses by ~1e-3 rad
    first = [float(np.abs(model.mean_trajectory(model.condition(s["x"], s["y"], contexts=s["contexts"]), s["x"])
                          - s["y"]).max()) for s in planner_sets]
    assert np.mean(np.array(first) > 1e-6) > 0.9  # what the re-conditioning has to close
    iterations = []
    for s in planner_sets:
        res = core.condition(request(s))
        assert res.code == Code.SUCCESS and res.reachable, res.message
        assert measured_error(core, model, res, s) <= 1e-6
        iterations.append(res.refine_iterations)
    assert min(iterations) >= 1 and "conditioned again" in res.message


def test_more_constraints_than_the_linear_block_has_are_reported_unmet_not_hidden():
    core, model = core_for(SPLIT)
    rng = np.random.default_rng(5)
    x = np.sort(rng.choice(np.linspace(0, 1, 101), 40, replace=False))  # 240 values for a 32-D block
    y = model.mean_trajectory(model.prior(), x) + rng.normal(0, 0.05, (40, 6))
    vps = [ViaPointIn(float(a), b, np.zeros(0, dtype=bool)) for a, b in zip(x, y)]
    t0 = time.perf_counter()
    res = core.condition(ConditionRequest("reach", vps))
    assert time.perf_counter() - t0 < ServerConfig().refine_time_budget + 1.0
    assert res.code == Code.SUCCESS and not res.reachable and res.refine_max_error > 1e-3, res.message
    lat = core.handles.get(res.handle).latent
    assert abs(float(np.abs(model.mean_trajectory(lat, x) - y).max()) - res.refine_max_error) < 1e-9


@pytest.mark.parametrize("via_noise", [PLANNER_VIA_NOISE, None], ids=["planner_noise", "models_noise"])
def test_condition_planner_is_the_servers_default_path(planner_sets, via_noise):
    """The same latent, error and re-conditionings as the server's default Condition, met by the first
    conditioning (the planner's noise) or only after conditioning again (the model's own noise)."""
    core, model = core_for(SPLIT, via_noise=via_noise or 0.0)
    wrapped = DeepProMPModel()
    wrapped._set(model)
    iterations = []
    for s in planner_sets[:10]:
        planned = model.condition_planner(s["x"], s["y"], contexts=s["contexts"], via_noise=via_noise)
        res = core.condition(request(s))
        served = core.handles.get(res.handle).latent
        np.testing.assert_allclose(planned.latent.mean, served.mean, rtol=0, atol=1e-12)
        assert (planned.via_error, planned.iterations) == (res.refine_max_error, res.refine_iterations)
        assert planned.via_error == pytest.approx(measured_error(core, model, res, s), rel=1e-6, abs=1e-12)
        iterations.append(planned.iterations)
        if via_noise is not None:
            np.testing.assert_allclose(wrapped.condition(s["x"], s["y"], s["contexts"]).mean, planned.latent.mean,
                                       rtol=0, atol=0)
    assert max(iterations) == 0 if via_noise is not None else min(iterations) >= 1


def test_condition_planner_reports_a_plain_latents_error_and_takes_no_empty_via_points(planner_sets):
    """A plain latent is the aggregation as it is, its error measured at the via-points of weight > 0;
    empty via-points are none (the aggregation of the contexts); bad budgets are refused."""
    prim = DeepProMP.from_checkpoint(str(PLAIN))
    s = next(s for s in planner_sets if len(s["x"]) >= 3)
    w = np.ones(len(s["x"]))
    worst = int(np.abs(prim.mean_trajectory(prim.condition(s["x"], s["y"], contexts=s["contexts"]), s["x"])
                       - s["y"]).max(1).argmax())
    w[worst] = 0.0  # the via-point the conditioned mean misses most, removed
    planned = prim.condition_planner(s["x"], s["y"], via_weights=w, contexts=s["contexts"])
    lat = prim.condition(s["x"], s["y"], via_weights=w, contexts=s["contexts"])
    np.testing.assert_array_equal(planned.latent.mean, lat.mean)
    err = np.abs(prim.mean_trajectory(lat, s["x"]) - s["y"]).max(1)
    assert planned.iterations == 0 and planned.via_error == pytest.approx(np.delete(err, worst).max(), rel=1e-12)
    assert planned.via_error < err[worst]
    empty = prim.condition_planner(np.zeros(0), np.zeros((0, 6)), contexts=s["contexts"])
    np.testing.assert_array_equal(empty.latent.mean, prim.condition(contexts=s["contexts"]).mean)
    assert empty.via_error == 0.0
    for kw, what in (({"tol": 0.0}, "tol"), ({"max_iterations": -1}, "max_iterations"),
                     ({"time_budget": float("nan")}, "time_budget")):
        with pytest.raises(ValueError, match=f"{what} = .* expected"):
            prim.condition_planner(s["x"], s["y"], **kw)


@pytest.mark.parametrize("path", [SPLIT, PLAIN], ids=["split", "plain"])
def test_condition_refuses_overflow_and_invalid_arguments_with_what_is_expected(path):
    prim = DeepProMP.from_checkpoint(str(path))
    with pytest.raises(ValueError, match=r"NaN or inf \(an overflow\): largest \|via-point position\| 1e\+308 rad"):
        prim.condition([0.5], np.full((1, 6), 1e308))
    with pytest.raises(ValueError, match="largest \\|context value\\| 1e\\+308"):
        prim.condition([0.5], prim.mean_trajectory(prim.prior(), [0.5]), contexts={"object": np.full(3, 1e308)})
    for bad in (0.0, -1e-3, float("nan"), "1e-3", True):
        with pytest.raises(ValueError, match="via_noise .* expected a finite standard deviation > 0"):
            prim.condition([0.5], prim.mean_trajectory(prim.prior(), [0.5]), via_noise=bad)
    for bad in (-1, 2.5, None):
        with pytest.raises(ValueError, match="n_candidates .* expected an integer >= 0"):
            prim.condition([0.5], prim.mean_trajectory(prim.prior(), [0.5]), n_candidates=bad)
    ok = prim.condition([0.5], prim.mean_trajectory(prim.prior(), [0.5]) + 0.01)
    assert np.all(np.isfinite(ok.mean)) and np.all(np.isfinite(ok.var))


def test_smallest_change_meets_the_rows_with_the_least_change_of_the_trajectory():
    net = DeepProMP.from_checkpoint(str(SPLIT))._np
    h = net.linear_design(np.array([0.1, 0.45, 0.8]))[1].reshape(-1, net.k_lin)  # 18 rows, 32-D block
    r = np.random.default_rng(0).normal(0.0, 0.01, (2, h.shape[0]))
    delta, sq, after = smallest_change(net, h, r)
    np.testing.assert_allclose(after, r - delta @ h.T, rtol=0, atol=0)
    np.testing.assert_allclose(delta @ h.T, r, rtol=0, atol=1e-10)
    metric = np.linalg.inv(net.trajectory_metric_inverse())
    np.testing.assert_allclose(sq, np.einsum("ik,kl,il->i", delta, metric, delta), rtol=1e-8)
    np.testing.assert_allclose(net.metric_design(np.array([0.1, 0.45, 0.8])).reshape(-1, net.k_lin),
                               h @ net.trajectory_metric_inverse(), rtol=1e-10, atol=1e-12)
    rows = net.trajectory_rows()  # the squared change over the phases: the metric without its ridge
    assert np.all(np.sum((delta @ rows.T) ** 2, 1) <= sq)
    null = np.linalg.svd(h)[2][h.shape[0]:]  # directions that leave the rows unchanged
    others = delta[0] + np.random.default_rng(1).normal(0.0, 0.01, (20, null.shape[0])) @ null
    np.testing.assert_allclose(others @ h.T, np.broadcast_to(r[0], (20, h.shape[0])), rtol=0, atol=1e-10)
    cost = np.einsum("ik,kl,il->i", others, metric, others)
    assert np.all(cost > delta[0] @ metric @ delta[0])
    # rows that cannot all be met (the same row twice with different values): refused, not a wild change
    with np.errstate(invalid="ignore"):  # as condition() calls it
        assert smallest_change(net, np.vstack([h[:1], h[:1]]), np.array([[0.0, 0.01]])) is None


def test_the_planner_mean_smooths_noisy_via_points_then_meets_them_with_the_least_change():
    """condition(..., smooth_noise): the posterior mean at the larger noise moved onto the via-points by
    the smallest change of the trajectory; the distribution is the one at via_noise. The planner's
    default is that with the model's own noise."""
    prim = DeepProMP.from_checkpoint(str(SPLIT))
    demo = gen3_lite_reach(seed=1001, n_demos=1).demos[0]
    x = np.array([0.0, 0.2, 0.45, 0.7, 1.0])
    y = demo.resampled(101)[np.round(x * 100).astype(int)] + np.random.default_rng(2).normal(0.0, 0.02, (5, 6))
    grid = np.linspace(0.0, 1.0, 101)
    soft = prim.condition(x, y, via_noise=0.05)
    exact = prim.condition(x, y, via_noise=PLANNER_VIA_NOISE)
    smooth = prim.condition(x, y, via_noise=PLANNER_VIA_NOISE, smooth_noise=0.05)
    for lat in (exact, smooth):
        assert np.abs(prim.mean_trajectory(lat, x) - y).max() <= 1e-6
    assert np.abs(prim.mean_trajectory(soft, x) - y).max() > 1e-3  # the soft mean does not meet them
    change = [np.linalg.norm(prim.mean_trajectory(lat, grid) - prim.mean_trajectory(soft, grid))
              for lat in (smooth, exact)]
    assert change[0] < change[1] - 1e-3, change  # the exact posterior mean meets them with a larger change
    np.testing.assert_array_equal(smooth.var, exact.var)
    np.testing.assert_array_equal(smooth.linear.chol, exact.linear.chol)
    assert smooth.linear.via_error <= 1e-6
    planned = prim.condition_planner(x, y)
    np.testing.assert_allclose(planned.latent.mean, prim.condition(
        x, y, via_noise=PLANNER_VIA_NOISE, smooth_noise=prim.cfg.via_noise).mean, rtol=0, atol=0)
    np.testing.assert_allclose(prim.condition_planner(x, y, smooth=False).latent.mean, exact.mean, rtol=0, atol=0)
    with pytest.raises(ValueError, match="smooth_noise"):
        prim.condition(x, y, smooth_noise=-1.0)


def test_close_noisy_via_points_get_the_smoothed_posterior_not_an_oscillation():
    """Five via-points 0.01 apart with 2 cm of noise: met exactly only by a trajectory that oscillates
    between them. The planner gets the posterior at the model's own noise with its error and why, and
    the server says so; 0.05 apart the same points are met."""
    core, prim = core_for(SPLIT)
    demo = gen3_lite_reach(seed=1001, n_demos=1).demos[0]
    grid = np.linspace(0.0, 1.0, 101)
    for spacing, met in ((0.05, True), (0.01, False)):
        x = 0.4 + spacing * np.arange(5)
        y = demo.resampled(1001)[np.round(x * 1000).astype(int)] + np.random.default_rng(2).normal(0.0, 0.02, (5, 6))
        soft = prim.condition(x, y)  # the model's own via-point noise
        soft_miss = float(np.abs(prim.mean_trajectory(soft, x) - y).max())
        planned = prim.condition_planner(x, y)
        assert (planned.via_error <= 1e-6) is met, (spacing, planned.via_error, planned.reason)
        change = np.abs(prim.mean_trajectory(planned.latent, grid) - prim.mean_trajectory(soft, grid)).max()
        assert change <= PLANNER_CHANGE_BOUND * max(soft_miss, 1e-6)
        res = core.condition(ConditionRequest("reach", [ViaPointIn(float(a), b, np.zeros(0, dtype=bool))
                                                        for a, b in zip(x, y)]))
        assert res.code == Code.SUCCESS and res.reachable is met, res.message
        if not met:
            np.testing.assert_array_equal(planned.latent.mean, soft.mean)
            assert planned.via_error == pytest.approx(soft_miss, rel=1e-12) and soft_miss > 1e-3
            assert "oscillation" in planned.reason and "not met" in res.message and "oscillation" in res.message
            # the exact posterior mean alone would meet them less well or move the trajectory far more
            exact = prim.condition(x, y, via_noise=PLANNER_VIA_NOISE)
            assert np.abs(prim.mean_trajectory(exact, grid) - prim.mean_trajectory(soft, grid)).max() > \
                PLANNER_CHANGE_BOUND * soft_miss or exact.linear.via_error > 1e-6


def test_a_partial_via_point_is_smoothed_and_met_on_its_constrained_joints():
    """The smoothed mean with a joint mask (and a via-point of weight 0) meets exactly the joints it
    constrains; the free joints and the weightless via-point are not pulled onto their values."""
    prim = DeepProMP.from_checkpoint(str(SPLIT))
    demo = gen3_lite_reach(seed=1001, n_demos=1).demos[0]
    x = np.array([0.0, 0.3, 0.6, 0.9])
    y = demo.resampled(101)[np.round(x * 100).astype(int)] + np.random.default_rng(4).normal(0.0, 0.02, (4, 6))
    mask = np.ones((4, 6), dtype=bool)
    mask[1, 3:] = False
    weights = np.array([1.0, 1.0, 1.0, 0.0])
    lat = prim.condition(x, y, via_weights=weights, via_mask=mask, via_noise=PLANNER_VIA_NOISE, smooth_noise=0.05)
    err = np.abs(prim.mean_trajectory(lat, x) - y)
    assert err[:3][mask[:3]].max() <= 1e-6 and lat.linear.via_error <= 1e-6
    assert err[1][~mask[1]].max() > 1e-3 and err[3].max() > 1e-3
    planned = prim.condition_planner(x, y, via_weights=weights, via_mask=mask)
    assert planned.via_error <= 1e-6, planned.reason
