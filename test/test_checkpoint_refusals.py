"""Every refusal path of model-file loading, each with the message that names what is wrong:
the safetensors layer (model.safetensors_file: not a file, pickles, truncated or corrupt files,
implausible header sizes), DeepProMP checkpoints (model.checkpoint.load_checkpoint: format tag,
metadata JSON, model config, joint names, architecture against the tensors, dtypes, NaN / inf,
normalization) and the baselines' files (CNMP, ProMP and load_model). Every bad file is made from
a good one by one change, and the good one, written the same way, loads."""
import json
import os
import pickle

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import save_file

from deepprompt_ros.baselines.concat import CNMP
from deepprompt_ros.baselines.promp_model import ProMPModel
from deepprompt_ros.baselines.registry import load_model
from deepprompt_ros.data.synthetic import bimodal_sine
from deepprompt_ros.model.checkpoint import CheckpointError, Normalization, load_checkpoint, save_checkpoint
from deepprompt_ros.model.network import DeepProMPNet, ModelConfig
from deepprompt_ros.model.safetensors_file import MAX_HEADER
from deepprompt_ros.primitive.deep_promp import DeepProMP
from deepprompt_ros.training.config import TrainConfig

torch.set_num_threads(1)


def _contents(path):
    with safe_open(str(path), framework="pt") as f:
        return dict(f.metadata()), {k: f.get_tensor(k) for k in f.keys()}


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    """A small DeepProMP checkpoint (2 joints, context 'obj' (3), hidden 8, latent 4): its path,
    metadata and tensors."""
    torch.manual_seed(0)
    net = DeepProMPNet(ModelConfig(n_joints=2, latent_dim=4, hidden=8, context_dims=(("obj", 3),)))
    norm = Normalization(np.zeros(2), np.ones(2), {"obj": np.zeros(3)}, {"obj": np.ones(3)})
    path = save_checkpoint(tmp_path_factory.mktemp("good") / "m.safetensors", net, norm, ["a", "b"],
                           {"provenance": {"dataset": "x"}})
    return (path, *_contents(path))


def _write(path, meta, tensors):
    save_file(tensors, str(path), metadata=meta)
    return path


def _raw(header: dict, data: bytes) -> bytes:
    """A safetensors file from its JSON header and data bytes (no checks: the header may lie)."""
    h = json.dumps(header).encode()
    return len(h).to_bytes(8, "little") + h + data


def _split(path):
    b = path.read_bytes()
    n = int.from_bytes(b[:8], "little")
    return json.loads(b[8:8 + n]), b[8 + n:]


def _config(meta, **change):
    return {**meta, "model_config": json.dumps({**json.loads(meta["model_config"]), **change})}


def test_the_unchanged_file_written_the_same_way_loads(good, tmp_path):
    path, meta, tensors = good
    ck = load_checkpoint(_write(tmp_path / "same.safetensors", meta, tensors))
    assert ck.joint_names == ("a", "b") and ck.config.hidden == 8 and ck.metadata["provenance"]["dataset"] == "x"
    assert DeepProMP.from_checkpoint(path).n_joints == 2


# ------------------------------------------------------------------------------------------------
# the file itself (model.safetensors_file, before anything is parsed)
# ------------------------------------------------------------------------------------------------
class _Evil:
    marker = None

    def __reduce__(self):
        return (os.system, (f"touch {_Evil.marker}",))


@pytest.mark.parametrize("write", [
    lambda p: p.write_bytes(pickle.dumps({"state_dict": _Evil()}, protocol=4)),
    lambda p: p.write_bytes(pickle.dumps({"state_dict": _Evil()}, protocol=0)),
    lambda p: torch.save({"x": _Evil()}, p),
], ids=["pickle", "pickle_protocol_0", "torch_save"])
def test_pickles_are_refused_and_never_executed(tmp_path, write):
    _Evil.marker = tmp_path / "pwned"
    path = tmp_path / "evil.safetensors"
    write(path)
    for load in (load_checkpoint, CNMP.load, ProMPModel.load, load_model):
        with pytest.raises(ValueError, match=r"is not a safetensors file \(.*pickled .* are refused: they can run code"):
            load(path)
    assert not _Evil.marker.exists()


def test_a_path_that_is_not_a_file_is_refused(tmp_path):
    with pytest.raises(CheckpointError, match="does not exist; expected a .safetensors DeepProMP checkpoint"):
        load_checkpoint(tmp_path / "nope.safetensors")
    with pytest.raises(CheckpointError, match="is a directory; expected"):
        load_checkpoint(tmp_path)
    os.mkfifo(tmp_path / "fifo.safetensors")  # opening it would block: refused before any read
    with pytest.raises(CheckpointError, match="is not a regular file"):
        load_checkpoint(tmp_path / "fifo.safetensors")


def test_truncated_files_are_refused(good, tmp_path):
    data = good[0].read_bytes()
    n = int.from_bytes(data[:8], "little")
    cases = {0: "0 bytes long, too short for a safetensors file", 5: "5 bytes long, too short",
             20: rf"truncated or not a safetensors file: its header size says {n} bytes but only 12 bytes follow",
             len(data) // 2: "truncated or not a safetensors file",
             len(data) - 4: r"corrupt or truncated \(not a complete safetensors file\)"}
    for size, message in cases.items():
        path = tmp_path / f"cut_{size}.safetensors"
        path.write_bytes(data[:size])
        with pytest.raises(CheckpointError, match=message):
            load_checkpoint(path)


def test_implausible_header_sizes_and_offsets_are_refused(good, tmp_path):
    header, data = _split(good[0])
    big = tmp_path / "big.safetensors"  # a header size over the limit in a file large enough to hold it
    with open(big, "wb") as f:
        f.write((MAX_HEADER + 1).to_bytes(8, "little") + b"{")
        f.truncate(MAX_HEADER + 100)  # sparse: no disk space used
    with pytest.raises(CheckpointError, match=f"header of {MAX_HEADER + 1} bytes, over the limit of {MAX_HEADER}"):
        load_checkpoint(big)
    k = "net.head.weight"
    for name, change in {"offset": lambda h: h[k]["data_offsets"].__setitem__(1, 10 ** 12),
                         "shape": lambda h: h[k].__setitem__("shape", [10 ** 6, 10 ** 6])}.items():
        h = json.loads(json.dumps(header))
        change(h)
        path = tmp_path / f"{name}.safetensors"
        path.write_bytes(_raw(h, data))
        with pytest.raises(CheckpointError, match="is corrupt or truncated.*invalid shape, data type, or offset"):
            load_checkpoint(path)


def test_a_header_that_is_not_json_is_refused(good, tmp_path):
    _, data = _split(good[0])
    path = tmp_path / "nojson.safetensors"
    path.write_bytes((4).to_bytes(8, "little") + b"[1,2" + data)
    with pytest.raises(CheckpointError, match="is not a safetensors file \\(its header is not a JSON object"):
        load_checkpoint(path)
    path.write_bytes((6).to_bytes(8, "little") + b"{oops}" + data)
    with pytest.raises(CheckpointError, match="is corrupt or truncated.*invalid JSON in header"):
        load_checkpoint(path)
    path.write_bytes(good[0].read_bytes() + b"\0" * 16)  # data past what the header describes
    with pytest.raises(CheckpointError, match="is corrupt or truncated"):
        load_checkpoint(path)


# ------------------------------------------------------------------------------------------------
# DeepProMP checkpoints: metadata
# ------------------------------------------------------------------------------------------------
def _without(meta, key):
    return {k: v for k, v in meta.items() if k != key}


METADATA_CASES = {
    "no_format": (lambda m: _without(m, "format"), "has no format tag; expected 'deepprompt_ros.deepprompt/1'"),
    "other_format": (lambda m: {**m, "format": "other"}, "has format 'other'; expected 'deepprompt_ros.deepprompt/1'"),
    "no_model_config": (lambda m: _without(m, "model_config"), "lacks the metadata entry 'model_config'"),
    "model_config_not_json": (lambda m: {**m, "model_config": "{n_joints: 2"},
                              "metadata entry 'model_config' is not valid JSON"),
    "model_config_not_object": (lambda m: {**m, "model_config": "[2, 4]"},
                                "metadata entry 'model_config' must be a JSON object; got list"),
    "model_config_unknown_key": (lambda m: _config(m, layers=3), "model config has unknown keys \\['layers'\\]"),
    "model_config_invalid_value": (lambda m: _config(m, hidden=-3), "hidden = -3: expected a value in \\[1, inf\\]"),
    "model_config_bad_phase": (lambda m: _config(m, phase_type="spiral"), "phase_type = 'spiral'"),
    "no_joint_names": (lambda m: _without(m, "joint_names"), "lacks the metadata entry 'joint_names'"),
    "joint_names_not_list": (lambda m: {**m, "joint_names": '"ab"'},
                             "metadata entry 'joint_names' must be a JSON array; got str"),
    "joint_names_not_strings": (lambda m: {**m, "joint_names": "[1, 2]"}, "joint names as non-empty strings"),
    "joint_names_repeated": (lambda m: {**m, "joint_names": '["a", "a"]'}, "names joint\\(s\\) \\['a'\\] more than once"),
    "joint_names_count": (lambda m: {**m, "joint_names": '["a", "b", "c"]'}, "names 3 joints but its model has 2"),
    "metadata_not_object": (lambda m: {**m, "metadata": "[1]"}, "metadata entry 'metadata' must be a JSON object"),
    "metadata_not_json": (lambda m: {**m, "metadata": "{"}, "metadata entry 'metadata' is not valid JSON"),
    "phase_type_disagrees": (lambda m: {**m, "phase_type": "rhythmic"},
                             "has phase type 'rhythmic' but its model config 'linear'"),
    "latent_linear_without_basis": (lambda m: _config(m, latent_linear=2),
                                    "latent_linear = 2 needs a linear basis: expected decoder_basis >= 2, got 0"),
    "latent_linear_above_latent_dim": (lambda m: _config(m, decoder_basis=4, latent_linear=5),
                                       "latent_linear = 5: expected at most latent_dim = 4"),
    "latent_linear_above_basis_weights": (lambda m: _config(m, decoder_basis=2, latent_dim=6, latent_linear=5),
                                          "latent_linear = 5: expected at most decoder_basis x n_joints = 2 x 2 = 4"),
    "latent_linear_negative": (lambda m: _config(m, latent_linear=-1), "latent_linear = -1: expected a value in"),
    "via_noise_zero": (lambda m: _config(m, via_noise=0.0), "via_noise = 0.0 normalized: expected a value in \\(0, inf\\)"),
}


@pytest.mark.parametrize("case", sorted(METADATA_CASES))
def test_bad_metadata_is_refused(good, tmp_path, case):
    change, message = METADATA_CASES[case]
    path = _write(tmp_path / f"{case}.safetensors", change(good[1]), good[2])
    with pytest.raises(CheckpointError, match=message):
        load_checkpoint(path)
    with pytest.raises(CheckpointError, match=message):
        DeepProMP.from_checkpoint(path)


# ------------------------------------------------------------------------------------------------
# DeepProMP checkpoints: tensors against the architecture of the model config
# ------------------------------------------------------------------------------------------------
def _set(tensors, key, fn):
    t = dict(tensors)
    t[key] = fn(t[key].clone())
    return t


def _poke(value):
    def fn(t):
        t.view(-1)[0] = value
        return t
    return fn


ARCH = r"its model config \(2 joints, latent_dim 4, hidden 8, decoder_basis 0, latent_linear 0\)"
TENSOR_CASES = {
    "missing_weight": (lambda t: _without(t, "net.head.weight"), f"lacks tensor\\(s\\) 'net.head.weight' that {ARCH} needs"),
    "missing_normalization": (lambda t: _without(t, "norm.ctx_std.obj"), "lacks tensor\\(s\\) 'norm.ctx_std.obj'"),
    "extra_weight": (lambda t: {**t, "net.extra.weight": torch.zeros(2)},
                     f"has tensor\\(s\\) 'net.extra.weight' that {ARCH} does not have"),
    "unknown_tensor": (lambda t: {**t, "optimizer.step": torch.zeros(1)}, "has tensor\\(s\\) 'optimizer.step'"),
    "wrong_shape": (lambda t: {**t, "net.head.weight": torch.zeros(3, 3)},
                    f"tensor 'net.head.weight' has shape \\(3, 3\\) but {ARCH} needs \\(8, 8\\)"),
    "integer_weight": (lambda t: _set(t, "net.head.weight", lambda w: w.to(torch.int64)),
                       "tensor 'net.head.weight' has dtype int64; expected floating point"),
    "nan_weight": (lambda t: _set(t, "net.decoder.0.weight", _poke(float("nan"))),
                   "tensor 'net.decoder.0.weight' contains NaN or inf"),
    "inf_weight": (lambda t: _set(t, "net.head.bias", _poke(float("inf"))), "tensor 'net.head.bias' contains NaN or inf"),
    "nan_normalization": (lambda t: _set(t, "norm.y_mean", _poke(float("nan"))), "tensor 'norm.y_mean' contains NaN or inf"),
    "zero_joint_std": (lambda t: _set(t, "norm.y_std", _poke(0.0)), "has invalid joint normalization"),
    "negative_context_std": (lambda t: _set(t, "norm.ctx_std.obj", _poke(-1.0)),
                             "has invalid normalization for context 'obj'"),
    "context_normalization_shape": (lambda t: {**t, "norm.ctx_mean.obj": torch.zeros(4, dtype=torch.float64)},
                                    "tensor 'norm.ctx_mean.obj' has shape \\(4,\\) but .* needs \\(3,\\)"),
}


@pytest.mark.parametrize("case", sorted(TENSOR_CASES))
def test_bad_tensors_are_refused(good, tmp_path, case):
    change, message = TENSOR_CASES[case]
    path = _write(tmp_path / f"{case}.safetensors", good[1], change(good[2]))
    with pytest.raises(CheckpointError, match=message):
        load_checkpoint(path)


def test_a_config_that_disagrees_with_the_weights_is_refused(good, tmp_path):
    path = _write(tmp_path / "wider.safetensors", _config(good[1], hidden=16), good[2])
    with pytest.raises(CheckpointError, match=r"tensor 'net.\w+.0.weight' has shape \(8, \d+\) but its model config "
                                              r"\(2 joints, latent_dim 4, hidden 16, decoder_basis 0, latent_linear 0\) "
                                              r"needs \(16, \d+\)"):
        load_checkpoint(path)
    path = _write(tmp_path / "context.safetensors", _config(good[1], context_dims=[["obj", 5]]), good[2])
    with pytest.raises(CheckpointError, match="has shape .* needs"):
        load_checkpoint(path)


def test_a_config_of_a_huge_network_is_refused_before_anything_is_allocated(good, tmp_path):
    # 10^6 x 10^6 float32 weights would be 4 TB: the shapes are compared on the meta device first
    path = _write(tmp_path / "huge.safetensors", _config(good[1], hidden=10 ** 6, latent_dim=10 ** 5), good[2])
    with pytest.raises(CheckpointError, match=r"has shape \(8, 3\) but its model config \(2 joints, latent_dim "
                                              r"100000, hidden 1000000, decoder_basis 0, latent_linear 0\) needs "
                                              r"\(1000000, 3\)"):
        load_checkpoint(path)


def test_a_latent_split_that_disagrees_with_the_weights_is_refused(tmp_path):
    """A file of a split latent (k_l = 2 of 4, basis 3) whose config states another split: the basis
    reads k_l inputs and the MLP k − k_l, so the shapes say which split the weights were made for."""
    net = DeepProMPNet(ModelConfig(n_joints=2, latent_dim=4, hidden=8, decoder_basis=3, latent_linear=2))
    path = save_checkpoint(tmp_path / "split.safetensors", net, Normalization(np.zeros(2), np.ones(2)), ["a", "b"])
    meta, tensors = _contents(path)
    assert load_checkpoint(path).config.latent_linear == 2
    # the decoder's first layer reads z_nl and the phase (k − k_l + 1 inputs), the basis z_lin (k_l, or k for 0)
    for k_l, needs in ((3, r"'net.decoder.0.weight' has shape \(8, 3\) but .* needs \(8, 2\)"),
                       (0, r"'net.decoder.0.weight' has shape \(8, 3\) but .* needs \(8, 5\)")):
        bad = _write(tmp_path / f"split{k_l}.safetensors", _config(meta, latent_linear=k_l), tensors)
        with pytest.raises(CheckpointError, match=rf"tensor {needs}"):
            load_checkpoint(bad)
        with pytest.raises(CheckpointError, match=rf"decoder_basis 3, latent_linear {k_l}\)"):
            load_checkpoint(bad)


# ------------------------------------------------------------------------------------------------
# the baselines' files
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def baselines(tmp_path_factory):
    """CNMP and ProMP files of a tiny fit on 12 bimodal sine demos: kind -> (class, path, meta, tensors)."""
    folder = tmp_path_factory.mktemp("baselines")
    cfg = TrainConfig(latent_dim=4, hidden=8, steps=2, val_every=2, n_points=20, threads=1)
    ds = bimodal_sine(12, n_points=20, seed=0)
    out = {}
    for cls in (CNMP, ProMPModel):
        path = cls().fit(ds, cfg).save(folder / f"{cls.kind}.safetensors")
        out[cls.kind] = (cls, path, *_contents(path))
    return out


def _json_entry(meta, key, **change):
    return {**meta, key: json.dumps({**json.loads(meta[key]), **change})}


BASELINE_CASES = {
    "spec_missing": ("both", lambda m, t: (_without(m, "spec"), t), "lacks the metadata entry 'spec'"),
    "spec_not_object": ("both", lambda m, t: ({**m, "spec": "[]"}, t), "metadata entry 'spec' must be a JSON object"),
    "spec_joint_names": ("both", lambda m, t: (_json_entry(m, "spec", joint_names="ab"), t),
                         "spec joint_names must be a list of distinct non-empty strings"),
    "spec_context_dims": ("both", lambda m, t: (_json_entry(m, "spec", context_dims=[["mode", 0]]), t),
                          "spec context_dims must be a list of \\[name, dimension >= 1\\]"),
    "metadata_not_object": ("both", lambda m, t: ({**m, "metadata": "[1]"}, t),
                            "metadata entry 'metadata' must be a JSON object"),
    "history_not_list": ("both", lambda m, t: ({**m, "metadata": '{"history": 5}'}, t),
                         "metadata 'history' must be a list"),
    "unknown_tensor": ("both", lambda m, t: (m, {**t, "junk": torch.zeros(2)}), "has tensor\\(s\\) 'junk'"),
    "missing_normalization": ("both", lambda m, t: (m, _without(t, "norm.y_std")), "lacks tensor\\(s\\) 'norm.y_std'"),
    "net_config_missing": ("cnmp", lambda m, t: (_without(m, "net_config"), t), "lacks the metadata entry 'net_config'"),
    "net_config_huge": ("cnmp", lambda m, t: (_json_entry(m, "net_config", hidden=10 ** 6, latent_dim=10 ** 5), t),
                        r"tensor 'net.encoder.0.weight' has shape \(8, \d+\) but its network config \(cnmp, "
                        r"latent_dim 100000, hidden 1000000\) needs \(1000000, \d+\)"),
    "net_config_variant": ("cnmp", lambda m, t: (_json_entry(m, "net_config", variant="vae_cnmp"), t),
                           "network config \\(vae_cnmp, .*\\) does not match a 'cnmp' model"),
    "weight_shape": ("cnmp", lambda m, t: (m, {**t, "net.head.weight": torch.zeros(3, 3)}),
                     "tensor 'net.head.weight' has shape \\(3, 3\\) but its network config"),
    "weight_integer": ("cnmp", lambda m, t: (m, _set(t, "net.head.weight", lambda w: w.to(torch.int32))),
                       "tensor 'net.head.weight' has dtype int32; expected floating point"),
    "weight_nan": ("cnmp", lambda m, t: (m, _set(t, "net.head.bias", _poke(float("nan")))),
                   "tensor 'net.head.bias' contains NaN or inf"),
    "promp_cov_nan": ("promp", lambda m, t: (m, _set(t, "promp.cov", _poke(float("nan")))),
                      "tensor 'promp.cov' contains NaN or inf"),
    "promp_mean_integer": ("promp", lambda m, t: (m, _set(t, "promp.mean", lambda w: w.to(torch.int64))),
                           "tensor 'promp.mean' has dtype int64"),
    "promp_cov_shape": ("promp", lambda m, t: (m, {**t, "promp.cov": torch.zeros(3, 3, dtype=torch.float64)}),
                        "array shapes .* do not match the metadata"),
    "promp_meta_not_json": ("promp", lambda m, t: ({**m, "promp": "{"}, t), "ProMP metadata is not valid JSON"),
    "promp_meta_key": ("promp", lambda m, t: ({**m, "promp": json.dumps(
        {k: v for k, v in json.loads(m["promp"]).items() if k != "n_basis"})}, t), "ProMP metadata lacks 'n_basis'"),
    "promp_n_basis_huge": ("promp", lambda m, t: (_json_entry(m, "promp", n_basis=10 ** 6), t),
                           "do not match the metadata"),
    "promp_options": ("promp", lambda m, t: ({**m, "options": '{"bogus": 1}'}, t), "has invalid ProMP options"),
    "promp_missing": ("promp", lambda m, t: (_without(m, "promp"), t), "lacks the metadata entry 'promp'"),
}


@pytest.mark.parametrize("kind", ["cnmp", "promp"])
def test_baseline_files_written_the_same_way_load(baselines, tmp_path, kind):
    cls, _, meta, tensors = baselines[kind]
    path = _write(tmp_path / "same.safetensors", meta, tensors)
    assert type(cls.load(path)) is cls and type(load_model(path)) is cls


@pytest.mark.parametrize("kind, case", [(k, c) for c, (which, _, _) in sorted(BASELINE_CASES.items())
                                        for k in ("cnmp", "promp") if which in ("both", k)])
def test_bad_baseline_files_are_refused(baselines, tmp_path, kind, case):
    cls, path, meta, tensors = baselines[kind]
    _, change, message = BASELINE_CASES[case]
    bad = _write(tmp_path / f"{case}.safetensors", *change(meta, tensors))
    for load in (cls.load, load_model):
        with pytest.raises(ValueError, match=message):
            load(bad)


def test_a_decoder_of_modes_refuses_bad_shares_and_a_context_model_without_a_mean_per_mode(tmp_path):
    cfg = ModelConfig(n_joints=1, latent_dim=3, hidden=8, decoder_basis=4, latent_linear=2, decoder_modes=2,
                      context_dims=(("mode", 1),))
    net = DeepProMPNet(cfg)
    norm = Normalization(np.zeros(1), np.ones(1), {"mode": np.zeros(1)}, {"mode": np.ones(1)})
    path = save_checkpoint(tmp_path / "modes.safetensors", net, norm, ["a"])
    np.testing.assert_allclose(load_checkpoint(path).build().mode_cumulative_shares.numpy(), [0.5, 1.0])
    meta, tensors = _contents(path)
    for shares in ([0.6, 0.4], [0.5, 0.9], [0.0, 1.0]):
        bad = _write(tmp_path / "bad.safetensors", meta,
                     {**tensors, "net.mode_cumulative_shares": torch.tensor(shares)})
        with pytest.raises(CheckpointError, match="mode_cumulative_shares.*strictly rising in \\(0, 1\\] and ending at 1"):
            load_checkpoint(bad)
    one_mean = {"names": ["mode"], "dims": [1], "mean": [0.0], "scale": [1.0], "b": [[0.0, 0.0]], "r": [[1.0]]}
    with pytest.raises(ValueError, match="a mean for 0 modes, the decoder 2 modes"):
        DeepProMP(net, norm, ["a"], metadata={"selection": {"context": {"linear": one_mean}}})
    DeepProMP(net, norm, ["a"], metadata={"selection": {"context": {"linear": {**one_mean,
                                                                                "mode_means": [[-1.0], [1.0]]}}}})
