"""One data-parallel training process for the tests (launched by torchrun, or alone for one process):
trains on the demonstrations of DATA (the validation split fixed, seed 0) with seed SEED for STEPS
updates, validating once at the end, and writes this process's final weights and the validation
MSE to OUTDIR/rank<RANK>.pt.

Usage: ddp_worker.py DATA OUTDIR SEED STEPS THREADS
"""
import pathlib
import sys

import torch

from deepprompt_ros.data.demo_dataset import load_dataset
from deepprompt_ros.training import distributed
from deepprompt_ros.training.config import TrainConfig
from deepprompt_ros.training.loop import train


def main(data, outdir, seed, steps, threads):
    ds = load_dataset(data)
    train_ds, val_ds = ds.split(max(1, len(ds) // 10), seed=0)
    cfg = TrainConfig(steps=int(steps), val_every=int(steps), hidden=32, latent_dim=4, n_points=30,
                      threads=int(threads), auto_select=False, batch_size=16, seed=int(seed), device="cpu")
    run = distributed.runtime_from_env(cfg.device)
    distributed.init(run)
    try:
        net, _, hist = train(train_ds, cfg, log=lambda s: None, val_ds=val_ds, run=run)
    finally:
        distributed.shutdown(run)
    torch.save({"state": net.state_dict(), "history": hist, "world_size": run.world_size, "backend": run.backend},
               pathlib.Path(outdir) / f"rank{run.rank}.pt")


if __name__ == "__main__":
    main(*sys.argv[1:])
