"""Low-dimensional contexts as linear Gaussian observations of z_lin (primitive.linear_context): the
fitted model recovers a known linear relation, conditioning on a context (and on via-points with it)
is textbook Gaussian conditioning of z_lin ~ N(0, I), a subset of the modalities conditions on their
marginal, the record survives a checkpoint and a malformed one is refused; the training's choice
(training.selection.choose_context_paths) on contexts that are a linear function of the demos."""
import numpy as np
import pytest
import torch

from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.data.demonstration import demo_from_arrays
from deepprompt_ros.model.checkpoint import save_checkpoint
from deepprompt_ros.primitive.deep_promp import DeepProMP
from deepprompt_ros.primitive.linear_context import R_FLOOR, LinearContext, fit_linear_context
from deepprompt_ros.training.config import TrainConfig
from deepprompt_ros.training.selection import choose_context_paths
from test_linear_conditioning import split_model

torch.set_num_threads(1)


def textbook(b, r, cs, h=None, y=None, noise=None):
    """Posterior mean and covariance of z ~ N(0, I) given cs = B z + N(0, R) (and y = H z + N(0, noise² I))."""
    obs, cov = b, r
    val = cs
    if h is not None:
        obs = np.vstack([b, h])
        cov = np.block([[r, np.zeros((r.shape[0], h.shape[0]))],
                        [np.zeros((h.shape[0], r.shape[0])), noise ** 2 * np.eye(h.shape[0])]])
        val = np.concatenate([cs, y])
    s = obs @ obs.T + cov
    gain = obs.T @ np.linalg.inv(s)
    return gain @ val, np.eye(b.shape[1]) - gain @ obs


def test_the_fit_recovers_a_known_linear_relation():
    rng = np.random.default_rng(0)
    n, k = 4000, 4
    z = rng.standard_normal((n, k))
    b_true = np.array([[0.8, 0.0, 0.3, 0.0], [0.0, -0.5, 0.0, 0.4]])
    c = 2.0 + (z @ b_true.T + 0.3 * rng.standard_normal((n, 2))) * np.array([1.0, 5.0])
    lin = fit_linear_context({"a": c[:, :1], "b": c[:, 1:]}, z)
    assert lin.names == ("a", "b") and lin.dims == (1, 1)
    # standardized units: B / std(c), R / var(c); the estimates' standard error is about 1 / sqrt(n) = 0.016
    std = np.sqrt((b_true ** 2).sum(1) + 0.09)
    assert np.abs(lin.b - b_true / std[:, None]).max() < 0.05
    assert np.abs(np.diag(lin.r) - 0.09 / std ** 2).max() < 0.02
    assert abs(lin.r[0, 1]) < 0.02


def test_a_relation_without_noise_keeps_the_floor():
    z = np.random.default_rng(1).standard_normal((50, 3))
    lin = fit_linear_context({"a": z[:, :2] * 3.0}, z)
    assert np.linalg.eigvalsh(lin.r).min() >= R_FLOOR * (1 - 1e-9)


def model_with_context():
    prim, x, Y = split_model(k_l=20, k_n=2, d=3, contexts=(("object", 2), ("flag", 1)))
    k_l = prim.cfg.latent_linear
    scores = np.stack([prim.condition(x, y, n_candidates=0).mean[:k_l] for y in Y])
    rng = np.random.default_rng(3)
    obj = scores[:, :2] * np.array([0.1, 0.2]) + 0.01 * rng.standard_normal((len(Y), 2))
    flag = scores[:, 2:3] + 0.1 * rng.standard_normal((len(Y), 1))
    lin = fit_linear_context({"object": obj, "flag": flag}, scores)
    with_lin = DeepProMP(prim.net, prim.norm, prim.joint_names,
                         metadata={"selection": {"context": {"linear": lin.to_json()}}})
    return prim, with_lin, lin, x, Y, obj, flag


def test_conditioning_on_contexts_is_gaussian_conditioning_of_z_lin():
    prim, with_lin, lin, x, Y, obj, flag = model_with_context()
    k_l = prim.cfg.latent_linear
    ctx = {"object": obj[0], "flag": flag[0]}
    lat = with_lin.condition(contexts=ctx)
    assert lin.names == ("flag", "object")  # name order
    cs = (np.concatenate([flag[0], obj[0]]) - lin.mean) / lin.scale
    # the model's z_lin prior with these contexts is N(0, I): their encodings inform z_nl only
    mean, cov = textbook(lin.b, lin.r, cs)
    assert np.abs(lat.mean[:k_l] - mean).max() < 1e-9
    assert np.abs(lat.var[:k_l] - np.diag(cov)).max() < 1e-9
    # with a via-point: the context rows and the via-point's rows together
    via_x, via_y, noise = np.array([0.5]), Y[0, len(x) // 2][None], 1e-3
    lat = with_lin.condition(via_x, via_y, contexts=ctx, via_noise=noise)
    _, h = prim._np.linear_design(via_x)
    b0, _ = prim._np.linear_design(via_x)
    off = prim._np.decode_nonlinear(lat.mean[None, k_l:], via_x)[0] + b0
    ys = np.asarray(prim.norm.y_std)
    mean, _ = textbook(lin.b, lin.r, cs, h.reshape(-1, k_l) / np.tile(ys, 1)[:, None],
                       ((via_y - off) / ys).reshape(-1), noise)
    assert np.abs(lat.mean[:k_l] - mean).max() < 1e-8
    # one modality alone: its marginal (the sub-blocks of B and R)
    lat = with_lin.condition(contexts={"object": obj[0]})
    mean, _ = textbook(lin.b[1:], lin.r[1:, 1:], cs[1:])
    assert np.abs(lat.mean[:k_l] - mean).max() < 1e-9
    # without the linear model the same request gives another z_lin (the encoders' factors)
    assert np.abs(prim.condition(contexts=ctx).mean[:k_l] - with_lin.condition(contexts=ctx).mean[:k_l]).max() > 1e-3


def test_the_record_survives_a_checkpoint_and_a_malformed_one_is_refused(tmp_path):
    prim, with_lin, lin, *_ = model_with_context()
    path = tmp_path / "m.safetensors"
    save_checkpoint(path, with_lin.net, with_lin.norm, with_lin.joint_names, with_lin.metadata)
    back = DeepProMP.from_checkpoint(path)
    assert back.linear_context.names == lin.names and np.array_equal(back.linear_context.b, lin.b)
    bad = lin.to_json() | {"b": np.zeros((3, 5)).tolist()}
    with pytest.raises(ValueError, match="does not fit the model"):
        DeepProMP(prim.net, prim.norm, prim.joint_names, metadata={"selection": {"context": {"linear": bad}}})
    with pytest.raises(ValueError, match="needs names, dims"):
        LinearContext.from_json({"names": ["object"]})
    with pytest.raises(ValueError, match="non-finite"):
        LinearContext.from_json(lin.to_json() | {"scale": [1.0, float("nan"), 1.0]})


def test_the_training_keeps_the_linear_model_where_the_contexts_are_linear_in_the_demos():
    prim, _, _, x, Y, obj, flag = model_with_context()
    ds = DemoDataset(tuple(demo_from_arrays(f"d{i}", x * 5.0, Y[i], prim.joint_names,
                                              contexts={"object": obj[i], "flag": flag[i]}) for i in range(len(Y))))
    cfg = TrainConfig(latent_dim=prim.cfg.latent_dim, latent_linear=prim.cfg.latent_linear,
                      decoder_basis=prim.cfg.decoder_basis, n_points=len(x))
    train, val = DemoDataset(ds.demos[:24]), DemoDataset(ds.demos[24:])
    rec = choose_context_paths(prim.net, prim.norm, prim.joint_names, cfg, train, val)
    # the random encoders know nothing of the contexts, which fix 3 of the 20 directions of z_lin: the
    # linear model reconstructs the validation demos better (0.52x in the run that set this bound)
    assert rec["chosen"] == "linear model" and rec["relative"]["linear model"] < 0.7, rec["relative"]
    assert set(rec["validation"]) == {"encoders", "linear model"}  # no images: no third candidate
    assert LinearContext.from_json(rec["linear"]).names == ("flag", "object")
    none = choose_context_paths(prim.net, prim.norm, prim.joint_names, cfg,
                                DemoDataset(tuple(demo_from_arrays(f"e{i}", x * 5.0, Y[i], prim.joint_names)
                                                  for i in range(5))), val)
    assert none == {"linear": None, "reason": "no low-dimensional context"}
