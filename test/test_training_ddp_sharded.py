"""A sharded dataset trains data-parallel under torchrun too: each process reads its share of every batch
(in the training process or in a DataLoader worker, the same model), and two processes on the shards give
the model two processes give on the same demonstrations in memory; --resume is refused for shards."""
import sys

import pytest

import torchrun_launch
from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.data.sharded import write_shards
from deepprompt_ros.data.synthetic import iter_image_reach
from deepprompt_ros.model.checkpoint import load_checkpoint

#: a fixed linear part (PCA-initialized) and a small network, as test_sharded_training's
CONFIG = ("steps: 20\nval_every: 10\nthreads: 1\nbatch_size: 8\nn_points: 40\nauto_select: false\ndecoder_basis: 10\n"
          "basis_init: pca\nbasis_lr_scale: 0.0\nlatent_linear: 8\nlatent_dim: 12\nhidden: 32\nn_val: 6\n")


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    root = tmp_path_factory.mktemp("ddp_sharded")
    demos = tuple(iter_image_reach(40, seed=3, n_joints=4, n_points=40, n_images=3, image_size=16))
    write_shards(demos, root / "shards", shard_size=7)
    DemoDataset(demos).save(root / "folder")
    (root / "cfg.yaml").write_text(CONFIG)
    (root / "workers.yaml").write_text(CONFIG + "data_workers: 1\n")
    return root


def _train(root, data, out, config="cfg.yaml", *extra, processes=2):
    head = ([*torchrun_launch.TORCHRUN, "--nnodes", "1", "--nproc_per_node", str(processes),
             "--master_addr", "127.0.0.1", "--master_port", str(torchrun_launch.free_port())] if processes > 1
            else [sys.executable])
    return torchrun_launch.run([*head, "-m", "deepprompt_ros.training.cli", "--data", str(root / data), "--config",
                                str(root / config), "--out", str(root / out), *extra], timeout=120)


def test_two_processes_on_shards_train_the_in_memory_model(root):
    runs = (("shards", "s.safetensors", "cfg.yaml"), ("folder", "m.safetensors", "cfg.yaml"),
            ("shards", "w.safetensors", "workers.yaml"))
    for data, out, config in runs:
        proc = _train(root, data, out, config)
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert "2 processes (torchrun), 4 of the batch's 8 demonstrations per process" in proc.stdout
    s, m, w = (load_checkpoint(root / f"{n}.safetensors") for n in "smw")
    assert [c.metadata["provenance"]["world_size"] for c in (s, m, w)] == [2, 2, 2]

    def diff(a, b):
        return max(float((a.state_dict[k] - b.state_dict[k]).abs().max()) for k in a.state_dict)

    # the same shares of the same draws on the same tensors: 0.0 measured (test_sharded_training: 0.0 in one process)
    assert diff(s, m) <= 1e-6
    assert s.metadata["metrics"]["best_val_mse_rad2"] == pytest.approx(
        m.metadata["metrics"]["best_val_mse_rad2"], rel=1e-6)  # 6e-8 relative measured (float64 chunked sums)
    # with several processes the batches are drawn apart from the other draws with workers or without:
    # a DataLoader worker reading each process's share gives the same model (0.0 measured)
    assert diff(s, w) <= 1e-6


def test_resume_is_refused_for_shards(root):
    proc = _train(root, "shards", "r.safetensors", "cfg.yaml", "--resume", processes=1)
    assert proc.returncode == 2 and "--resume: the sharded dataset" in proc.stderr, proc.stderr
