"""`train` under torchrun: two processes on one node and a two-node rendezvous over 127.0.0.1 train
to the end, process 0 writes a model that loads and conditions; refused launches exit with status 2
and say why."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from deepprompt_ros.data.synthetic import bimodal_sine
from deepprompt_ros.model.checkpoint import load_checkpoint
from deepprompt_ros.primitive.deep_promp import DeepProMP
from deepprompt_ros.training import distributed
from torchrun_launch import TORCHRUN, free_port, start, stop
from torchrun_launch import run as launch

CLI = ["-m", "deepprompt_ros.training.cli"]
CONFIG = "steps: 40\nval_every: 20\nhidden: 32\nthreads: 1\nn_points: 30\nbatch_size: 8\ncv_folds: 3\n"


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("ddp")
    bimodal_sine(24, n_points=30, seed=1).save(root / "data")
    (root / "cfg.yaml").write_text(CONFIG)
    return root


def _args(root, out, config="cfg.yaml"):
    return [*CLI, "--data", str(root / "data"), "--config", str(root / config), "--out", str(out)]


def _env():
    return {**os.environ, "OMP_NUM_THREADS": "1"}


def _check_model(out, summary):
    """The checkpoint loads, says it was trained by two gloo processes, and conditions: a via-point the
    prior's mean misses by 0.3 rad draws the conditioned mean towards it, and the refinement the server
    applies by default meets it."""
    ck = load_checkpoint(out)
    prov = ck.metadata["provenance"]
    assert (prov["world_size"], prov["backend"], prov["device"]) == (2, "gloo", "cpu")
    assert (summary["world_size"], summary["backend"]) == (2, "gloo")
    assert ck.metadata["metrics"]["best_val_mse_rad2"] == pytest.approx(summary["best_val_mse_rad2"])
    p = DeepProMP.from_checkpoint(out)
    x = np.linspace(0, 1, 31)
    prior = p.mean_trajectory(p.condition(), x)
    via = prior[15] + 0.3
    lat = p.condition(via_x=[0.5], via_y=[via])
    # measured 0.19 rad (the bimodal sines have little variance at 0.5)
    assert np.abs(p.mean_trajectory(lat, x)[15] - via).max() < 0.29
    refined = p.mean_trajectory(p.refine(lat, [0.5], [via]).latent, x)
    assert np.abs(refined[15] - via).max() < 1e-5  # measured 5e-7 rad


def test_torchrun_one_node_two_processes(setup):
    out = setup / "one_node.safetensors"
    proc = launch([*TORCHRUN, "--nnodes", "1", "--nproc_per_node", "2", "--master_addr", "127.0.0.1",
                   "--master_port", str(free_port()), *_args(setup, out)], timeout=120, env=_env())
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert ("device cpu, backend gloo, 2 processes (torchrun), 4 of the batch's 8 demonstrations per process"
            in proc.stdout)
    assert proc.stdout.count("training on 24 demonstrations") == 1  # process 0 alone prints
    _check_model(out, json.loads(proc.stdout.strip().splitlines()[-1]))


def test_torchrun_two_nodes_rendezvous_on_localhost(setup):
    out = setup / "two_nodes.safetensors"
    port = free_port()
    procs = [start([*TORCHRUN, "--nnodes", "2", "--nproc_per_node", "1", "--node_rank", str(node),
                    "--rdzv_backend", "c10d", "--rdzv_endpoint", f"127.0.0.1:{port}", "--rdzv_id", "t",
                    *_args(setup, out)], env=_env()) for node in (0, 1)]
    try:
        outs = [p.communicate(timeout=120) for p in procs]
    finally:
        for p in procs:  # both nodes' process trees, also when one overran its time
            stop(p)
    assert [p.returncode for p in procs] == [0, 0], [e[-2000:] for _, e in outs]
    printed = [o for o, _ in outs if o.strip()]
    assert len(printed) == 1, outs  # the node whose process got rank 0
    _check_model(out, json.loads(printed[0].strip().splitlines()[-1]))


def test_batch_not_divisible_is_refused(setup):
    (setup / "odd.yaml").write_text(CONFIG.replace("batch_size: 8", "batch_size: 7"))
    message = ("error: batch_size = 7 is not divisible by the 2 processes of this run (WORLD_SIZE): expected a "
               "multiple of 2")
    proc = launch([*TORCHRUN, "--nproc_per_node", "2", "--master_port", str(free_port()),
                   *_args(setup, setup / "odd.safetensors", "odd.yaml")], timeout=120, env=_env())
    assert proc.returncode != 0 and message in proc.stderr and "exitcode  : 2" in proc.stderr, proc.stderr[-3000:]
    # refused before joining the process group: the process alone exits with status 2
    env = {**_env(), "RANK": "0", "WORLD_SIZE": "2", "LOCAL_RANK": "0", "MASTER_ADDR": "127.0.0.1",
           "MASTER_PORT": str(free_port())}
    proc = subprocess.run([sys.executable, *_args(setup, setup / "odd.safetensors", "odd.yaml")],
                          capture_output=True, text=True, timeout=60, env=env)
    assert proc.returncode == 2 and message in proc.stderr, proc.stderr
    assert not (setup / "odd.safetensors").exists()


def test_residual_folds_under_several_processes_are_refused(setup):
    (setup / "folds.yaml").write_text(CONFIG + "residual_folds: 3\n")
    env = {**_env(), "RANK": "1", "WORLD_SIZE": "2", "LOCAL_RANK": "1", "MASTER_ADDR": "127.0.0.1",
           "MASTER_PORT": str(free_port())}
    proc = subprocess.run([sys.executable, *_args(setup, setup / "f.safetensors", "folds.yaml")],
                          capture_output=True, text=True, timeout=60, env=env)
    assert proc.returncode == 2, proc.stderr
    assert "error: residual_folds = 3 with 2 processes" in proc.stderr and "expected residual_folds 0" in proc.stderr


def test_partial_torchrun_environment_is_refused(setup):
    env = {**_env(), "RANK": "0"}
    env.pop("WORLD_SIZE", None), env.pop("LOCAL_RANK", None)
    proc = subprocess.run([sys.executable, *_args(setup, setup / "x.safetensors")], capture_output=True, text=True,
                          timeout=60, env=env)
    assert proc.returncode == 2 and "environment has RANK but not LOCAL_RANK, WORLD_SIZE" in proc.stderr, proc.stderr


def test_torchrun_environment_without_the_rendezvous_address_is_refused():
    env = {"RANK": "0", "WORLD_SIZE": "2", "LOCAL_RANK": "0", "MASTER_PORT": "29500"}
    with pytest.raises(ValueError, match="environment has RANK, WORLD_SIZE, LOCAL_RANK but not MASTER_ADDR: expected"):
        distributed.runtime_from_env("cpu", env)
    run = distributed.runtime_from_env("cpu", {**env, "MASTER_ADDR": "127.0.0.1"})
    assert (run.rank, run.world_size, run.backend) == (0, 2, "gloo")


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_cuda_without_cuda_is_refused(setup):
    (setup / "cuda.yaml").write_text(CONFIG + "device: cuda\n")
    proc = subprocess.run([sys.executable, *_args(setup, setup / "c.safetensors", "cuda.yaml")],
                          capture_output=True, text=True, timeout=60, env=_env())
    assert proc.returncode == 2, proc.stderr
    assert "device = 'cuda' but CUDA is not available" in proc.stderr and "expected device cpu or auto" in proc.stderr
    (setup / "gpu.yaml").write_text(CONFIG + "device: gpu\n")
    proc = subprocess.run([sys.executable, *_args(setup, setup / "c.safetensors", "gpu.yaml")],
                          capture_output=True, text=True, timeout=60, env=_env())
    assert proc.returncode == 2 and "device = 'gpu'" in proc.stderr, proc.stderr
