"""Reproduce the paper's experiments: one command, quick and full modes.

Usage::

    python experiments/run.py [--quick | --medium | --full] [--only NAME ...] [--out DIR] [--tasks TASK ...]
                              [--config TRAIN.yaml] [--jobs N] [--fresh] [--data-cache DIR]

``--quick`` (default) is a smoke-sized run (≲ 2 min on 2 cores, built-in data only) written to
``--out`` (default ``$TMPDIR/deepprompt_experiments_quick``); ``--medium`` is the run documented in
EXPERIMENTS.md (PyBullet tasks at reduced sizes) and ``--full`` a larger one closer to the paper,
both written to ``docs/experiments/`` unless ``--out`` is given. Experiments (``--only`` takes these
names):

``reconstruction``  held-out reconstruction MSE of the six models per conditioning, radar plots
``refinement``      deployment-time refinement error vs iterations, posterior vs prior init
``rhythmic``        learned cyclic motion vs the demonstration, continuity at the seam
``small_data``      ~30 demos of a 7-joint task: DeepProMP (± refinement) vs ProMP
``bimodal``         bimodal sine: 3 / many / conflicting via-points
``goals``           one table per goal of the model family (via-points vs ProMP, context vs every
                    model, modes, samples, planner via-points, uncertainty, ablation and the paper's
                    objective); reads and adds to the reconstruction experiment's units

Each experiment writes PNG figures and ``<name>.md`` / ``<name>.json`` tables; ``timings.json`` has
the wall time of each. One torch / BLAS thread per process (the machine is shared).

Resuming: the independent units of the costly experiments (reconstruction: task × model × seed;
refinement: N × initialization; small data: seed) are written as they finish to
``<out>/units/<experiment>/<unit>__<key>.json`` (``key``: a hash of everything that determines the
unit's result — configuration, data, the sources that compute it; :mod:`experiments.units`). The
same command run again reads the finished units and computes only the others, so a stopped run
continues where it was stopped; ``--fresh`` computes every unit again. ``--jobs N`` computes N units
at a time in worker processes (same results as ``--jobs 1``). Generated PyBullet task data are kept in
``--data-cache`` (default ``$DEEPPROMPT_DATA_CACHE``, else ``<out>/data_cache``).
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse  # noqa: E402
import importlib  # noqa: E402
import json  # noqa: E402
import pathlib  # noqa: E402
import signal  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import torch  # noqa: E402

from experiments import common  # noqa: E402
from experiments.common import SCALES, Scale, base_train_config  # noqa: E402
from experiments.units import UnitCache, UnitReport  # noqa: E402

EXPERIMENTS = ("reconstruction", "refinement", "rhythmic", "small_data", "bimodal", "goals")
UNIT_EXPERIMENTS = ("reconstruction", "refinement", "small_data", "goals")  # those whose run() takes a unit cache and jobs
#: experiments whose units are another's: goals reads and adds to the reconstruction units
SHARED_UNITS = {"goals": "reconstruction"}


def run_all(scale: Scale, out: pathlib.Path, only=None, tasks=None, config=None, log=print, jobs: int = 1,
            fresh: bool = False, data_cache: str | pathlib.Path | None = None) -> dict:
    """Run the experiments ``only`` (default all) at ``scale``; returns {name: result} and writes
    ``timings.json`` under ``out``. Finished units are read from / written to ``<out>/units`` (``fresh``:
    none read); ``jobs`` worker processes compute units; generated task data are kept in
    ``data_cache`` (default ``$DEEPPROMPT_DATA_CACHE``, else ``<out>/data_cache``)."""
    torch.set_num_threads(1)
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    names = list(only or EXPERIMENTS)
    bad = sorted(set(names) - set(EXPERIMENTS))
    if bad:
        raise ValueError(f"unknown experiments {bad}; expected names from {list(EXPERIMENTS)}")
    if jobs < 1:
        raise ValueError(f"--jobs must be >= 1, got {jobs}")
    cache = UnitCache(out / "units", fresh=fresh)
    results, timings, units = {}, {}, {}
    t_all = time.perf_counter()
    load0 = os.getloadavg()[0]
    common.set_data_cache_dir(data_cache or common.env_data_cache_dir() or out / "data_cache")
    try:
        for name in names:
            mod = importlib.import_module(f"experiments.{name}")
            log(f"== {name} ({scale.name}) ==")
            t0 = time.perf_counter()
            kw = dict(cache=cache.sub(SHARED_UNITS.get(name, name)), jobs=jobs) if name in UNIT_EXPERIMENTS else {}
            if name in ("reconstruction", "goals"):
                results[name] = mod.run(scale, out, tasks=tasks, base=base_train_config(config), log=log, **kw)
            elif name == "small_data":
                results[name] = mod.run(scale, out, train_config=base_train_config(config), log=log, **kw)
            else:
                results[name] = mod.run(scale, out, log=log, **kw)
            timings[name] = time.perf_counter() - t0
            if "units" in results[name]:
                units[name] = results[name]["units"]
            log(f"== {name}: {timings[name]:.1f} s wall time ==")
    finally:
        common.set_data_cache_dir(None)
    timings["total"] = time.perf_counter() - t_all
    total = UnitReport()
    for u in units.values():
        total = total.add(UnitReport(**u))
    info = {"scale": scale.name, "wall_time_s": timings, "load_average_1min": {"start": load0,
                                                                               "end": os.getloadavg()[0]},
            "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(), "jobs": jobs,
            # per experiment: units reused / computed by this invocation, the summed wall time of every
            # unit of the results (compute_s, whichever invocation computed it) and of those computed now
            "units": units, "unit_compute_s": {**{k: v["compute_s"] for k, v in units.items()},
                                               "total": total.compute_s}}
    (out / "timings.json").write_text(json.dumps(info, indent=1) + "\n")
    log("wall time: " + ", ".join(f"{k} {v:.1f} s" for k, v in timings.items()))
    if units:
        log(f"units: {total.reused} reused, {total.computed} computed; summed unit compute time "
            f"{total.compute_s:.1f} s (of which computed now {total.computed_s:.1f} s)")
    return results


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="experiments/run.py", description=__doc__.split("\n\n")[0])
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_const", const="quick", dest="scale", help="smoke-sized run (default)")
    mode.add_argument("--medium", action="store_const", const="medium", dest="scale",
                      help="the run documented in EXPERIMENTS.md (PyBullet tasks at reduced sizes)")
    mode.add_argument("--full", action="store_const", const="full", dest="scale", help="closer to the paper's sizes")
    mode.add_argument("--scale", choices=sorted(SCALES), help=argparse.SUPPRESS)  # 'tiny' for the test suite
    ap.add_argument("--only", nargs="+", choices=EXPERIMENTS, metavar="NAME", help=f"subset of {list(EXPERIMENTS)}")
    ap.add_argument("--out", help="output folder (default: docs/experiments for --medium / --full, a temp folder "
                    "for --quick)")
    ap.add_argument("--tasks", nargs="+", help="reconstruction tasks (default: gen3_lite_reach for --quick; else "
                    "reach close_box pour kinova_pick_place (if deepprompt_ros/sim/tasks/registry.py exists) gen3_lite_reach "
                    "bimodal_sine)")
    ap.add_argument("--config", help="TrainConfig YAML for the deep models (default config/train_gen3_lite_reach.yaml)")
    ap.add_argument("--jobs", type=int, default=1, metavar="N",
                    help="compute N independent units at a time in worker processes, one thread each (default 1)")
    ap.add_argument("--fresh", action="store_true",
                    help="compute every unit again instead of reading the finished ones from <out>/units")
    ap.add_argument("--data-cache", metavar="DIR", help="folder of the generated PyBullet task data (default "
                    "$DEEPPROMPT_DATA_CACHE, else <out>/data_cache)")
    args = ap.parse_args(argv)
    scale = SCALES[args.scale or "quick"]
    if args.out:
        out = pathlib.Path(args.out)
    elif scale.name in ("medium", "full"):
        out = ROOT / "docs" / "experiments"
    else:
        out = pathlib.Path(tempfile.gettempdir()) / "deepprompt_experiments_quick"
    # SIGTERM (kill PID) ends the run like Ctrl-C: the worker processes are stopped too; finished units stay
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
    try:
        run_all(scale, out, args.only, args.tasks, args.config, jobs=args.jobs, fresh=args.fresh,
                data_cache=args.data_cache)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"outputs in {out.resolve()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
