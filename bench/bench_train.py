"""Training throughput data-parallel against one process: the same `train` command, data and
configuration run as 2 processes x 1 thread under torchrun (gloo, DistributedDataParallel) and as
1 process x 2 threads, one after the other in the same run; 1 process x 1 thread beside them shows
what the threads of one process give on this machine.

Usage: python bench/bench_train.py [--quick]
Prints a table, then as the LAST line space-separated name=value pairs:
train_ddp_speedup (two processes' samples/s over one process's), train_ddp_samples_per_s,
train_single_samples_per_s, train_single_1t_samples_per_s, train_ddp_over_1t (two processes' samples/s
over one single-threaded process's).
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import socket
import subprocess
import sys
import tempfile

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from deepprompt_ros.data.synthetic import bimodal_sine  # noqa: E402

#: the training of both runs (train's defaults otherwise: hidden 128, latent 16, batch 16); the model
#: selection is off so that the runs time the training updates alone
CONFIG = "auto_select: false\nval_every: {steps}\nsteps: {steps}\nthreads: {threads}\ndevice: cpu\n"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_train(work: pathlib.Path, name: str, steps: int, threads: int, processes: int) -> dict:
    """One `train` run; its JSON summary (``samples_per_s``: trajectories per second of the update loop)."""
    cfg = work / f"{name}.yaml"
    cfg.write_text(CONFIG.format(steps=steps, threads=threads))
    head = ([sys.executable, "-m", "torch.distributed.run", "--nnodes", "1", "--nproc_per_node", str(processes),
             "--master_addr", "127.0.0.1", "--master_port", str(free_port())] if processes > 1
            else [sys.executable])
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([*head, "-m", "deepprompt_ros.training.cli", "--data", str(work / "data"), "--config",
                           str(cfg), "--out", str(work / f"{name}.safetensors")],
                          capture_output=True, text=True, env=env, timeout=3600)
    if proc.returncode != 0:
        # a training process's own message comes first; torchrun's summary of the failure last
        err = proc.stderr if len(proc.stderr) <= 4000 else f"{proc.stderr[:2000]}\n[...]\n{proc.stderr[-2000:]}"
        raise RuntimeError(f"{name} failed ({proc.returncode}): {err}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="few updates (smoke run)")
    args = ap.parse_args()
    steps = 40 if args.quick else 1000
    with tempfile.TemporaryDirectory() as tmp:
        work = pathlib.Path(tmp)
        bimodal_sine(100, seed=0).save(work / "data")
        single = run_train(work, "single", steps, threads=2, processes=1)
        ddp = run_train(work, "ddp", steps, threads=1, processes=2)
        one_thread = run_train(work, "single_1t", steps, threads=1, processes=1)
    assert (single["world_size"], ddp["world_size"], ddp["backend"]) == (1, 2, "gloo"), (single, ddp)
    speedup = ddp["samples_per_s"] / single["samples_per_s"]
    rows = [
        ("train_single_samples_per_s", single["samples_per_s"], f"1 process x 2 threads, {steps} updates of batch "
         "16 on 100 bimodal-sine demos"),
        ("train_ddp_samples_per_s", ddp["samples_per_s"], "2 processes x 1 thread under torchrun (gloo), same data "
         "and configuration, 8 demos per process and update"),
        ("train_ddp_speedup", speedup, "ddp / single"),
        ("train_single_1t_samples_per_s", one_thread["samples_per_s"], "1 process x 1 thread, same data and "
         "configuration"),
        ("train_ddp_over_1t", ddp["samples_per_s"] / one_thread["samples_per_s"], "ddp / single_1t"),
    ]
    for name, value, what in rows:
        print(f"{name:30s} {value:10.3f}  {what}")
    print(" ".join(f"{name}={value:.4g}" for name, value, _ in rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
