"""Command line of the task datasets: ``python -m deepprompt_ros.sim.tasks.cli TASK --out DIR``.

Writes ``DIR/train``, ``DIR/val``, ``DIR/test`` (dataset folders of ``.npz`` demonstrations) and
``DIR/task.json`` (task, seed, sizes, context layout, generation time); ``--help`` lists the options.
"""
from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import sys
import time
from typing import Sequence

from deepprompt_ros.data.demonstration import DatasetError
from deepprompt_ros.sim.tasks.registry import SPLITS, TASKS, make_task

__all__ = ["main"]


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m deepprompt_ros.sim.tasks.cli",
        description="Generate a task dataset (PyBullet, scripted demonstrator) in the .npz demonstration "
                    "format: OUT/train, OUT/val, OUT/test and OUT/task.json.")
    ap.add_argument("task", help=f"task name: {' | '.join(TASKS)}")
    ap.add_argument("--out", required=True, help="output folder (created)")
    ap.add_argument("--quick", action="store_true", help="quick sizes (20/5/10 demos) instead of the full ones")
    ap.add_argument("--split", default="all", help="train | val | test | all (default: all)")
    ap.add_argument("--n", type=int, help="demonstrations per split (overrides the sizes)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--n-points", type=int, default=100, help="samples per demonstration (default 100)")
    ap.add_argument("--image-size", type=int, default=64, help="image width = height (default 64)")
    sim = ap.add_mutually_exclusive_group()
    sim.add_argument("--sim", dest="simulate", action="store_const", const=True,
                     help="record the simulated execution (default without --quick)")
    sim.add_argument("--no-sim", dest="simulate", action="store_const", const=False,
                     help="record the plan (default with --quick)")
    args = ap.parse_args(argv)
    if args.task not in TASKS:
        ap.error(f"unknown task '{args.task}'; available tasks: {', '.join(TASKS)}")
    if args.split != "all" and args.split not in SPLITS:
        ap.error(f"unknown split '{args.split}'; expected one of {', '.join(SPLITS)} or all")
    splits = SPLITS if args.split == "all" else (args.split,)
    out = pathlib.Path(args.out)
    task = TASKS[args.task]
    simulate = (not args.quick) if args.simulate is None else args.simulate
    manifest = {"task": args.task, "robot": task.robot, "description": task.description, "seed": args.seed,
                "quick": args.quick, "simulate": simulate, "n_points": args.n_points,
                "image_size": args.image_size, "n_images": task.n_images,
                "contexts": dict(task.contexts), "splits": {}}
    t_all = time.perf_counter()
    for split in splits:
        n = args.n if args.n is not None else task.size(split, args.quick)
        t0 = time.perf_counter()
        step = max(1, n // 20)

        def report(done, total, split=split, t0=t0, step=step):
            if done % step == 0 or done == total:
                el = time.perf_counter() - t0
                print(f"[{args.task}/{split}] {done}/{total} demos  {el:.1f} s  ({el / done:.3f} s/demo)",
                      file=sys.stderr, flush=True)

        try:
            ds = make_task(args.task, split, n=n, quick=args.quick, seed=args.seed, n_points=args.n_points,
                           image_size=args.image_size, simulate=simulate, progress=report)
        except (ValueError, DatasetError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        folder = ds.save(out / split)
        el = time.perf_counter() - t0
        manifest["splits"][split] = {"n": len(ds), "folder": str(folder), "seconds": round(el, 2),
                                     "seconds_per_demo": round(el / len(ds), 4)}
        print(f"[{args.task}/{split}] wrote {len(ds)} demonstrations to {folder}", file=sys.stderr, flush=True)
    manifest["seconds"] = round(time.perf_counter() - t_all, 2)
    manifest["created"] = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    out.mkdir(parents=True, exist_ok=True)
    (out / "task.json").write_text(json.dumps(manifest, indent=2) + "\n")
    print(f"[{args.task}] done in {manifest['seconds']:.1f} s; dataset in {out.resolve()} "
          f"(description: {out / 'task.json'})", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
