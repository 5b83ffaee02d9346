"""Experiment 2 — deployment-time refinement (paper appendix, figure "post-processing optimization").

A trained DeepProMP is asked to pass through N = 1, 5, 50 via-points taken from held-out
demonstrations (``refine_sets`` sets per N). :meth:`deepprompt_ros.primitive.deep_promp.DeepProMP.refine` starts either
at the model's posterior q(z | via-points) ("posterior") or at the prior N(0, I) ("prior"); the
curve is the max via-point error of the executed trajectory μ_y(μ̃, x) (rad) against the iteration
budget, mean ± standard error over the sets, log y.

How the curve is measured: ``refine`` returns no per-iteration history, so each budget m of
``scale.refine_budgets`` is a separate call with ``max_iterations=m`` (the error the solver reaches
with m iterations). refine splits its budget between Levenberg–Marquardt, a smoothing continuation
and restarts, so a larger budget can take a different path: the curve need not be monotone. If a
``RefinementResult`` carries ``error_history`` (array, shape (iterations + 1,): max via-point error of
the current iterate after each iteration, entry 0 = the initialization), one call at the largest
budget is used instead.

Units: phases in [0, 1], joints in rad; errors in rad.
"""
from __future__ import annotations

import hashlib
import pathlib
import time
from typing import Callable

import numpy as np

from deepprompt_ros.primitive.deep_promp import DeepProMP

from . import common
from .common import Scale
from .units import Unit, UnitCache, run_units

INITS = ("posterior", "prior")
TOL = 1e-6


def default_model_and_data(scale: Scale) -> tuple[DeepProMP, list[np.ndarray]]:
    """The shipped Gen3 lite reaching primitive and held-out demonstrations (a data seed it was not
    trained on), resampled on 100 phases."""
    prim = DeepProMP.from_checkpoint(str(common.MODELS / "gen3_lite_reach.safetensors"))
    demos = common.BUILTIN_TASKS["gen3_lite_reach"](scale.refine_sets, common.DATA_SEED + 1)
    return prim, [d.resampled(100) for d in demos.demos]


def error_curve(prim: DeepProMP, init, xv: np.ndarray, yv: np.ndarray, budgets) -> tuple[np.ndarray, dict]:
    """Max via-point error (rad) at the initialization and after each budget, shape (1 + len(budgets),),
    and the facts of the run at the largest budget."""
    budgets = list(budgets)
    t0 = time.perf_counter()
    res = prim.refine(init, xv, yv, max_iterations=max(budgets), tol=TOL)
    t_full = time.perf_counter() - t0
    hist = getattr(res, "error_history", None)
    if hist is not None:
        h = np.asarray(hist, dtype=np.float64)
        errs = np.array([h[min(m, h.size - 1)] for m in budgets])
    else:
        errs = np.array([prim.refine(init, xv, yv, max_iterations=m, tol=TOL).max_error if m != max(budgets)
                         else res.max_error for m in budgets])
    init_err = float(np.abs(yv - prim.mean_trajectory(init, xv)).max())
    errs = np.concatenate([[init_err], errs])  # budget 0: the initialization
    return errs, {"init_error": init_err, "final_error": res.max_error, "iterations": res.iterations,
                  "reachable": bool(res.reachable), "sample_mean_error": res.sample_mean_error,
                  "reason": res.reason, "time_s": t_full}


# The files whose code determines a unit's result (their digest is part of every unit's key).
SOURCES = ("experiments/refinement.py", "experiments/common.py", "deepprompt_ros/**/*.py")
CHECKPOINT = common.MODELS / "gen3_lite_reach.safetensors"


def _demos_digest(demos: list[np.ndarray]) -> str:
    h = hashlib.sha1()
    for y in demos:
        y = np.ascontiguousarray(y, dtype=np.float64)
        h.update(f"{y.shape}".encode())
        h.update(y.tobytes())
    return h.hexdigest()[:12]


def curve_unit(shared: dict, n: int, init_name: str, budgets: tuple[int, ...]) -> dict:
    """One unit: the error curves (``curves``: one per set, :func:`error_curve`) and facts of ``n``
    via-points from every demo of ``shared`` (``prim`` and ``demos``, or ``scale`` to load them with
    :func:`default_model_and_data` — once per process), refinement started at ``init_name``."""
    if "prim" not in shared:
        shared["prim"], shared["demos"] = default_model_and_data(shared["scale"])
    prim, demos = shared["prim"], shared["demos"]
    x = np.linspace(0.0, 1.0, demos[0].shape[0])
    curves, facts = [], []
    for i, y in enumerate(demos):
        sel = np.sort(np.random.default_rng([n, i]).choice(x.size, n, replace=False))
        xv, yv = x[sel], y[sel]
        init = prim.condition(xv, yv) if init_name == "posterior" else prim.prior()
        errs, f = error_curve(prim, init, xv, yv, budgets)
        curves.append(errs)
        facts.append(f)
    return {"curves": curves, "facts": facts}


def run(scale: Scale, out: pathlib.Path, prim: DeepProMP | None = None, demos: list[np.ndarray] | None = None,
        log: Callable[[str], None] = print, cache: UnitCache | None = None, jobs: int = 1) -> dict:
    """Experiment 2; writes ``refinement.{png,json,md}`` under ``out``. One unit per (N, init)
    (:func:`curve_unit`); with the default model and data (``prim``, ``demos`` None) finished units are
    read from ``cache`` and the others computed (``jobs`` worker processes); a given ``prim`` / ``demos``
    is computed here, uncached. The returned dict's ``units`` is the :class:`UnitReport` (not in the JSON)."""
    default = prim is None or demos is None
    if default:
        prim, demos = default_model_and_data(scale)
    x = np.linspace(0.0, 1.0, demos[0].shape[0])
    budgets = tuple(sorted(scale.refine_budgets))
    keys = [(n, init_name) for n in scale.refine_n_via for init_name in INITS]
    fixed = {"experiment": "refinement", "checkpoint": common.file_digest([CHECKPOINT]),
             "data": {"n_sets": len(demos), "digest": _demos_digest(demos)}, "budgets": list(budgets), "tol": TOL,
             **common.code_parts(SOURCES)}
    units = [Unit(f"N{n}__{init_name}", {**fixed, "n_via": n, "init": init_name}, (n, init_name, budgets),
                  cost=float(n)) for n, init_name in keys]

    def show(u: Unit, r: dict, reused: bool, wall_s: float) -> None:
        key = f"N={u.args[0]} {u.args[1]}"
        log(f"  {key:16s} max error (mean over {len(r['curves'])} sets) at budgets {(0,) + budgets}: "
            + " ".join(f"{v:.1e}" for v in np.mean(r["curves"], 0)) + ("  (reused)" if reused else ""))

    if default:
        results, report = run_units(units, curve_unit, {"scale": scale}, cache, jobs, SOURCES, show, log)
    else:
        results, report = run_units(units, curve_unit, {"prim": prim, "demos": demos}, None, 1, (), show, log)
    curves = {f"N={n} {i}": [np.asarray(c, dtype=np.float64) for c in r["curves"]] for (n, i), r in zip(keys, results)}
    facts = {f"N={n} {i}": r["facts"] for (n, i), r in zip(keys, results)}
    summary = {}
    for key, c in curves.items():
        c = np.array(c)
        f = facts[key]
        final = c[:, -1]
        summary[key] = {
            "budgets": [0, *budgets],
            "mean": c.mean(0).tolist(), "se": (c.std(0, ddof=1) / np.sqrt(len(c))).tolist() if len(c) > 1 else
            [float("nan")] * (len(budgets) + 1),
            "median": np.median(c, 0).tolist(),
            "init_error_mean": float(np.mean([v["init_error"] for v in f])),
            "final_median": float(np.median(final)),
            "fraction_within_tol": float(np.mean(final <= TOL)),
            "time_s_median": float(np.median([v["time_s"] for v in f])),
            "iterations_median": float(np.median([v["iterations"] for v in f])),
            "sample_mean_error_median": float(np.median([v["sample_mean_error"] for v in f])),
            "per_set": np.array(c).tolist(),
        }
    meta = {"scale": scale.name, "n_sets": len(demos), "n_via": list(scale.refine_n_via), "tol_rad": TOL,
            "model": prim.name, "latent_dim": prim.latent_dim, "latent_linear": int(prim.cfg.latent_linear),
            "n_joints": prim.n_joints,
            "history_from": "error_history" if hasattr(prim.refine(prim.prior(), x[:1], demos[0][:1],
                                                                     max_iterations=1), "error_history")
            else "one refine call per budget"}
    files = [plot(summary, scale.refine_n_via, out / "refinement.png")]
    files += common.write_outputs(out, "refinement", {"meta": meta, "curves": summary}, markdown(summary, meta))
    return {"meta": meta, "curves": summary, "files": [str(f) for f in files], "units": report.to_json()}


def plot(summary: dict, n_vias, path: pathlib.Path) -> pathlib.Path:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(n_vias), figsize=(4 * len(n_vias), 3.4), sharey=True)
    axes = np.atleast_1d(axes)
    for ax, n in zip(axes, n_vias):
        for init_name, color in zip(INITS, ("C2", "C0")):
            s = summary[f"N={n} {init_name}"]
            b, m, se = np.array(s["budgets"]), np.array(s["mean"]), np.nan_to_num(np.array(s["se"]))
            ax.errorbar(b, m, yerr=[np.minimum(se, m * 0.999), se], marker="o", ms=3, capsize=3, color=color,
                        label=init_name)
        ax.axhline(TOL, color="0.5", ls=":", lw=1)
        ax.set_xscale("symlog", linthresh=1.0)  # 0 = the initialization
        ax.set_xlim(0, b[-1] * 1.3)
        ax.set_yscale("log")
        ax.set_xlabel("iteration budget (0 = initialization)")
        ax.set_title(f"N = {n} via-point{'s' if n > 1 else ''}")
    axes[0].set_ylabel("max via-point error (rad)")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def markdown(summary: dict, meta: dict) -> str:
    b = summary[next(iter(summary))]["budgets"]
    show = [i for i, v in enumerate(b) if v in (0, 1, 10, b[-1])]
    header = ["N, init"] + ["at init" if b[i] == 0 else f"after {b[i]} it." for i in show] + [
        "median final", f"≤ {meta['tol_rad']:.0e}", "K-sample mean: median", "median iterations", "median time"]
    rows = []
    for key, s in summary.items():
        rows.append([key]
                    + [common.fmt_pm(s["mean"][i], s["se"][i]) for i in show]
                    + [common.fmt(s["final_median"]), f"{s['fraction_within_tol']:.0%}",
                       common.fmt(s["sample_mean_error_median"]), f"{s['iterations_median']:.0f}",
                       f"{1e3 * s['time_s_median']:.0f} ms"])
    return (f"# Deployment-time refinement — max via-point error (rad), mean ± standard error over {meta['n_sets']} "
            f"sets\n\nModel `{meta['model']}` ({meta['n_joints']} joints, latent {meta['latent_dim']}, of which "
            f"{meta['latent_linear']} the linear block); held-out demonstrations; history: "
            f"{meta['history_from']}. K-sample mean: max via-point error of the mean of the refined latent's K "
            f"sample decodings (the paper's Eq. 5 term), median over the sets.\n\n"
            + common.markdown_table(header, rows))
