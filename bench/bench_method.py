"""Method benchmark: how the model family does against ProMP and the deep baselines, at the bench's size.

Usage: python bench/bench_method.py [--quick]
Prints a table (each figure with what produced it), then as the LAST line space-separated name=value pairs:

``small_data_ratio``     DeepProMP MSE / ProMP MSE, 5 random via-points per held-out demo, the small-data
                         study (experiments/small_data.py) at the bench's size: both trained on the same
                         demos (their own validation split, seed 0), DeepProMP with ``train``'s default
                         configuration (``TrainConfig()``, one torch thread), ProMP with ``ProMPModel``'s
                         defaults (its automatic selection)
``context_ratio``        DeepProMP Low Dim MSE (first point + context) / the best of ProMP and the four
                         deep baselines (deepprompt_ros.baselines.registry), the built-in
                         ``gen3_lite_reach``, every model with its defaults at the same small budget of updates
``bimodal_on_mode``      share of the shipped ``models/bimodal_sine.safetensors``'s samples on a mode when
                         conditioned on y = 0 at the zero crossings x = 0, 0.5, 1
``via_met_share``        share of random planner via-point sets (1-5 via-points inside the joint limits and
                         the demos' range ±20 % of each joint's span at that phase) met to 1e-6 rad by the
                         executed mean, through the server's default Condition path
                         (``PrimitiveServerCore.condition``) on the shipped ``models/gen3_lite_reach.safetensors``
``promp_via_met_share``  the same sets conditioned by ProMP (``ProMPModel`` defaults on that model's
                         training demos)

The measures are those of the experiments' goals (:mod:`experiments.goal_metrics`); the trainings run
in 2 worker processes (:func:`experiments.units.run_units`). ``--quick``: a smoke run at smaller sizes
and budgets (the figures are computed the same way, they measure little).
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import pathlib
import sys
import time

# Small matrices: one BLAS thread per process (the trainings run in 2 processes on 2 cores).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from deepprompt_ros.baselines.deep_promp_model import DeepProMPModel  # noqa: E402
from deepprompt_ros.baselines.promp_model import ProMPModel  # noqa: E402
from deepprompt_ros.baselines.registry import MODEL_CLASSES  # noqa: E402
from deepprompt_ros.evaluation.reconstruction import reconstruction_mse  # noqa: E402
from deepprompt_ros.training.config import TrainConfig  # noqa: E402
from experiments import common, goal_metrics  # noqa: E402
from experiments.small_data import default_data  # noqa: E402
from experiments.units import Unit, run_units  # noqa: E402


@dataclasses.dataclass(frozen=True)
class Size:
    small_task: str = "wam_reach"
    small_n_train: int = 30
    small_n_test: int = 30
    small_steps: int | None = None  # None: TrainConfig's default
    context_task: str = "gen3_lite_reach"
    context_sizes: tuple[int, int, int] = (60, 15, 30)
    context_steps: int = 1000
    via_sets: int = 100
    bimodal_samples: int = 200


FULL = Size()
QUICK = Size(small_n_train=12, small_n_test=5, small_steps=40, context_sizes=(24, 6, 8), context_steps=40,
             via_sets=12, bimodal_samples=100)
N_VIA = 5


def fit_unit(shared: dict, study: str, kind: str, cfg: TrainConfig) -> dict:
    """One training of the bench: model ``kind`` on study ``study`` ("small": 5 random via-points,
    "context": first point + context) trained with ``cfg``; its held-out MSE and what produced it."""
    data = shared[study]
    cls = {c.kind: c for c in MODEL_CLASSES}[kind]
    t0 = time.perf_counter()
    model = cls(log=lambda s: None) if cls in (ProMPModel, DeepProMPModel) else cls()
    model.fit(data["train"], cfg, data.get("val"))
    fit_s = time.perf_counter() - t0
    if study == "small":
        mse = reconstruction_mse(model, data["test"], "via_point", n_via=N_VIA, n_points=cfg.n_points)
    else:
        mse = reconstruction_mse(model, data["test"], "low_dim", n_points=cfg.n_points)
    return {"mse": mse, "fit_s": fit_s, "label": goal_metrics.model_label(model) if kind in ("deepprompt", "promp")
            else f"{cfg.steps} updates"}


def trainings(size: Size, log=print) -> dict:
    """Both studies' trainings in 2 worker processes; {(study, kind): result of :func:`fit_unit`}."""
    small_train, small_test = default_data(size.small_n_train, size.small_n_test, size.small_task)
    ctx = common.load_task(size.context_task, common.SCALES["quick"], sizes=size.context_sizes)
    shared = {"small": {"train": small_train, "test": small_test},
              "context": {"train": ctx.train, "val": ctx.val, "test": ctx.test}}
    small_cfg = TrainConfig(threads=1) if size.small_steps is None else \
        TrainConfig(threads=1, steps=size.small_steps, val_every=max(1, size.small_steps // 4))
    ctx_cfg = TrainConfig(threads=1, steps=size.context_steps, val_every=max(1, size.context_steps // 4))
    units = [Unit(f"small__{k}", {}, ("small", k, small_cfg), cost=1.0 + 3 * (k == "deepprompt"))
             for k in ("deepprompt", "promp")]
    units += [Unit(f"context__{c.kind}", {}, ("context", c.kind, ctx_cfg), cost=1.0 + (c.kind == "deepprompt"))
              for c in MODEL_CLASSES]
    results, _ = run_units(units, fit_unit, shared, None, 2, (), log=log)
    out = {u.args[:2]: r for u, r in zip(units, results)}
    out["sizes"] = {"small": (len(small_train), len(small_test)), "small_cfg": small_cfg,
                    "context": (len(ctx.train), len(ctx.val), len(ctx.test)), "context_cfg": ctx_cfg}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="smoke run at smaller sizes and budgets")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    size = QUICK if args.quick else FULL
    t0 = time.perf_counter()
    tr = trainings(size, log=lambda s: None)
    sz = tr["sizes"]

    deep, promp = tr[("small", "deepprompt")], tr[("small", "promp")]
    small_ratio = deep["mse"] / promp["mse"]

    others = {k: tr[("context", k)] for k in ("promp", "cnmp", "cnmp_indep", "vae_cnmp", "vae_cnmp_indep")}
    best = min(others, key=lambda k: others[k]["mse"])
    ctx_deep = tr[("context", "deepprompt")]
    context_ratio = ctx_deep["mse"] / others[best]["mse"]

    bim_path = ROOT / "models" / "bimodal_sine.safetensors"
    bim_model = DeepProMPModel.load(bim_path)
    modes = goal_metrics.mode_shares(bim_model, n_samples=size.bimodal_samples, n_held=3)
    bim_tc = bim_model.primitive.metadata.get("train_config", {})

    via = goal_metrics.shipped_reach_via_met(ROOT, size.via_sets)
    srv, pro = via["server"], via["promp"]
    wall = time.perf_counter() - t0

    steps = sz["small_cfg"].steps
    rows = [
        ("small_data_ratio", small_ratio,
         f"DeepProMP / ProMP held-out MSE, {N_VIA} via-points; {size.small_task}, {sz['small'][0]} demos (10 % of "
         f"them validate), {sz['small'][1]} held out; DeepProMP: TrainConfig() defaults"
         + ("" if size.small_steps is None else f" but {steps} updates") + f", seed 0 ({deep['label']}); "
         f"ProMP: ProMPModel defaults ({promp['label']})"),
        ("  small_data_deepprompt_mse", deep["mse"], "rad²"),
        ("  small_data_promp_mse", promp["mse"], "rad²"),
        ("context_ratio", context_ratio,
         f"DeepProMP Low Dim MSE / the best other ({best}); {size.context_task} {sz['context'][0]} / "
         f"{sz['context'][1]} / {sz['context'][2]} demos, every model its defaults at {size.context_steps} updates "
         f"(DeepProMP: {ctx_deep['label']}; ProMP: on the whole training split)"),
        ("  context_deepprompt_mse", ctx_deep["mse"], "rad², first point + object"),
        *((f"  context_{k}_mse", r["mse"], "rad²") for k, r in others.items()),
        ("bimodal_on_mode", modes["ambiguous"]["on_mode"],
         f"shipped models/bimodal_sine.safetensors ({bim_tc.get('steps', '?')} updates, objective "
         f"{bim_tc.get('objective', '?')}, {goal_metrics.model_label(bim_model).split(', objective')[0]}), "
         f"{size.bimodal_samples} samples, y = 0 at x = 0, 0.5, 1; target >= 0.9"),
        ("  bimodal_on_pos", modes["ambiguous"]["on_pos"], "the + mode alone (both modes present: each >= 0.1)"),
        ("  bimodal_on_neg", modes["ambiguous"]["on_neg"], "the − mode alone"),
        ("  bimodal_right_mode_3", modes["3 via-points"], "3 distinguishing via-points: on the demo's mode, "
         "target >= 0.98"),
        ("via_met_share", srv["share"],
         f"{srv['n']} random sets, server default Condition (refine={srv['refine']}) on the shipped "
         f"models/gen3_lite_reach.safetensors ({via['model']['steps']} updates, latent_linear "
         f"{via['model']['latent_linear']}); target 1.0"),
        ("  via_met_median_err_rad", srv["median_error"], f"median max via-point error; {len(srv['refused'])} "
         "requests refused"),
        ("  via_met_share_other_refine", via["server_other_refine"]["share"],
         f"the same requests with refine={via['server_other_refine']['refine']} (not the server's default)"),
        ("  via_met_other_refine_median_err_rad", via["server_other_refine"]["median_error"], "its median max error"),
        ("promp_via_met_share", pro["share"], f"ProMP on the same sets ({via['promp_label']}, fitted on the model's "
         f"{via['n_train_demos']} training demos)"),
        ("  promp_via_met_median_err_rad", pro["median_error"], "median max via-point error"),
        ("  wall_s", wall, "this benchmark, 2 worker processes for the trainings"),
    ]
    print(f"{'metric':38s} {'value':>12s}  what produced it")
    for name, val, note in rows:
        print(f"{name:38s} {val:12.4g}  {note}")
    last = ("small_data_ratio", "context_ratio", "bimodal_on_mode", "via_met_share", "promp_via_met_share")
    print(" ".join(f"{n}={v:.6g}" for n, v, _ in rows if n in last))
    return 0


if __name__ == "__main__":
    sys.exit(main())
