"""A two-process torchrun training resumed from its resume file (every process's generators restored)
ends bitwise where an uninterrupted one does."""

import pytest
import torch

import torchrun_launch
from deepprompt_ros.data.synthetic import bimodal_sine
from deepprompt_ros.model.checkpoint import load_checkpoint

TORCHRUN = [*torchrun_launch.TORCHRUN, "--nnodes", "1", "--nproc_per_node", "2",
            "--master_addr", "127.0.0.1"]


@pytest.fixture()
def data(tmp_path):
    folder = tmp_path / "data"
    bimodal_sine(40, n_points=30, seed=1).save(folder)
    return folder


def test_two_process_run_resumes_to_the_uninterrupted_result(data, tmp_path):
    (tmp_path / "cfg.yaml").write_text("val_every: 20\nhidden: 32\nlatent_dim: 4\nthreads: 1\nn_points: 30\n"
                                       "auto_select: false\nbatch_size: 8\n")

    def run(out, steps, *extra):
        proc = torchrun_launch.run([*TORCHRUN, "--master_port", str(torchrun_launch.free_port()), "-m",
                                    "deepprompt_ros.training.cli", "--data", str(data), "--config",
                                    str(tmp_path / "cfg.yaml"), "--out", str(out), "--steps", str(steps), *extra],
                                   timeout=120)
        assert proc.returncode == 0, proc.stderr[-3000:]
        return proc.stdout

    run(tmp_path / "straight.safetensors", 60)
    run(tmp_path / "resumed.safetensors", 40)
    assert "resumed from" in run(tmp_path / "resumed.safetensors", 60, "--resume")
    a, b = (load_checkpoint(tmp_path / f"{n}.safetensors") for n in ("straight", "resumed"))
    for k, t in a.state_dict.items():
        assert torch.equal(t, b.state_dict[k]), k
    assert a.metadata["metrics"]["best_val_mse_rad2"] == b.metadata["metrics"]["best_val_mse_rad2"]
