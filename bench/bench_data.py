"""Datasets larger than memory: the peak resident memory of a training on a sharded dataset of
1 000 and of 10 000 generated demonstrations (5 images of 64 x 64 each, the image tasks' size) and
their ratio, and the samples/s of both.

Each dataset is generated one demonstration at a time (``data.synthetic.iter_image_reach``) into a
temporary folder as shards (``data.sharded.write_shards``) and deleted afterwards. Each training runs
in its own process (``--train DIR``): the same fixed number of updates, ``data_workers`` 2 worker
processes, 1 torch thread, the validation at the end on the same 100 held-out demos; its peak
resident memory is measured by the training process itself (:func:`peak_rss_mb`: the high-water mark of
its own address space and the ``ru_maxrss`` of its worker processes, the larger). Not ``ru_maxrss`` of
the training process seen from here: Linux keeps it across fork and exec, so it would start at this
process's resident memory. Beside it, the same run: the 1 000 demos trained from memory
(``train_peak_rss_mb_1k_inmemory``, the folder format's path, which holds every image as floats).

Usage: python bench/bench_data.py [--quick]   (--quick: 200 and 2 000 demos, fewer updates)
Prints a table, then as the LAST line space-separated name=value pairs.
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: The training of every run (auto_select off: a fixed linear part, so that the runs differ only in
#: the dataset's size; the PCA initialization reads select_max_demos demos).
TRAIN = {"auto_select": False, "decoder_basis": 20, "basis_init": "pca", "basis_lr_scale": 0.0,
         "latent_linear": 16, "latent_dim": 24, "batch_size": 16, "threads": 1, "data_workers": 2,
         "n_val": 100, "val_max_demos": 100}
FULL = {"sizes": (1000, 10000), "steps": 300}
QUICK = {"sizes": (200, 2000), "steps": 20}
N_IMAGES, IMAGE_SIZE = 5, 64


def train_child(folder: str, steps: int, in_memory: bool) -> int:
    """The training process: train on ``folder`` and print its samples/s as JSON."""
    import dataclasses

    from deepprompt_ros.data.demo_dataset import DemoDataset
    from deepprompt_ros.data.sharded import ShardedDataset
    from deepprompt_ros.training.config import TrainConfig
    from deepprompt_ros.training.loop import train
    from deepprompt_ros.training.streaming import train_sharded

    cfg = TrainConfig.from_dict({**TRAIN, "steps": steps, "val_every": steps})
    ds, trainer = ShardedDataset(folder), train_sharded
    if in_memory:
        ds, trainer = DemoDataset(tuple(ds.read(range(len(ds)))), folder), train
        cfg = dataclasses.replace(cfg, data_workers=0)
    t0 = time.perf_counter()
    _, _, hist = trainer(ds, cfg, log=lambda s: None)
    wall = time.perf_counter() - t0
    print(json.dumps({"samples_per_s": hist[-1]["samples_per_s"], "wall_s": wall, "peak_rss_mb": peak_rss_mb()}))
    return 0


def peak_rss_mb() -> float:
    """The peak resident memory (MB) of this process and its ended worker processes: ``VmHWM`` of
    /proc/self/status (the high-water mark of this address space, which exec started afresh) and
    ``ru_maxrss`` of ``RUSAGE_CHILDREN`` (the largest of the workers it waited for, each counting the pages
    it shares with this process), the larger (proc(5), getrusage(2))."""
    import gc
    import re
    import resource

    gc.collect()  # the DataLoader's workers ended and waited for
    own = int(re.search(r"^VmHWM:\s+(\d+) kB", pathlib.Path("/proc/self/status").read_text(), re.M).group(1))
    return max(own, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss) / 1024.0  # kB


def run_training(folder: pathlib.Path, steps: int, in_memory: bool = False) -> dict:
    """Train in a child process; its result (samples/s, peak RSS in MB over it and its worker processes)."""
    cmd = [sys.executable, __file__, "--train", str(folder), "--steps", str(steps)]
    cmd += ["--in-memory"] if in_memory else []
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"training on {folder} failed (exit {proc.returncode}): {proc.stdout[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def generate(folder: pathlib.Path, n: int) -> float:
    """Write ``n`` generated demos as shards; returns the seconds it took."""
    from deepprompt_ros.data.sharded import write_shards
    from deepprompt_ros.data.synthetic import iter_image_reach

    t0 = time.perf_counter()
    write_shards(iter_image_reach(n, seed=0, n_images=N_IMAGES, image_size=IMAGE_SIZE), folder)
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--train", help=argparse.SUPPRESS)
    ap.add_argument("--steps", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--in-memory", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.train:
        return train_child(args.train, args.steps, args.in_memory)
    plan = QUICK if args.quick else FULL
    small, large = plan["sizes"]
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="bench_data_"))
    try:
        rows = {}
        for label, n in (("small", small), ("large", large)):
            folder = tmp / f"demos_{n}"
            gen_s = generate(folder, n)
            disk = sum(f.stat().st_size for f in folder.rglob("*") if f.is_file()) / 2**20
            rows[label] = {"n": n, "gen_s": gen_s, "disk_mb": disk, **run_training(folder, plan["steps"])}
            if label == "small":
                rows["memory"] = run_training(folder, plan["steps"], in_memory=True)
            shutil.rmtree(folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    s, l_, m = rows["small"], rows["large"], rows["memory"]
    figures = [
        ("train_peak_rss_mb_1k", s["peak_rss_mb"], f"{s['n']} demos ({s['disk_mb']:.0f} MB of shards)"),
        ("train_peak_rss_mb_10k", l_["peak_rss_mb"], f"{l_['n']} demos ({l_['disk_mb']:.0f} MB of shards)"),
        ("train_rss_ratio", l_["peak_rss_mb"] / s["peak_rss_mb"], "target <= 1.3"),
        ("train_samples_per_s_1k", s["samples_per_s"], f"{plan['steps']} updates of 16, 2 workers, 1 thread"),
        ("train_samples_per_s_10k", l_["samples_per_s"], "same"),
        ("train_peak_rss_mb_1k_inmemory", m["peak_rss_mb"], f"the {s['n']} demos trained from memory"),
        ("train_samples_per_s_1k_inmemory", m["samples_per_s"], "same"),
        ("shard_write_demos_per_s", l_["n"] / l_["gen_s"], "generation + writing of the larger set"),
    ]
    print(f"{'metric':32s} {'value':>12s}  note")
    for name, val, note in figures:
        print(f"{name:32s} {val:12.4g}  {note}")
    print(" ".join(f"{n}={v:.6g}" for n, v, _ in figures))
    return 0


if __name__ == "__main__":
    sys.exit(main())
