"""Experiment 1 — reconstruction of held-out demonstrations (paper Sec. IV, radar-plot figure).

For every task, model (:data:`deepprompt_ros.baselines.registry.MODEL_CLASSES`) and seed: train on the task's training
demonstrations (best validation weights kept), then reconstruct each test demonstration from

``via_point``   the full trajectory as via-points (the paper's "Via Point"),
``image``       the first point + the demo's images,
``low_dim``     the first point + the low-dimensional contexts,
``image+low``   the first point + both,
``aggregate``   the mean of the above that the model and the data support,

(the first point is "the initial robot position included with each context", as in the paper), with
:func:`deepprompt_ros.evaluation.reconstruction.reconstruction_mse` (decoded mean vs demo on 100
phases, rad²). An extra
column, ``via_5`` (5 random via-points per demo, the same for every model), is not in the paper and
not in the aggregate: it is the deployment case the models were trained for.

ProMP is deterministic: its "seeds" are bootstrap resamples of the training set (the paper
bootstraps ProMP). ProMP takes no images, so its aggregate averages fewer conditionings.

Each (task, model, seed) is a unit (:func:`fit_unit`, :mod:`experiments.units`): stored when it is
done, read back by the next run with the same key (:func:`task_units`), computed in worker processes
with ``jobs`` > 1. A DeepProMP unit also measures the goals of :mod:`experiments.goal_metrics` on its
model and on its ablation, a ``promp_full`` unit on its ProMP; the goals experiment
(:mod:`experiments.goals`) adds the :data:`VARIANTS` and reads the same units.
"""
from __future__ import annotations

import dataclasses
import pathlib
import time
from typing import Callable, Mapping, Sequence

import numpy as np

from deepprompt_ros.baselines.deep_promp_model import DeepProMPModel
from deepprompt_ros.baselines.promp_model import ProMPModel
from deepprompt_ros.baselines.registry import MODEL_CLASSES
from deepprompt_ros.evaluation.reconstruction import available_conditionings, reconstruction_mse
from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.training.config import TrainConfig

from . import common, goal_metrics
from .common import Scale, TaskData
from .units import Unit, UnitCache, UnitReport, run_units

CONDITIONING_LABELS = {"via_point": "Via Point", "image": "Image", "low_dim": "Low Dim", "image+low": "Image+Low",
                       "aggregate": "Aggregate", "via_5": "5 via-points"}
PAPER_CONDITIONINGS = ("via_point", "image", "low_dim", "image+low", "aggregate")
MODEL_LABELS = {"deepprompt": "DeepProMP", "promp": "ProMP", "cnmp": "CNMP", "vae_cnmp": "VAE-CNMP",
                "cnmp_indep": "CNMP (Indep)", "vae_cnmp_indep": "VAE-CNMP (Indep)",
                "deepprompt_np": "DeepProMP, objective: np", "promp_full": "ProMP (whole training split)"}
N_VIA_EXTRA = 5
#: Models that are not in the registry's list, by kind: (class, changes of the training config,
#: ProMP on bootstrap resamples). ``deepprompt_np``: DeepProMP trained with the Neural-Process
#: objective (``train``'s default is the paper's); ``promp_full``: ProMP fitted on the whole training
#: split (its seed only moves the folds of its cross-validation), the comparison of the goals.
VARIANTS = {"deepprompt_np": (DeepProMPModel, {"objective": "np"}), "promp_full": (ProMPModel, {})}
#: The kinds whose units measure the goals (:func:`goal_metrics.measure`); a DeepProMP unit's ablation too.
GOAL_KINDS = ("deepprompt", "deepprompt_np", "promp_full")


def bootstrap(ds: DemoDataset, seed: int) -> DemoDataset:
    """A resample of ``ds`` with replacement (ProMP's seeds)."""
    idx = np.random.default_rng([seed, 7]).integers(0, len(ds), len(ds))
    return DemoDataset(tuple(ds.demos[i] for i in idx), f"{ds.source}:bootstrap({seed})")


def evaluate(model, test: DemoDataset, n_points: int) -> dict[str, float]:
    """{conditioning: MSE rad²} for every conditioning the model and data support, their aggregate,
    and ``via_5``."""
    out = {c: reconstruction_mse(model, test, c, n_points=n_points) for c in available_conditionings(model, test)}
    out["aggregate"] = float(np.mean(list(out.values())))
    out["via_5"] = reconstruction_mse(model, test, "via_point", n_via=N_VIA_EXTRA, n_points=n_points, seed=0)
    return out


# The files whose code determines a unit's result (their digest is part of every unit's key).
SOURCES = ("experiments/reconstruction.py", "experiments/common.py", "experiments/goal_metrics.py",
           "bench/plot_bimodal.py", "deepprompt_ros/**/*.py")


def fit_unit(tasks: Mapping[str, TaskData], task: str, kind: str, seed: int, cfg: TrainConfig,
             goals: Mapping | None = None) -> dict:
    """One unit of the experiment: model ``kind`` trained with ``cfg`` (seed ``seed``; ProMP on bootstrap
    resample ``seed`` of the training set, ``promp_full`` on all of it) on ``tasks[task]`` and evaluated
    on its test demos: ``{seed, mse: {cond: value}, fit_s, eval_s}``; for the :data:`GOAL_KINDS` also
    ``goals`` (:func:`goal_metrics.measure` with the parameters ``goals``) and, for DeepProMP,
    ``ablation`` (``mse`` and ``goals`` of :class:`goal_metrics.AblatedDeepProMP`)."""
    data = tasks[task]
    cls = MODEL_CLASSES_BY_KIND[kind]
    t0 = time.perf_counter()
    if kind == "promp":
        model = cls(log=lambda s: None).fit(bootstrap(data.train, seed), cfg, data.val)
    elif cls is ProMPModel:
        model = cls(log=lambda s: None).fit(data.train, cfg, data.val)
    else:
        model = cls().fit(data.train, cfg, data.val)
    fit_s = time.perf_counter() - t0
    out = {"seed": seed, "mse": evaluate(model, data.test, cfg.n_points), "fit_s": fit_s}
    if kind in GOAL_KINDS:
        params = dict(goals or {})
        out["goals"] = goal_metrics.measure(model, data, cfg.n_points, **params)
        if isinstance(model, DeepProMPModel):
            abl = goal_metrics.AblatedDeepProMP(model)
            out["ablation"] = {"mse": evaluate(abl, data.test, cfg.n_points),
                               "goals": goal_metrics.measure(abl, data, cfg.n_points, **params)}
    out["eval_s"] = time.perf_counter() - t0 - fit_s
    return out


MODEL_CLASSES_BY_KIND = {**{cls.kind: cls for cls in MODEL_CLASSES}, **{k: v[0] for k, v in VARIANTS.items()}}


def goal_params(scale: Scale) -> dict:
    """The parameters of :func:`goal_metrics.measure` at ``scale`` (part of every unit's key)."""
    return {"n_sets": scale.goal_sets, "n_samples": scale.goal_samples}


def task_units(task: TaskData, base: TrainConfig, scale: Scale, kinds: Sequence[str] | None = None,
               variants: Sequence[str] = (), seeds: Sequence[int] | None = None,
               steps: tuple[int, int] | None = None) -> list[Unit]:
    """The units of one task, in table order (model classes, then ``variants`` of :data:`VARIANTS`, ×
    ``seeds``, default ``range(scale.recon_seeds)``; ``kinds``: only those; ``steps``: (updates,
    validation period) instead of the scale's ``recon_steps``, ``recon_val_every``); each unit's
    ``parts`` hold what determines its result: the training config as :func:`common.train_config`
    builds it, the scale's steps, the data (sizes and :func:`common.dataset_digest`), the goals'
    parameters, the digest of :data:`SOURCES` and the torch / numpy versions."""
    bad = sorted(set(variants) - set(VARIANTS))
    if bad:
        raise ValueError(f"unknown variants {bad}; expected names from {sorted(VARIANTS)}")
    data = {"sizes": [len(task.train), len(task.val), len(task.test)],
            "digest": common.dataset_digest([task.train, task.val, task.test])}
    fixed = {"experiment": "reconstruction", "task": task.name, "data": data,
             "scale": {"recon_steps": scale.recon_steps, "recon_val_every": scale.recon_val_every},
             "n_via_extra": N_VIA_EXTRA, "goals": goal_params(scale), **common.code_parts(SOURCES)}
    units = []
    for kind in [c.kind for c in MODEL_CLASSES] + list(variants):
        if kinds and kind not in kinds:
            continue
        for seed in (range(scale.recon_seeds) if seeds is None else seeds):
            cfg = common.train_config(base, *(steps or (scale.recon_steps, scale.recon_val_every)), int(seed),
                                      task.name)
            if kind in VARIANTS:
                cfg = dataclasses.replace(cfg, **VARIANTS[kind][1])
            parts = {**fixed, "kind": kind, "seed": int(seed), "train_config": dataclasses.asdict(cfg)}
            cost = 0.01 if MODEL_CLASSES_BY_KIND[kind] is ProMPModel else 1.0 + (task.train.image_shape is not None)
            units.append(Unit(f"{task.name}__{kind}__s{seed}", parts,
                              (task.name, kind, int(seed), cfg, goal_params(scale)), cost))
    return units


def run_tasks(tasks: Sequence[TaskData], base: TrainConfig, scale: Scale, kinds: Sequence[str] | None = None,
              log: Callable[[str], None] = print, cache: UnitCache | None = None,
              jobs: int = 1) -> tuple[dict[str, dict], UnitReport]:
    """Train and evaluate every model on every task, unit by unit (:func:`fit_unit`): units found in
    ``cache`` are read, the others computed (``jobs`` worker processes) and stored. Returns ({task name:
    :func:`task_result`}, what was reused / computed)."""
    return run_task_units(tasks, [u for t in tasks for u in task_units(t, base, scale, kinds)], log, cache, jobs)


def run_task_units(tasks: Sequence[TaskData], units: Sequence[Unit], log: Callable[[str], None] = print,
                   cache: UnitCache | None = None, jobs: int = 1) -> tuple[dict[str, dict], UnitReport]:
    """The ``units`` (of :func:`task_units` on ``tasks``) read from ``cache`` or computed (``jobs``
    worker processes) and stored, as :func:`run_tasks` returns them."""
    def show(u: Unit, r: dict, reused: bool, wall_s: float) -> None:
        task, kind, seed = u.args[:3]
        log(f"  {task:16s} {kind:15s} seed {seed}  fit {r['fit_s']:6.1f} s  "
            + "  ".join(f"{c} {v:.2e}" for c, v in r["mse"].items()) + ("  (reused)" if reused else ""))

    results, report = run_units(units, fit_unit, {t.name: t for t in tasks}, cache, jobs, SOURCES, show, log)
    runs: dict[str, dict[str, list]] = {t.name: {} for t in tasks}
    for u, r in zip(units, results):
        runs[u.args[0]].setdefault(u.args[1], []).append(r)
    return {t.name: task_result(t, runs[t.name]) for t in tasks if runs[t.name]}, report


def run_task(task: TaskData, base: TrainConfig, scale: Scale, kinds: Sequence[str] | None = None,
             log: Callable[[str], None] = print, cache: UnitCache | None = None, jobs: int = 1) -> dict:
    """Train and evaluate every model on one task (:func:`run_tasks`).

    Returns
    -------
    dict: ``runs`` {kind: [ {seed, mse: {cond: value}, fit_s, eval_s} ]}, ``stats`` {kind: {cond:
    {mean, se, n}}}, ``conditionings`` (those any model has), dataset sizes.
    """
    return run_tasks([task], base, scale, kinds, log, cache, jobs)[0][task.name]


def task_result(task: TaskData, runs: dict[str, list]) -> dict:
    """The table entry of one task from its units' results ``runs`` {kind: [unit result per seed]}."""
    conds = [c for c in PAPER_CONDITIONINGS + ("via_5",) if any(c in r["mse"] for rs in runs.values() for r in rs)]
    stats = {k: {c: dict(zip(("mean", "se"), common.mean_se([r["mse"].get(c, np.nan) for r in rs])),
                         n=sum(c in r["mse"] for r in rs)) for c in conds} for k, rs in runs.items()}
    return {"runs": runs, "stats": stats, "conditionings": conds,
            "sizes": {"train": len(task.train), "val": len(task.val), "test": len(task.test)},
            "joints": len(task.train.joint_names), "contexts": task.train.context_dims,
            "images": task.train.image_shape}


# ------------------------------------------------------------------------------------------------
# Figure and table
# ------------------------------------------------------------------------------------------------

def radar(ax, task: str, result: dict) -> None:
    """Log-scale radar of mean MSE per conditioning (paper's figure); smaller polygon = better."""
    conds = [c for c in result["conditionings"] if c in PAPER_CONDITIONINGS]
    stats = result["stats"]
    means = np.array([[stats[k][c]["mean"] for c in conds] for k in stats], dtype=np.float64)
    logs = np.log10(np.where(means > 0, means, np.nan))
    lo = np.floor(np.nanmin(logs)) - 0.5
    hi = np.ceil(np.nanmax(logs))
    ang = np.linspace(0, 2 * np.pi, len(conds), endpoint=False)
    ang_c = np.append(ang, ang[0])
    for i, kind in enumerate(stats):
        r = np.append(logs[i], logs[i][0]) - lo
        ax.plot(ang_c, r, marker="*" if kind == "promp" else "o", ms=7 if kind == "promp" else 4, lw=1.4,
                label=MODEL_LABELS.get(kind, kind))
    ticks = np.arange(lo + 0.5, hi + 1)
    ax.set_rticks(ticks - lo)
    ax.set_yticklabels([f"1e{int(t)}" for t in ticks], fontsize=7)
    ax.set_rlim(0, hi - lo + 0.2)
    ax.set_xticks(ang)
    ax.set_xticklabels([CONDITIONING_LABELS[c] for c in conds], fontsize=8)
    ax.set_title(f"{task}\nMSE (rad², log scale)", fontsize=9)


def plot(results: dict[str, dict], out: pathlib.Path) -> list[pathlib.Path]:
    import matplotlib.pyplot as plt

    files = []
    for task, res in results.items():
        fig = plt.figure(figsize=(5, 4.6))
        ax = fig.add_subplot(projection="polar")
        radar(ax, task, res)
        ax.legend(loc="upper left", bbox_to_anchor=(-0.25, -0.05), ncol=3, fontsize=7)
        fig.tight_layout()
        f = out / f"reconstruction_radar_{task}.png"
        fig.savefig(f, dpi=100)
        plt.close(fig)
        files.append(f)
    return files


def markdown(results: dict[str, dict], meta: dict) -> str:
    lines = [f"# Reconstruction of held-out demonstrations (MSE, rad², mean ± standard error over "
             f"{meta['seeds']} seeds)\n",
             f"Deep models: {meta['steps']} updates each (best validation weights); ProMP: bootstrap resamples "
             "of the training set. `via_5` is not in the paper nor in the aggregate. — = not applicable.\n"]
    for task, res in results.items():
        conds = res["conditionings"]
        s = res["sizes"]
        lines.append(f"\n## {task}\n\n{res['joints']} joints; contexts {res['contexts'] or 'none'}; images "
                     f"{res['images'] or 'none'}; {s['train']} train / {s['val']} val / {s['test']} test demos\n\n")
        rows = [[MODEL_LABELS.get(k, k)] + [common.fmt_pm(st[c]["mean"], st[c]["se"]) for c in conds]
                for k, st in res["stats"].items()]
        lines.append(common.markdown_table(["model"] + [CONDITIONING_LABELS[c] for c in conds], rows))
    return "".join(lines)


def run(scale: Scale, out: pathlib.Path, tasks: Sequence[str] | None = None, base: TrainConfig | None = None,
        log: Callable[[str], None] = print, cache: UnitCache | None = None, jobs: int = 1) -> dict:
    """Experiment 1 on ``tasks`` (default :func:`common.default_tasks`); writes
    ``reconstruction.{json,md}`` and ``reconstruction_radar_<task>.png`` under ``out``. The task data
    are loaded first (PyBullet tasks: generated or read from :func:`common.data_cache_dir`), then the
    units run (:func:`run_tasks`; ``cache``: finished units, e.g. ``UnitCache(out / "units" /
    "reconstruction")``). The returned dict's ``units`` is the :class:`UnitReport` (not in the JSON)."""
    base = base or common.base_train_config()
    tasks = tuple(tasks) if tasks else common.default_tasks(scale)
    datas = []
    for name in tasks:
        t0 = time.perf_counter()
        data = common.load_task(name, scale)
        log(f"  task {name}: {len(data.train)} train / {len(data.val)} val / {len(data.test)} test "
            f"({time.perf_counter() - t0:.1f} s to load)")
        datas.append(data)
    results, report = run_tasks(datas, base, scale, log=log, cache=cache, jobs=jobs)
    meta = {"scale": scale.name, "seeds": scale.recon_seeds, "steps": scale.recon_steps,
            "base_config": dataclasses.asdict(base), "tasks": list(tasks)}
    files = plot(results, out)
    files += common.write_outputs(out, "reconstruction", {"meta": meta, "tasks": results}, markdown(results, meta))
    return {"meta": meta, "tasks": results, "files": [str(f) for f in files], "units": report.to_json()}
