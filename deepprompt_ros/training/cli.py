"""The ``train`` command: train a DeepProMP on demonstrations and write its checkpoint.

Usage::

    train --data DATASET_DIR --config config/train_gen3_lite_reach.yaml --out models/NAME.safetensors
    python -m deepprompt_ros.training.cli --builtin bimodal_sine --config config/train_bimodal_sine.yaml --out ...
    torchrun --nproc_per_node 2 -m deepprompt_ros.training.cli --data DATASET_DIR --out ...   # data-parallel
    train --data DATASET_DIR --out models/NAME.safetensors --resume   # continue from models/NAME.resume.pt

Without a configuration every default applies, ``auto_select`` among them: the decoder's linear part
and its via-point noise are chosen by cross-validation on the training demonstrations and the MLP
residual is kept or dropped on the validation ones (:mod:`deepprompt_ros.training.selection`); the
choices are printed and stored in the checkpoint. The last line printed is a JSON summary (``out``,
``best_val_mse_rad2``, ``selected``, ``samples_per_s`` of the last training, ``device``, ``backend``,
``world_size``). The training YAML files of the shipped models are
``config/train_*.yaml``. ``--data`` takes a folder of demonstrations, or a sharded dataset
(a folder with ``index.json``: :mod:`deepprompt_ros.data.sharded`), which is read lazily and
trained with bounded memory (:mod:`deepprompt_ros.training.streaming`; on the CPU, without
``--resume``). Exit status 2 with a
message (``error: ...``) naming every refused key or value when the configuration or the data
are refused.

Launched by ``torchrun`` the same command trains data-parallel
(:mod:`deepprompt_ros.training.distributed`): process 0 prints, validates and writes the checkpoint.
Every run writes ``OUT.resume.pt`` beside ``--out`` every ``checkpoint_every`` updates; ``--resume``
continues an interrupted run from it (:mod:`deepprompt_ros.training.resume`).
"""
from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import pathlib
import sys

from deepprompt_ros.data.builtin import builtin_dataset
from deepprompt_ros.data.demo_dataset import load_dataset
from deepprompt_ros.data.demonstration import DatasetError
from deepprompt_ros.data.sharded import ShardedDataset, is_sharded
from deepprompt_ros.training import distributed
from deepprompt_ros.training.config import TrainConfig
from deepprompt_ros.training.loop import train
from deepprompt_ros.training.streaming import train_sharded

__all__ = ["main"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="train", description="Train a DeepProMP on demonstrations.")
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--data", help="dataset folder of .npz/.csv demonstrations (see deepprompt_ros.data.demo_dataset)"
                     ", or a sharded dataset (a folder with index.json, deepprompt_ros.data.sharded), read lazily")
    src.add_argument("--builtin", help="built-in generated dataset: bimodal_sine | rhythmic_shake | wam_shake | "
                     "gen3_lite_reach, or a PyBullet task (deepprompt_ros.sim.tasks; full sets take minutes to "
                     "generate): "
                     "reach | close_box | pour | kinova_pick_place")
    ap.add_argument("--config", help="training YAML (keys of TrainConfig); defaults if omitted")
    ap.add_argument("--out", required=True, help="output checkpoint path (.safetensors)")
    ap.add_argument("--steps", type=int, help="override the number of updates")
    ap.add_argument("--resume", action="store_true", help="continue from OUT.resume.pt, the resume file an "
                    "interrupted run with the same --out, configuration and data wrote")
    args = ap.parse_args(argv)
    try:
        cfg = TrainConfig.from_yaml(args.config) if args.config else TrainConfig()
        if args.steps is not None:
            cfg = dataclasses.replace(cfg, steps=args.steps)
        run = distributed.runtime_from_env(cfg.device)
        run.check(cfg)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    distributed.init(run)
    try:
        status = _train(args, cfg, run)
        distributed.finish(run)
        return status
    finally:
        distributed.shutdown(run)


def _train(args, cfg: TrainConfig, run: distributed.Runtime) -> int:
    say = print if run.is_main else (lambda *a, **k: None)
    try:
        if args.data:
            ds = ShardedDataset(args.data) if is_sharded(args.data) else load_dataset(args.data)
        else:
            ds = builtin_dataset(args.builtin, seed=cfg.seed)
        sharded = isinstance(ds, ShardedDataset)
        if sharded and args.resume:
            raise ValueError(f"--resume: the sharded dataset '{args.data}' trains without a resume file: expected a "
                             "run without --resume, or a folder of demonstrations")
    except (ValueError, DatasetError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    say(f"training on {len(ds)} demonstrations from {ds.source}: joints {list(ds.joint_names)}, "
        f"phase {ds.phase_type}, contexts {ds.context_dims or 'none'}, images {ds.image_shape or 'none'}")
    say(f"{run.label()}, {cfg.batch_size // run.world_size} of the batch's {cfg.batch_size} demonstrations per "
        f"process, {cfg.threads} thread(s) each")
    info = {}
    try:
        trainer = train_sharded if sharded else functools.partial(train, resume=args.resume)
        _, _, hist = trainer(ds, cfg, out_path=args.out, info=info, log=say, run=run)
    except (ValueError, DatasetError) as exc:  # data the configuration cannot train on, a refused resume file
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not run.is_main:
        return 0
    best = min(h["val"]["mean"] for h in hist)
    print(f"best validation MSE {best:.3e} rad²; checkpoint written to {pathlib.Path(args.out).resolve()}")
    trained = info["train_config"]
    chosen = {k: trained[k] for k in ("decoder_basis", "latent_linear", "latent_dim", "basis_cov_reg", "linear_modes",
                                      "basis_cov_reg_units", "via_noise", "mode_noise", "residual_scale")} if cfg.auto_select else {}
    print(json.dumps({"out": str(pathlib.Path(args.out).resolve()), "best_val_mse_rad2": best, "selected": chosen,
                      "samples_per_s": hist[-1]["samples_per_s"], "device": str(run.device), "backend": run.backend,
                      "world_size": run.world_size}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
