"""Why DeepProMP's context conditioning trails the Indep baselines (EXPERIMENTS.md §1): one trained
model, the paper's "first point + context" conditioning taken apart.

Usage::

    python experiments/context_ablation.py TASK [--steps 2000] [--seed 0] [--set FIELD=VALUE ...]
                                          [--data-cache DIR] [--out FILE.json]

Trains DeepProMP on the ``--full`` split of TASK (200 / 50 / 100 demos; PyBullet tasks are generated
into the data cache on first use, ~15-45 s each) with the experiments' training configuration
(``experiments.common.train_config``; ``--set`` overrides TrainConfig fields, e.g.
``--set p_low_info=0.3 --set low_info_fraction=0.05``) and prints, as JSON, the held-out MSE (rad²,
100 phases, conditioned mean) for: first point + context (the paper's Low Dim), context alone, first
point alone, first point with importance weight 0.1, context with weight 10, nothing (the prior),
the whole trajectory and 5 random via-points
(``deepprompt_ros.evaluation.reconstruction.reconstruction_mse``), Image and Image+Low where the task has images — and the mean posterior variance of z for one test demo given
the first point, the context, and both (the prior's is 1).
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import pathlib  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import torch  # noqa: E402
import yaml  # noqa: E402

from experiments import common  # noqa: E402
from deepprompt_ros.baselines.deep_promp_model import DeepProMPModel  # noqa: E402
from deepprompt_ros.evaluation.reconstruction import reconstruction_mse  # noqa: E402


def ablation(task: str, steps: int = 2000, seed: int = 0, overrides: dict | None = None) -> dict:
    """The MSEs and posterior variances described in the module docstring, as a dict."""
    torch.set_num_threads(1)
    data = common.load_task(task, common.SCALES["full"])
    cfg = common.train_config(common.base_train_config(), steps, max(steps // 4, 1), seed, task)
    if overrides:
        cfg = dataclasses.replace(cfg, **overrides)
    t0 = time.perf_counter()
    model = DeepProMPModel().fit(data.train, cfg, data.val)
    fit_s = time.perf_counter() - t0
    p = model.primitive
    x = np.linspace(0.0, 1.0, 100)

    def ctx(demo):
        return {k: np.atleast_2d(v) for k, v in demo.contexts.items()}

    def mse(latent_of):
        errs = []
        for demo in data.test.demos:
            y = demo.resampled(100)
            errs.append(float(((p.mean_trajectory(latent_of(demo, y), x) - y) ** 2).mean()))
        return float(np.mean(errs))

    out = {
        "first point + context (paper Low Dim)": mse(lambda d, y: p.condition(x[:1], y[:1], contexts=ctx(d))),
        "context alone": mse(lambda d, y: p.condition(contexts=ctx(d))),
        "first point alone": mse(lambda d, y: p.condition(x[:1], y[:1])),
        "first point (weight 0.1) + context": mse(lambda d, y: p.condition(
            x[:1], y[:1], via_weights=np.array([0.1]), contexts=ctx(d))),
        "first point + context (weight 10)": mse(lambda d, y: p.condition(
            x[:1], y[:1], contexts=ctx(d), context_weights={k: [10.0] for k in d.contexts})),
        "nothing (prior)": mse(lambda d, y: p.condition()),
        "whole trajectory (Via Point)": reconstruction_mse(model, data.test, "via_point"),
        "5 via-points": reconstruction_mse(model, data.test, "via_point", n_via=5),
    }
    if data.test.image_shape:
        out["Image"] = reconstruction_mse(model, data.test, "image")
        out["Image+Low"] = reconstruction_mse(model, data.test, "image+low")
    d0 = data.test.demos[0]
    y0 = d0.resampled(100)
    var = {"prior": 1.0, "first point": float(p.condition(x[:1], y0[:1]).var.mean()),
           "context": float(p.condition(contexts=ctx(d0)).var.mean()),
           "first point + context": float(p.condition(x[:1], y0[:1], contexts=ctx(d0)).var.mean())}
    return {"task": task, "steps": steps, "seed": seed, "overrides": overrides or {}, "fit_s": round(fit_s, 1),
            "sizes": [len(data.train), len(data.val), len(data.test)], "mse": out, "mean_posterior_var_z": var}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="experiments/context_ablation.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("task", help=f"a task of experiments.common (e.g. gen3_lite_reach, {', '.join(common.PYBULLET_TASKS)})")
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="TrainConfig override")
    ap.add_argument("--data-cache", help="folder of generated task data (default $DEEPPROMPT_DATA_CACHE, else a temp folder)")
    ap.add_argument("--out", help="also write the JSON here")
    args = ap.parse_args(argv)
    overrides = {}
    for item in args.set:
        if "=" not in item:
            print(f"error: --set {item!r}: expected FIELD=VALUE", file=sys.stderr)
            return 2
        k, v = item.split("=", 1)
        overrides[k] = yaml.safe_load(v)
    if args.data_cache:
        os.environ["DEEPPROMPT_DATA_CACHE"] = args.data_cache
    try:
        res = ablation(args.task, args.steps, args.seed, overrides)
    except (ValueError, TypeError, KeyError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    text = json.dumps(res, indent=1)
    print(text)
    if args.out:
        pathlib.Path(args.out).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
