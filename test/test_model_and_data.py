"""Core without a trained model: the aggregator, phase features, operation errors, the dataset format,
the checkpoint round trip (every checkpoint refusal: test_checkpoint_refusals.py)."""
import pathlib

import numpy as np
import pytest
import torch

from deepprompt_ros.data.demo_dataset import DemoDataset, load_dataset
from deepprompt_ros.data.demonstration import DatasetError, demo_from_arrays
from deepprompt_ros.data.io import load_csv, load_demo, save_demo
from deepprompt_ros.data.synthetic import bimodal_sine
from deepprompt_ros.model.checkpoint import Normalization, load_checkpoint, save_checkpoint
from deepprompt_ros.model.aggregation import bayesian_aggregate
from deepprompt_ros.model.network import DeepProMPNet, ModelConfig
from deepprompt_ros.model.phase import phase_features
from deepprompt_ros.primitive.deep_promp import DeepProMP

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _net(seed=0, **kw):
    torch.manual_seed(seed)
    cfg = ModelConfig(n_joints=2, latent_dim=4, hidden=16, context_dims=(("obj", 3),), **kw)
    net = DeepProMPNet(cfg)
    norm = Normalization(np.zeros(2), np.ones(2), {"obj": np.zeros(3)}, {"obj": np.ones(3)})
    return net, norm


def test_aggregator_equals_sequential_bayes_closed_form():
    rng = np.random.default_rng(0)
    mu = rng.normal(size=(5, 3))
    var = rng.uniform(0.1, 2.0, size=(5, 3))
    w = rng.uniform(0.0, 2.0, size=5)
    # Sequential Bayesian updates p_{i+1}(z) ∝ N(z | μ_i, σ²_i / ω_i) p_i(z), starting at N(0, I).
    m, v = np.zeros(3), np.ones(3)
    for i in range(5):
        vi = var[i] / w[i]
        m, v = (m / v + mu[i] / vi) / (1 / v + 1 / vi), 1 / (1 / v + 1 / vi)
    got = DeepProMP.aggregate(mu, var, w)
    np.testing.assert_allclose(got.mean, m, rtol=1e-12)
    np.testing.assert_allclose(got.var, v, rtol=1e-12)
    tm, tv = bayesian_aggregate(torch.tensor(mu)[None], torch.tensor(var)[None], torch.tensor(w)[None])
    np.testing.assert_allclose(tm[0].numpy(), m, rtol=1e-12)
    np.testing.assert_allclose(tv[0].numpy(), v, rtol=1e-12)


def test_zero_weight_removes_element_exactly_and_weight_pulls():
    net, norm = _net()
    p = DeepProMP(net, norm, ["a", "b"])
    x = np.array([0.1, 0.5, 0.9])
    y = np.array([[0.2, -0.1], [1.0, 0.5], [0.3, 0.3]])
    full = p.condition(x, y, via_weights=[1.0, 0.0, 1.0])
    drop = p.condition(x[[0, 2]], y[[0, 2]])
    # equal to rounding: the sums over three elements and over two are ordered differently by some BLAS
    # kernels (1 ulp under OpenBLAS's Prescott kernel); the element kept at weight 1 moves the mean by 0.019
    np.testing.assert_allclose(full.mean, drop.mean, rtol=1e-15, atol=1e-17)
    np.testing.assert_allclose(full.var, drop.var, rtol=1e-15, atol=1e-17)
    mu_i, _ = p.encode_via_points(x[1:2], y[1:2])
    dists = [np.linalg.norm(p.condition(x, y, via_weights=[1, w, 1]).mean - mu_i[0]) for w in (0.5, 1, 4, 16)]
    assert all(a > b for a, b in zip(dists, dists[1:])), dists
    ctx0 = p.condition(x, y, contexts={"obj": [1, 2, 3]}, context_weights={"obj": [0.0]})
    np.testing.assert_array_equal(ctx0.mean, p.condition(x, y).mean)


def test_variance_shrinks_with_each_added_via_point():
    net, norm = _net(1)
    p = DeepProMP(net, norm, ["a", "b"])
    rng = np.random.default_rng(1)
    x, y = rng.uniform(0, 1, 8), rng.normal(size=(8, 2))
    vars_ = [p.condition(x[:n], y[:n]).var for n in range(0, 9)]
    for a, b in zip(vars_, vars_[1:]):
        assert np.all(b < a)


def test_rhythmic_phase_features_are_periodic():
    x = np.array([0.0, 1.0, 0.25])
    f = phase_features(x, "rhythmic", 2)
    np.testing.assert_allclose(f[0], f[1], atol=1e-12)
    assert f.shape == (3, 4)


def test_operation_errors_say_what_is_expected():
    net, norm = _net()
    p = DeepProMP(net, norm, ["a", "b"], name="reach")
    with pytest.raises(ValueError, match="3 joint values; primitive 'reach' has 2 joints"):
        p.condition([0.5], [[0.1, 0.2, 0.3]])
    with pytest.raises(ValueError, match="NaN or inf"):
        p.condition([0.5], [[np.nan, 0.2]])
    with pytest.raises(ValueError, match=r"outside \[0, 1\]"):
        p.condition([1.5], [[0.1, 0.2]])
    with pytest.raises(ValueError, match="NaN or inf"):
        p.condition([np.inf], [[0.1, 0.2]])
    with pytest.raises(ValueError, match="takes no context 'camera'"):
        p.condition(contexts={"camera": [1.0]})
    with pytest.raises(ValueError, match=r"3 values per vector"):
        p.condition(contexts={"obj": [1.0, 2.0]})
    with pytest.raises(ValueError, match="importance weights must be finite and >= 0"):
        p.condition([0.5], [[0.1, 0.2]], via_weights=[-1.0])
    with pytest.raises(ValueError, match="at least one via-point"):
        p.refine(p.prior(), [], np.zeros((0, 2)))
    with pytest.raises(ValueError, match="number of samples"):
        p.sample(p.prior(), [0.0, 1.0], 0)
    with pytest.raises(ValueError, match="both phases"):
        p.condition(via_x=[0.5])


# ------------------------------------------------------------------------- dataset format
def _demo(name="d0", n=20, **kw):
    t = np.linspace(0, 2, n)
    q = np.stack([np.sin(t), np.cos(t)], 1)
    return demo_from_arrays(name, t, q, ["j1", "j2"], **kw)


def test_dataset_roundtrip_npz_and_csv(tmp_path):
    d = _demo(contexts={"obj": [0.1, 0.2, 0.3]}, images=np.zeros((2, 8, 8, 3), np.uint8))
    save_demo(d, tmp_path / "a.npz")
    back = load_demo(tmp_path / "a.npz")
    np.testing.assert_array_equal(back.q, d.q)
    np.testing.assert_array_equal(back.contexts["obj"], [[0.1, 0.2, 0.3]])
    assert back.images.shape == (2, 8, 8, 3) and back.joint_names == ("j1", "j2")
    csv = tmp_path / "demo_b.csv"
    csv.write_text("t,j1,j2\n0,0,1\n0.5,0.1,0.9\n1.0,0.2,0.8\n")
    c = load_csv(csv)
    assert c.q.shape == (3, 2) and c.name == "demo_b"
    with pytest.raises(DatasetError, match="demo_b': context modalities"):
        load_dataset(tmp_path)  # one demo has a context, the other not
    (tmp_path / "a.npz").unlink()
    ds = load_dataset(tmp_path)
    assert len(ds) == 1 and ds.joint_names == ("j1", "j2")


@pytest.mark.parametrize("mutate, message", [
    (lambda t, q: (t, np.where(np.arange(q.size).reshape(q.shape) == 7, np.nan, q)), "NaN or inf"),
    (lambda t, q: (t[:-1], q), "ragged shapes"),
    (lambda t, q: (np.r_[t[:5], t[4], t[6:]], q), "not strictly increasing"),
])
def test_bad_demonstrations_are_refused_with_demo_name(mutate, message):
    t = np.linspace(0, 1, 10)
    q = np.zeros((10, 2))
    t2, q2 = mutate(t, q)
    with pytest.raises(DatasetError, match=f"demonstration 'bad_one'.*{message}"):
        demo_from_arrays("bad_one", t2, q2, ["j1", "j2"])


def test_dataset_refuses_mismatched_joint_names(tmp_path):
    a = _demo("a")
    b = demo_from_arrays("b", a.t, a.q, ["j1", "elbow"])
    with pytest.raises(DatasetError, match="demonstration 'b': joint names"):
        DemoDataset((a, b))
    save_demo(a, tmp_path / "a.npz")
    np.savez(tmp_path / "broken.npz", t=np.arange(3.0))
    with pytest.raises(DatasetError, match="broken.npz.*missing arrays"):
        load_dataset(tmp_path)


def test_bimodal_sine_has_two_modes_crossing_zero():
    ds = bimodal_sine(40, seed=3)
    y = np.stack([d.resampled(101)[:, 0] for d in ds.demos])
    assert np.all(np.abs(y[:, [0, 50, 100]]) < 0.05)
    quarter = y[:, 25]
    assert (quarter > 0.7).sum() >= 10 and (quarter < -0.7).sum() >= 10
    assert not np.any(np.abs(quarter) < 0.7)


# ------------------------------------------------------------------------- checkpoints
def test_checkpoint_roundtrip_carries_config_and_normalization(tmp_path):
    net, norm = _net()
    path = save_checkpoint(tmp_path / "m.safetensors", net, norm, ["a", "b"], {"provenance": {"dataset": "x"}})
    ck = load_checkpoint(path)
    assert ck.config == net.cfg and ck.joint_names == ("a", "b")
    assert ck.metadata["provenance"]["dataset"] == "x"
    p1, p2 = DeepProMP(net, norm, ["a", "b"]), DeepProMP.from_checkpoint(path)
    x = np.linspace(0, 1, 7)
    lat = p1.condition([0.3], [[0.1, 0.2]], contexts={"obj": [1, 0, 0]})
    np.testing.assert_allclose(p2.mean_trajectory(lat, x), p1.mean_trajectory(lat, x), atol=1e-12)
