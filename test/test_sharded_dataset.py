"""The sharded dataset format (deepprompt_ros.data.sharded): the converter round-trips demonstrations
exactly, the streaming normalization equals the in-memory one, and damaged or inconsistent data is
refused with a message and exit status 2 (the converter's and train's command lines)."""
import json
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from deepprompt_ros.data.demo_dataset import DemoDataset, load_dataset
from deepprompt_ros.data.demonstration import DatasetError, demo_from_arrays
from deepprompt_ros.data.sharded import INDEX, ShardedDataset, convert_folder, is_sharded, main as shard_main, \
    write_shards
from deepprompt_ros.training.cli import main as train_main
from deepprompt_ros.training.config import TrainConfig
from deepprompt_ros.training.streaming import streaming_normalization, train_sharded
from deepprompt_ros.training.tensors import fit_normalization

ROOT = pathlib.Path(__file__).resolve().parents[1]


def ragged_demos(n: int, seed: int = 0, joints=("a", "b", "c")):
    """Demos of different lengths, context counts and image counts (what the format must keep)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        T = int(rng.integers(20, 40))
        t = np.cumsum(rng.uniform(0.01, 0.05, T))
        q = rng.normal(size=(T, len(joints)))
        ctx = {"object": rng.normal(size=(int(rng.integers(1, 4)), 3)), "task": rng.normal(size=(1, 2))}
        images = rng.integers(0, 256, size=(int(rng.integers(1, 4)), 8, 12, 3), dtype=np.uint8)
        out.append(demo_from_arrays(f"demo {i}", t, q, joints, ctx, images))
    return out


def assert_same_demo(a, b):
    assert a.name == b.name and a.joint_names == b.joint_names and a.phase_type == b.phase_type
    assert np.array_equal(a.t, b.t) and np.array_equal(a.q, b.q)
    assert sorted(a.contexts) == sorted(b.contexts)
    for k in a.contexts:
        assert np.array_equal(a.contexts[k], b.contexts[k])
    assert np.array_equal(a.images, b.images) and b.images.dtype == np.uint8


def test_converter_round_trips_every_demo_exactly(tmp_path):
    demos = ragged_demos(23)
    DemoDataset(tuple(demos)).save(tmp_path / "folder")
    assert shard_main([str(tmp_path / "folder"), str(tmp_path / "shards"), "--shard-size", "5"]) == 0
    ds = ShardedDataset(tmp_path / "shards")
    ref = load_dataset(tmp_path / "folder")
    assert is_sharded(tmp_path / "shards") and not is_sharded(tmp_path / "folder")
    assert len(ds) == 23 and len(ds.shards) == 5 and ds.joint_names == ref.joint_names
    assert ds.context_dims == ref.context_dims == {"object": 3, "task": 2} and ds.image_shape == (8, 12)
    assert ds.max_contexts == {"object": max(len(d.contexts["object"]) for d in demos), "task": 1}
    assert ds.max_images == max(len(d.images) for d in demos)
    for a, b in zip(ref.demos, ds.read(range(23))):  # load_dataset's order
        assert_same_demo(a, b)
    # any order, across shards; without images
    order = [22, 0, 7, 7, 13]
    for i, b in zip(order, ds.read(order)):
        assert_same_demo(ref.demos[i], b)
    assert all(d.images is None for d in ds.read([3, 9], images=False))


def test_streaming_normalization_equals_the_in_memory_one(tmp_path):
    demos = ragged_demos(30, seed=1)
    ds = write_shards(demos, tmp_path / "s", shard_size=7)
    ids = [1, 2, 5, 8, 13, 21, 22, 29]
    ref = fit_normalization(DemoDataset(tuple(demos[i] for i in ids)), 50)
    got = streaming_normalization(ds, ids, 50)
    np.testing.assert_allclose(got.y_mean, ref.y_mean, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(got.y_std, ref.y_std, rtol=1e-12)
    for k in ref.ctx_mean:
        np.testing.assert_allclose(got.ctx_mean[k], ref.ctx_mean[k], rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(got.ctx_std[k], ref.ctx_std[k], rtol=1e-12)


def test_converter_refuses_mixed_joint_names_and_leaves_no_dataset(tmp_path, capsys):
    demos = ragged_demos(4) + ragged_demos(2, joints=("a", "b", "x"))
    DemoDataset(tuple(demos[:4])).save(tmp_path / "folder")
    for i, d in enumerate(demos[4:]):  # written after the others: the converter meets them last
        DemoDataset((d,)).save(tmp_path / "tmp")
        (tmp_path / "tmp" / f"00000_{d.name.replace(' ', '_')}.npz").rename(tmp_path / "folder" / f"9999{i}.npz")
    assert shard_main([str(tmp_path / "folder"), str(tmp_path / "shards"), "--shard-size", "2"]) == 2
    err = capsys.readouterr().err
    assert "joint names ['a', 'b', 'x'] do not match the dataset's ['a', 'b', 'c']" in err
    assert not (tmp_path / "shards").exists()
    with pytest.raises(DatasetError, match="not empty"):
        write_shards(demos[:2], tmp_path / "folder")
    (tmp_path / "empty").mkdir()  # an empty folder given as the output stays, empty, when the conversion fails
    with pytest.raises(DatasetError, match="joint names"):
        write_shards(demos, tmp_path / "empty", shard_size=2)
    assert (tmp_path / "empty").is_dir() and not any((tmp_path / "empty").iterdir())
    with pytest.raises(DatasetError, match="'.*nowhere' does not exist; expected a folder of .npz/.csv"):
        convert_folder(tmp_path / "nowhere", tmp_path / "out")


def damage(folder: pathlib.Path, how: str):
    index = json.loads((folder / INDEX).read_text())
    shard = folder / index["shards"][1]["dir"]
    if how == "missing shard file":
        (shard / "q.npy").unlink()
    elif how == "truncated images":
        data = (shard / "images.npy").read_bytes()
        (shard / "images.npy").write_bytes(data[: len(data) // 2])
    elif how == "index count":
        index["n_demos"] += 1
        (folder / INDEX).write_text(json.dumps(index))
    elif how == "index rows":
        index["shards"][1]["rows"] += 3
        (folder / INDEX).write_text(json.dumps(index))
    elif how == "index shard entry":
        del index["shards"][1]["first"]
        (folder / INDEX).write_text(json.dumps(index))
    elif how == "index shard not a dict":
        index["shards"][1] = "shard_00001"
        (folder / INDEX).write_text(json.dumps(index))
    elif how == "index shard dir outside":
        index["shards"][1]["dir"] = "../shards/shard_00001"
        (folder / INDEX).write_text(json.dumps(index))
    elif how == "index json":
        (folder / INDEX).write_text("{not json")
    elif how == "nan in q":
        q = np.load(shard / "q.npy")
        q[4, 1] = np.nan
        np.save(shard / "q.npy", q)


@pytest.mark.parametrize("how, message", [
    ("missing shard file", "shard 'shard_00001' has no file q.npy"),
    ("truncated images", "shard 'shard_00001' file images.npy cannot be read"),
    ("index count", "the shards hold 12 demonstrations; index.json says 13"),
    ("index rows", "shard 'shard_00001' file t.npy has shape"),
    ("index json", "index.json cannot be read"),
    ("index shard entry", "index.json cannot be read (KeyError('first'))"),
    ("index shard not a dict", "index.json cannot be read (TypeError("),
    ("index shard dir outside", "shard dir '../shards/shard_00001' is not a folder name inside the dataset"),
    ("nan in q", "joint positions contain NaN or inf"),
])
def test_train_refuses_a_damaged_sharded_dataset_with_exit_status_2(tmp_path, capsys, how, message):
    folder = tmp_path / "shards"
    write_shards(ragged_demos(12), folder, shard_size=4)
    damage(folder, how)
    code = train_main(["--data", str(folder), "--out", str(tmp_path / "m.safetensors"), "--steps", "2"])
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err, err
    assert not (tmp_path / "m.safetensors").exists()


def test_train_command_exits_2_on_a_damaged_shard(tmp_path):
    folder = tmp_path / "shards"
    write_shards(ragged_demos(6), folder, shard_size=3)
    damage(folder, "missing shard file")
    out = subprocess.run([sys.executable, "-m", "deepprompt_ros.training.cli", "--data", str(folder), "--out",
                          str(tmp_path / "m.safetensors")], capture_output=True, text=True, timeout=120,
                         cwd=ROOT)
    assert out.returncode == 2, out.stderr
    assert "has no file q.npy; expected every file the index lists" in out.stderr


def test_a_shard_damaged_during_training_stops_it_with_the_workers_message(tmp_path):
    folder = tmp_path / "shards"
    ds = write_shards(ragged_demos(12), folder, shard_size=4)  # opened: the files' sizes are known
    images = folder / "shard_00002" / "images.npy"
    images.write_bytes(images.read_bytes()[:-100])
    cfg = TrainConfig(steps=20, threads=1, batch_size=4, n_points=20, auto_select=False, data_workers=2, n_val=2,
                      hidden=16, latent_dim=4)
    with pytest.raises(DatasetError) as err:
        train_sharded(ds, cfg, log=lambda s: None)
    assert str(err.value).startswith(f"sharded dataset '{folder}': shard 'shard_00002' file images.npy has ")
    assert str(err.value).endswith("when the dataset was opened; expected it unchanged")
