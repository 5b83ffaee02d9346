"""The paper's baselines (CNMP, VAE-CNMP, their Indep variants) and the DeepProMP / ProMP adapters
behind one interface, and the reconstruction metric (paper Sec. IV). Seeded; tiny trainings."""
import os
import pickle

import numpy as np
import pytest
import torch

from deepprompt_ros.baselines.concat import CNMP, VAECNMP, CNMPIndep, VAECNMPIndep, _kinds
from deepprompt_ros.baselines.interface import InputSpec, MovementPrimitiveModel
from deepprompt_ros.baselines.promp_model import ProMPModel
from deepprompt_ros.baselines.registry import MODEL_CLASSES, load_model
from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.data.demonstration import Demonstration
from deepprompt_ros.evaluation.reconstruction import available_conditionings, reconstruction_mse, reconstruction_table
from deepprompt_ros.training.config import TrainConfig
from deepprompt_ros.training.tensors import fit_normalization, to_tensors

torch.set_num_threads(1)

N_POINTS = 30
X = np.linspace(0.0, 1.0, N_POINTS)
IMAGE = (8, 8)


def goal_image(c, rng) -> np.ndarray:
    """2 RGB images whose red / green levels encode the 2-D goal c ∈ [-1, 1]² (plus noise)."""
    im = rng.integers(0, 30, (2, *IMAGE, 3))
    im[..., 0] += int(110 + 100 * c[0])
    im[..., 1] += int(110 + 100 * c[1])
    return np.clip(im, 0, 255).astype(np.uint8)


def linear_family(n: int, seed: int) -> DemoDataset:
    """2 joints driven linearly by a 2-D goal c ~ U[-1, 1]²:
    q1 = c1 sin(πx) + c2 x / 2,  q2 = c1 x / 2 + c2 sin(πx)  (+ 0.01 rad noise);
    context 'goal' = c and two 8×8 images encoding c."""
    rng = np.random.default_rng(seed)
    demos = []
    for i in range(n):
        c = rng.uniform(-1, 1, 2)
        q = np.stack([c[0] * np.sin(np.pi * X) + 0.5 * c[1] * X, 0.5 * c[0] * X + c[1] * np.sin(np.pi * X)], 1)
        q = q + 0.01 * rng.standard_normal(q.shape)
        demos.append(Demonstration(f"lin_{i:03d}", X * 2.0, q, ("j1", "j2"), {"goal": c[None]}, goal_image(c, rng)))
    return DemoDataset(tuple(demos), f"linear_family(seed={seed})")


FULL = linear_family(80, seed=1)
TRAIN_VAL, TEST = FULL.split(20, seed=0)
TRAIN, VAL = TRAIN_VAL.split(10, seed=0)
CFG = TrainConfig(latent_dim=8, hidden=64, steps=300, val_every=100, n_points=N_POINTS, threads=1,
                  kl_anneal_steps=100, max_via_points=10, seed=0)

_FITTED: dict = {}


def fitted(cls) -> MovementPrimitiveModel:
    """Each model class trained once per test session (300 updates; ProMP is closed form)."""
    if cls not in _FITTED:
        _FITTED[cls] = cls().fit(TRAIN, CFG, VAL)
    return _FITTED[cls]


@pytest.fixture(params=MODEL_CLASSES, ids=[c.kind for c in MODEL_CLASSES])
def model(request):
    return fitted(request.param)


def _mse(model, **cond) -> float:
    """Mean-trajectory MSE over the test demos; cond(demo) builds the conditioning of each."""
    errs = []
    for d in TEST.demos:
        y = d.resampled(N_POINTS)
        kw = {k: f(d, y) for k, f in cond.items()}
        errs.append(((model.mean_trajectory(model.condition(**kw), X) - y) ** 2).mean())
    return float(np.mean(errs))


def _all_contexts(model):
    """What 'all contexts' means for a model: low-dim + images, or low-dim only (ProMP)."""
    cond = {"contexts": lambda d, y: d.contexts}
    if model.supports_images:
        cond["images"] = lambda d, y: d.images
    return cond


FIRST = {"via_x": lambda d, y: X[:1], "via_y": lambda d, y: y[:1]}
ALL_VIA = {"via_x": lambda d, y: X, "via_y": lambda d, y: y}


# ------------------------------------------------------------------ one test body, every model
def test_via_points_reduce_reconstruction_error(model):
    unconditioned = _mse(model)
    if model.independent_inputs:
        # via-points alone (the paper's "Via Point" metric: the full trajectory as via-points)
        err = reconstruction_mse(model, TEST, "via_point", n_points=N_POINTS)
    else:
        # CNMP / VAE-CNMP always get via-points AND every context (their training distribution)
        err = _mse(model, **ALL_VIA, **_all_contexts(model))
    assert err < 0.5 * unconditioned, (err, unconditioned)


def test_context_conditioning_predicts_the_goal(model):
    unconditioned = _mse(model)
    richest = available_conditionings(model, TEST)[-1]
    assert richest == ("low_dim" if model.kind == "promp" else "image+low")
    err = reconstruction_mse(model, TEST, richest, n_points=N_POINTS)
    assert err < 0.5 * unconditioned, (err, unconditioned)
    # q1(0.5) = c1 + c2/4: the goal's first coordinate moves the first joint at mid-phase
    rng = np.random.default_rng(5)
    mids = []
    for c1 in (-0.8, 0.8):
        c = np.array([c1, 0.0])
        kw = {"via_x": [0.0], "via_y": [[0.0, 0.0]], "contexts": {"goal": c}}
        if model.supports_images:
            kw["images"] = goal_image(c, rng)
        mids.append(model.mean_trajectory(model.condition(**kw), [0.5])[0, 0])
    assert mids[0] < 0 < mids[1] and mids[1] - mids[0] > 0.4, mids  # true: −0.8, +0.8 rad


def test_save_load_round_trip_gives_identical_predictions(model, tmp_path):
    path = model.save(tmp_path / f"{model.kind}.safetensors")
    assert path.read_bytes()[8:9] == b"{"  # a safetensors JSON header, not a pickle
    for loaded in (type(model).load(path), load_model(path)):
        assert type(loaded) is type(model)
        assert loaded.joint_names == model.joint_names and loaded.context_dims == model.context_dims
        d = TEST.demos[0]
        y = d.resampled(N_POINTS)
        conds = [{}, {"via_x": X[::7], "via_y": y[::7]}, {"via_x": X[:1], "via_y": y[:1], "contexts": d.contexts}]
        if model.supports_images:
            conds.append({"images": d.images, "contexts": d.contexts})
        for kw in conds:
            a, b = model.condition(**kw), loaded.condition(**kw)
            np.testing.assert_array_equal(loaded.mean_trajectory(b, X), model.mean_trajectory(a, X))
            np.testing.assert_array_equal(loaded.sample(b, X, 3, rng=7), model.sample(a, X, 3, rng=7))
    other = VAECNMP if model.kind != "vae_cnmp" else CNMP
    with pytest.raises(ValueError, match="model file|format"):
        other.load(path)


def test_samples_have_the_documented_shape_and_follow_the_conditioning(model):
    d = TEST.demos[3]
    y = d.resampled(N_POINTS)
    cond = model.condition(X, y, contexts=d.contexts)
    s = model.sample(cond, X, 64, rng=1)
    assert s.shape == (64, N_POINTS, 2) and np.isfinite(s).all()
    np.testing.assert_array_equal(s, model.sample(cond, X, 64, rng=1))  # seeded
    assert not np.array_equal(s, model.sample(cond, X, 64, rng=2))  # stochastic
    mean = model.mean_trajectory(cond, X)
    assert mean.shape == (N_POINTS, 2)
    # the samples scatter around the mean trajectory: within 4 standard errors (CNMP: independent
    # per-point noise) plus the decoder's curvature over a narrow conditioned latent (≤ 0.05 rad)
    tol = 0.05 + 4 * s.std(0) / np.sqrt(len(s))
    assert (np.abs(s.mean(0) - mean) < tol).all(), np.abs(s.mean(0) - mean).max()


BAD_INPUTS = [
    (dict(via_x=[0.5]), "need both phases via_x"),
    (dict(via_x=[0.2, 0.5], via_y=[[0.1, 0.2, 0.3]] * 2), "have 3 joint values; model '.*' has 2 joints: j1, j2"),
    (dict(via_x=[1.5], via_y=[[0.0, 0.0]]), "outside \\[0, 1\\]"),
    (dict(via_x=[[0.5]], via_y=[[0.0, 0.0]]), "1-D array of phases"),
    (dict(via_x=[0.2, 0.5], via_y=[[0.0, 0.0]]), "1 via-point position rows for 2 phases"),
    (dict(via_x=[0.5], via_y=[[np.nan, 0.0]]), "joint 'j1' is NaN"),
    (dict(contexts={"target": [1.0, 2.0]}), "takes no context 'target'; it accepts \\['goal'\\]"),
    (dict(contexts={"goal": [1.0, 2.0, 3.0]}), "context 'goal' must have 2 values per vector"),
    (dict(contexts={"goal": [np.inf, 0.0]}), "context 'goal' contains NaN or inf"),
    (dict(contexts=[1.0, 2.0]), "contexts must be a mapping"),
]


def test_malformed_inputs_raise_value_error_saying_what_is_expected(model):
    for kw, message in BAD_INPUTS:
        with pytest.raises(ValueError, match=message):
            model.condition(**kw)
    bad_images = np.zeros((2, 5, 5, 3), np.uint8)
    with pytest.raises(ValueError, match="uint8 RGB with shape \\(n, 8, 8, 3\\)" if model.supports_images
                       else "ProMP takes no images"):
        model.condition(images=bad_images)
    cond = model.condition()
    with pytest.raises(ValueError, match="outside \\[0, 1\\]"):
        model.mean_trajectory(cond, [0.0, 1.2])
    with pytest.raises(ValueError, match="must be an integer >= 1"):
        model.sample(cond, X, 0)
    with pytest.raises(ValueError, match="conditioned object returned by this"):
        model.mean_trajectory("not a conditioning", X)
    with pytest.raises(ValueError, match="not trained"):
        type(model)().condition()


# ------------------------------------------------------------------ what is specific to the baselines
def test_zero_padding_training_is_what_makes_via_point_only_conditioning_work():
    """Paper Sec. IV: "the zero padding training is crucial for improving baselines' ability to do
    via-point conditioning". Trained on every update with all inputs, the plain models see a
    zero-padded context at evaluation for the first time."""
    for plain, indep in ((CNMP, CNMPIndep), (VAECNMP, VAECNMPIndep)):
        e_plain = reconstruction_mse(fitted(plain), TEST, "via_point", n_points=N_POINTS)
        e_indep = reconstruction_mse(fitted(indep), TEST, "via_point", n_points=N_POINTS)
        assert e_indep < 0.6 * e_plain, (plain.kind, e_indep, e_plain)


def test_missing_inputs_are_zero_padded_in_the_concatenated_element():
    m = fitted(CNMPIndep)
    net, norm = m.net, m.norm
    d = TEST.demos[0]
    y = d.resampled(N_POINTS)
    c_norm = (d.contexts["goal"][0] - norm.ctx_mean["goal"]) / norm.ctx_std["goal"]
    emb = net.image_encoder(torch.from_numpy(d.images).permute(0, 3, 1, 2).float()[None] / 255.0, torch.ones(1, 2))

    def r_of(elements):
        with torch.no_grad():
            e = torch.tensor(np.asarray(elements), dtype=torch.float32)[None]
            return net.encode(e, torch.ones(1, e.shape[1]))[0][0].double().numpy()

    zeros_via, zeros_img = np.zeros(1 + 2), np.zeros(net.cfg.hidden)
    img = emb[0].detach().numpy()
    # contexts only: ONE element [0, c, 0]
    np.testing.assert_allclose(m.condition(contexts=d.contexts).r, r_of([np.r_[zeros_via, c_norm, zeros_img]]),
                               atol=1e-6)
    # images only: [0, 0, emb]
    np.testing.assert_allclose(m.condition(images=d.images).r, r_of([np.r_[zeros_via, 0.0, 0.0, img]]), atol=1e-6)
    # 3 via-points, no context: mean of [x_i, y_i, 0, 0]
    sel = [0, 10, 20]
    yn = (y[sel] - norm.y_mean) / norm.y_std
    elems = [np.r_[X[i], yn[j], 0.0, 0.0, zeros_img] for j, i in enumerate(sel)]
    np.testing.assert_allclose(m.condition(X[sel], y[sel]).r, r_of(elems), atol=1e-6)
    # nothing at all: the all-zero element
    np.testing.assert_allclose(m.condition().r, r_of([np.zeros(net.cfg.input_dim)]), atol=1e-6)


def test_input_subsampling_plain_always_all_inputs_indep_all_combinations():
    norm = fit_normalization(TRAIN, N_POINTS)
    data = to_tensors(TRAIN, norm, N_POINTS)
    kinds = _kinds(data)
    assert [k for k, _ in kinds] == ["via", "goal", "image"]
    idx = torch.arange(len(TRAIN)).repeat(40)  # 2000 draws
    w_plain = CNMP().input_weights(CFG, data, idx, kinds, torch.Generator().manual_seed(0))
    n_via = w_plain[:, :N_POINTS].sum(1)
    assert n_via.min() >= 1 and n_via.max() <= CFG.max_via_points
    assert (w_plain[:, N_POINTS:] == 1).all()  # the goal and the images, every time
    w = CNMPIndep().input_weights(CFG, data, idx, kinds, torch.Generator().manual_seed(0))
    via, goal, image = (w[:, :N_POINTS].sum(1) > 0), w[:, N_POINTS] > 0, w[:, N_POINTS + 1] > 0
    assert w[:, :N_POINTS].sum(1).max() <= CFG.max_via_points
    combos = {(a, b, c): float(((via == a) & (goal == b) & (image == c)).float().mean())
              for a in (False, True) for b in (False, True) for c in (False, True)}
    assert all(f > 0.02 for f in combos.values()), combos  # every combination of inputs occurs
    # nothing at all: p_empty = 0.1 (the other draws are repeated until something is given); 2000 draws: SE 0.007
    assert abs(combos[(False, False, False)] - 0.1) < 0.025


def test_fit_keeps_the_best_validation_weights():
    for cls in (CNMP, VAECNMPIndep):
        m = fitted(cls)
        vals = [h["val"]["mean"] for h in m.history]
        assert [h["step"] for h in m.history] == [100, 200, 300]
        val = to_tensors(VAL, m.norm, N_POINTS)
        assert m.validation_mse(CFG, val)["mean"] == pytest.approx(min(vals), rel=1e-5)
        assert m.metadata["metrics"]["best_val_mse_rad2"] == min(vals)


def test_cnmp_predicts_its_output_std_and_samples_it():
    m = fitted(CNMPIndep)
    cond = m.condition(contexts=TEST.demos[0].contexts)
    std = m.std_trajectory(cond, X)
    assert std.shape == (N_POINTS, 2) and (std >= m.std_floor * m.norm.y_std - 1e-9).all()
    s = m.sample(cond, X, 4000, rng=0)
    np.testing.assert_allclose(s.std(0), std, rtol=0.1)
    np.testing.assert_allclose(s.mean(0), m.mean_trajectory(cond, X), atol=4 * std.max() / np.sqrt(4000))


def test_promp_adapter_needs_all_context_modalities_and_no_images():
    m = fitted(ProMPModel)
    assert available_conditionings(m, TEST) == ("via_point", "low_dim")
    with pytest.raises(ValueError, match="not available for model 'promp'"):
        reconstruction_mse(m, TEST, "image")


# ------------------------------------------------------------------ the metric's definition
class _Recorder(MovementPrimitiveModel):
    """Predicts zeros and records what it was conditioned on."""

    kind = "recorder"

    def __init__(self, spec):
        super().__init__()
        self.spec, self.calls = spec, []

    def fit(self, train_ds, config, val_ds=None):
        return self

    def condition(self, via_x=None, via_y=None, contexts=None, images=None):
        self.calls.append(self.check_inputs(via_x, via_y, contexts, images))
        return None

    def mean_trajectory(self, cond, x):
        return np.zeros((len(x), 2))

    def sample(self, cond, x, n, rng=None):
        return np.zeros((n, len(x), 2))

    def save(self, path):
        raise NotImplementedError

    @classmethod
    def load(cls, path):
        raise NotImplementedError


def test_reconstruction_mse_follows_the_papers_definition():
    test = DemoDataset(TEST.demos[:3], "tiny")
    rec = _Recorder(InputSpec.from_dataset("recorder", test))
    truth = np.mean([(d.resampled(N_POINTS) ** 2).mean() for d in test.demos])  # zeros predicted
    # "Via Point": the full trajectory as via-points, no context
    assert reconstruction_mse(rec, test, "via_point", n_points=N_POINTS) == pytest.approx(truth, rel=1e-12)
    for call, d in zip(rec.calls, test.demos):
        np.testing.assert_array_equal(call.via_x, X)
        np.testing.assert_array_equal(call.via_y, d.resampled(N_POINTS))
        assert call.contexts == {} and call.images is None
    # n_via = k: a fixed seeded set of k distinct points per demo, the same for every call (model)
    sets = []
    for _ in range(2):
        rec.calls.clear()
        reconstruction_mse(rec, test, "via_point", n_via=5, n_points=N_POINTS, seed=3)
        sets.append([c.via_x for c in rec.calls])
    for a, b in zip(*sets):
        np.testing.assert_array_equal(a, b)
        assert a.shape == (5,) and np.all(np.diff(a) > 0)
    assert not np.array_equal(sets[0][0], sets[0][1])
    # every context conditioning includes the initial robot position
    expect = {"image": (False, True), "low_dim": (True, False), "image+low": (True, True)}
    for name, (low, img) in expect.items():
        rec.calls.clear()
        assert reconstruction_mse(rec, test, name, n_points=N_POINTS) == pytest.approx(truth, rel=1e-12)
        for call, d in zip(rec.calls, test.demos):
            np.testing.assert_array_equal(call.via_x, [0.0])
            np.testing.assert_array_equal(call.via_y, d.resampled(N_POINTS)[:1])
            assert (call.contexts == {"goal": d.contexts["goal"]}) if low else call.contexts == {}
            assert (call.images is d.images) if img else call.images is None
    rec.calls.clear()
    assert reconstruction_mse(rec, test, "aggregate", n_points=N_POINTS) == pytest.approx(truth, rel=1e-12)
    assert len(rec.calls) == 4 * len(test)
    with pytest.raises(ValueError, match="unknown; expected one of"):
        reconstruction_mse(rec, test, "velocity")
    with pytest.raises(ValueError, match="n_via must be None"):
        reconstruction_mse(rec, test, "via_point", n_via=0)


def test_reconstruction_table_on_a_tiny_case():
    m = fitted(ProMPModel)
    table = reconstruction_table(m, TEST, n_points=N_POINTS)
    assert set(table) == {"via_point", "low_dim", "aggregate"}
    # the data are linear in the goal and smooth: closed-form conditioning reconstructs them to
    # about the noise level (0.01² rad²) from the full trajectory, and nearly so from the goal alone
    assert table["via_point"] < 2e-4 and table["low_dim"] < 5e-4
    assert table["aggregate"] == pytest.approx((table["via_point"] + table["low_dim"]) / 2)


class _Evil:
    def __reduce__(self):
        return (os.system, (f"touch {_Evil.marker}",))


def test_pickle_files_are_refused_and_never_executed(tmp_path):
    _Evil.marker = tmp_path / "pwned"
    evil = tmp_path / "evil.safetensors"
    with open(evil, "wb") as f:
        pickle.dump({"state_dict": _Evil()}, f)
    for load in (load_model, CNMP.load, ProMPModel.load):
        with pytest.raises(ValueError, match="not a safetensors file"):
            load(evil)
    with pytest.raises(ValueError, match="does not exist"):
        load_model(tmp_path / "missing.safetensors")
    assert not _Evil.marker.exists()
