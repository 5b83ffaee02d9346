"""The goals of the model family — one table per goal (EXPERIMENTS.md, "Goals"):

1. via-points: never worse than ProMP (start only, start + end, 5 via-points, whole trajectory);
2. context: the best of all (Low Dim, Image, Image+Low, Aggregate vs ProMP and the four deep baselines);
3. modes kept (bimodal sine: ambiguous and distinguishing via-points);
4. samples honour the via-points (executed mean, K-sample mean, per-sample spread; N = 1, 5, 50);
5. any reasonable via-point is met (random planner via-points, 1e-6 rad);
6. honest uncertainty (partial vs full via-points, MAP refinement counting the via-points once);
7. the trained network earns its place: every table has the ablation row (the trained parts
   replaced by what they start from, :class:`experiments.goal_metrics.AblatedDeepProMP`) and a
   row for the other objective (``objective: np``, the Neural-Process form; DeepProMP's rows use
   ``train``'s default, the paper's objective); a last table says where DeepProMP does not beat them.

The numbers come from the reconstruction experiment's units (:func:`experiments.reconstruction.fit_unit`,
the same unit files: a run of both trains each model once), which measure the goals of
:mod:`experiments.goal_metrics` on every DeepProMP, its ablation and ProMP. This experiment adds the
variants ``deepprompt_np`` and ``promp_full`` (ProMP on the whole training split — the fair
comparison; the radar's ProMP is on bootstrap resamples), the bimodal sine task for goal 3 when it
is not among the tasks, and the small-data study's demonstrations (:func:`small_data_task`) as a
task of its own. The shipped models add two rows: ``models/bimodal_sine.safetensors`` in goal 3,
``models/gen3_lite_reach.safetensors`` through the server's Condition path in goal 5.

Mean ± standard error over seeds. "within 1 SE": a mean at most one standard error of the difference
(√(se_a² + se_b²), a missing one counted as 0) above the reference's.

Length: a little over 400 lines: seven tables, each a short function over the same unit records, and
the run that gathers them; split, the tables would lose the helpers they share.
"""
from __future__ import annotations

import dataclasses
import math
import pathlib
import time
from typing import Callable, Sequence

import numpy as np

from deepprompt_ros.baselines.deep_promp_model import DeepProMPModel
from deepprompt_ros.training.config import TrainConfig

from . import common, goal_metrics, reconstruction, small_data
from .common import Scale, TaskData
from .units import UnitCache

VARIANTS = ("deepprompt_np", "promp_full")
BASELINES = ("cnmp", "cnmp_indep", "vae_cnmp", "vae_cnmp_indep")
#: rows of every table: (key, label); "ablation" is read from the DeepProMP units
ROWS = (("deepprompt", "DeepProMP"), ("ablation", "ablation (trained parts at their start)"),
        ("deepprompt_np", "DeepProMP, objective: np"), ("promp_full", "ProMP (automatic selection)"))
DEEP_ROWS = ("deepprompt", "ablation", "deepprompt_np")
VIA_CONDITIONINGS = (("start", "start only"), ("start_end", "start + end"), ("via_5", "5 via-points"),
                     ("via_point", "whole trajectory"))
CONTEXT_CONDITIONINGS = (("low_dim", "Low Dim"), ("image", "Image"), ("image+low", "Image+Low"),
                         ("aggregate", "Aggregate"))
N_VIAS = ("1", "5", "50")


def small_data_task(scale: Scale) -> TaskData:
    """The small-data study's demonstrations (:func:`experiments.small_data.default_data`: ``small_n_train``
    demos of :func:`common.small_data_task` without images, ``small_n_test`` held out) as a task named
    ``small_data``: the training demos split as the study's models split them (10 %, at least one, for
    validation; seed 0)."""
    train, test = small_data.default_data(scale.small_n_train, scale.small_n_test, common.small_data_task(scale))
    tr, va = train.split(max(1, len(train) // 10), seed=0)
    return TaskData("small_data", tr, va, test)


# ------------------------------------------------------------------------------------------------
# Reading the units
# ------------------------------------------------------------------------------------------------

def records(runs: dict, row: str) -> list[tuple[dict, dict | None]]:
    """(mse, goals) of every seed of ``row`` (a kind, or ``ablation``: the DeepProMP units' ablation)."""
    if row == "ablation":
        return [(r["ablation"]["mse"], r["ablation"]["goals"]) for r in runs.get("deepprompt", []) if "ablation" in r]
    return [(r["mse"], r.get("goals")) for r in runs.get(row, [])]


def stat(runs: dict, row: str, get: Callable[[dict, dict | None], float]) -> dict:
    """{mean, se, n} of ``get(mse, goals)`` over the seeds of ``row`` (missing values skipped)."""
    vals = []
    for mse, goals in records(runs, row):
        try:
            v = get(mse, goals)
        except (KeyError, TypeError):
            continue
        if v is not None and math.isfinite(v):
            vals.append(float(v))
    m, se = common.mean_se(vals)
    return {"mean": m, "se": se, "n": len(vals)}


def within(a: dict, ref: dict, higher_is_better: bool = False) -> bool | None:
    """``a`` at least as good as ``ref`` within one standard error of the difference; None if either is missing."""
    if not (a["n"] and ref["n"]):
        return None
    se = math.sqrt(sum(s ** 2 for s in (a["se"], ref["se"]) if math.isfinite(s)))
    return (ref["mean"] - a["mean"] <= se) if higher_is_better else (a["mean"] - ref["mean"] <= se)


def compare(a: dict, ref: dict, higher_is_better: bool = False) -> str | None:
    """'better' (by more than one standard error of the difference), 'within 1 SE' or 'worse'; None if missing."""
    if not (a["n"] and ref["n"]):
        return None
    se = math.sqrt(sum(s ** 2 for s in (a["se"], ref["se"]) if math.isfinite(s)))
    d = (a["mean"] - ref["mean"]) * (-1 if higher_is_better else 1)
    return "better" if d < -se else ("worse" if d > se else "within 1 SE")


def _mse(cond: str) -> Callable:
    if cond in ("start", "start_end"):
        return lambda mse, goals: goals["subsets"][cond]
    return lambda mse, goals: mse[cond]


def _cell(st: dict, ref: dict | None = None, higher_is_better: bool = False, pct: bool = False) -> str:
    if not st["n"]:
        return "—"
    txt = (f"{st['mean']:.0%}" + (f" ± {st['se']:.0%}" if math.isfinite(st["se"]) else "")) if pct else \
        common.fmt_pm(st["mean"], st["se"])
    if ref is not None and ref["n"]:
        ok = within(st, ref, higher_is_better)
        txt += (f" ({st['mean'] / ref['mean']:.2f}×, {'✓' if ok else '✗'})" if not pct and ref["mean"] > 0 else
                f" ({'✓' if ok else '✗'})")
    return txt


# ------------------------------------------------------------------------------------------------
# The tables
# ------------------------------------------------------------------------------------------------

def goal1(results: dict) -> tuple[str, dict]:
    """Goal 1: MSE per via-point conditioning; (ratio to ProMP, ✓ = at most ProMP's within 1 SE)."""
    data, rows, met = {}, [], []
    for task, res in results.items():
        runs = res["runs"]
        ref = {c: stat(runs, "promp_full", _mse(c)) for c, _ in VIA_CONDITIONINGS}
        data[task] = {}
        for row, label in ROWS:
            st = {c: stat(runs, row, _mse(c)) for c, _ in VIA_CONDITIONINGS}
            data[task][row] = st
            rows.append([task, label] + [_cell(st[c], None if row == "promp_full" else ref[c]) for c, _ in
                                         VIA_CONDITIONINGS])
            if row == "deepprompt":
                met += [within(st[c], ref[c]) for c, _ in VIA_CONDITIONINGS]
    ok = [m for m in met if m is not None]
    md = (common.markdown_table(["task", "model"] + [lab for _, lab in VIA_CONDITIONINGS], rows)
          + f"\nDeepProMP at most ProMP's MSE within one standard error: {sum(ok)} of {len(ok)} (task, conditioning)"
            " pairs.\n")
    return md, data


def goal2(results: dict) -> tuple[str, dict]:
    """Goal 2: MSE per context conditioning vs the best of ProMP and the four deep baselines."""
    data, rows, met = {}, [], []
    for task, res in results.items():
        runs = res["runs"]
        conds = [(c, lab) for c, lab in CONTEXT_CONDITIONINGS if c in res["conditionings"]]
        if not any(c != "aggregate" for c, _ in conds) or not any(k in runs for k in BASELINES):
            continue  # no context in the data, or the baselines were not run on this task
        # Aggregate: the mean over the conditionings every compared model takes on this task (ProMP takes no
        # image), so that no model's mean holds conditionings another's lacks
        shared = [c for c in reconstruction.PAPER_CONDITIONINGS if c in res["conditionings"] and c != "aggregate" and all(
            all(c in mse for mse, _ in records(runs, k)) for k in ("deepprompt", "promp_full") + BASELINES
            if records(runs, k))]
        data[task] = {"aggregate_over": shared}

        def get(c):
            return (lambda mse, goals: float(np.mean([mse[x] for x in shared]))) if c == "aggregate" else _mse(c)
        best = {}
        for c, _ in conds:
            cands = {k: stat(runs, k, get(c)) for k in ("promp_full",) + BASELINES}
            cands = {k: v for k, v in cands.items() if v["n"]}
            k = min(cands, key=lambda k: cands[k]["mean"]) if cands else None
            best[c] = {**cands[k], "model": k} if k else {"mean": float("nan"), "se": float("nan"), "n": 0,
                                                         "model": None}
        data[task]["best_other"] = best
        have = [c for c, _ in conds]
        for row, label in ROWS[:3]:
            st = {c: stat(runs, row, get(c)) for c in have}
            data[task][row] = st
            rows.append([task, label] + [_cell(st[c], best[c]) if c in have else "—" for c, _ in CONTEXT_CONDITIONINGS])
            if row == "deepprompt":
                met += [within(st[c], best[c]) for c in have]
        rows.append([task, "best of ProMP and the deep baselines"]
                    + [f"{common.fmt_pm(best[c]['mean'], best[c]['se'])} "
                       f"({reconstruction.MODEL_LABELS.get(best[c]['model'], best[c]['model'])})" if c in have else "—"
                       for c, _ in CONTEXT_CONDITIONINGS])
    ok = [m for m in met if m is not None]
    md = (common.markdown_table(["task", "model"] + [lab for _, lab in CONTEXT_CONDITIONINGS], rows)
          + f"\nDeepProMP at most the best other model's MSE within one standard error: {sum(ok)} of {len(ok)} "
            "(task, conditioning) pairs. Columns a task has no data for: —. Aggregate: the mean over the conditionings "
            "every compared model takes on the task (via-point and Low Dim where there are images: ProMP takes none).\n")
    return md, data


MODE_COLUMNS = (("on_mode", "ambiguous: on a mode", lambda g: g["modes"]["ambiguous"]["on_mode"]),
                ("on_pos", "ambiguous: + mode", lambda g: g["modes"]["ambiguous"]["on_pos"]),
                ("on_neg", "ambiguous: − mode", lambda g: g["modes"]["ambiguous"]["on_neg"]),
                ("both", "both modes present", lambda g: float(g["modes"]["ambiguous"]["both"])),
                ("3 via-points", "3 via-points: right mode", lambda g: g["modes"]["3 via-points"]),
                ("12 via-points", "12 via-points: right mode", lambda g: g["modes"]["12 via-points"]))


def goal3(results: dict, shipped: dict | None) -> tuple[str, dict]:
    """Goal 3: shares of samples on the bimodal sine's modes."""
    res = results.get("bimodal_sine")
    data, rows = {}, []
    if res is not None:
        for row, label in ROWS:
            st = {k: stat(res["runs"], row, lambda m, g, f=f: f(g)) for k, _, f in MODE_COLUMNS}
            data[row] = st
            rows.append([label] + [(f"{round(st[k]['mean'] * st[k]['n'])} of {st[k]['n']} seeds" if st[k]["n"] else "—")
                                   if k == "both" else _cell(st[k], pct=True) for k, _, _ in MODE_COLUMNS])
    if shipped is not None:
        data["shipped"] = shipped
        rows.append([f"shipped `{shipped['file']}` ({shipped['training']})"]
                    + [f"{shipped['modes']['ambiguous'][k]:.0%}" if k in ("on_mode", "on_pos", "on_neg") else
                       ("yes" if shipped["modes"]["ambiguous"]["both"] else "no") if k == "both" else
                       f"{shipped['modes'][k]:.0%}" for k, _, _ in MODE_COLUMNS])
    rows.append(["goal", "≥ 90%", "", "", "yes", "≥ 98%", "≥ 98%"])
    md = (common.markdown_table(["model"] + [lab for _, lab, _ in MODE_COLUMNS], rows)
          + "\nFractions of 200 samples at x = 0.25 (+ mode y > 0.6, − mode "
            "y < −0.6). Ambiguous: y = 0 at x = 0, 0.5, 1; distinguishing: points of 10 held-out demonstrations; "
            f"both modes present: each holds ≥ {goal_metrics.BOTH_MODES_MIN:.0%} of the samples.\n")
    return md, data


SAMPLE_COLUMNS = (("mean_error", "executed mean: max error"), ("sample_mean_error", "K-sample mean: max error"),
                  ("spread", "per-sample spread (RMS)"), ("noise", "stated noise (RMS)"))


def goal4(results: dict) -> tuple[str, dict]:
    """Goal 4: errors of the executed mean, of the K-sample mean and the samples' spread at N via-points."""
    data, rows = {}, []
    for task, res in results.items():
        data[task] = {}
        for row, label in ROWS:
            for n in N_VIAS:
                st = {k: stat(res["runs"], row, lambda m, g, k=k, n=n: g["samples"][n][k]) for k, _ in SAMPLE_COLUMNS}
                if not any(v["n"] for v in st.values()):
                    continue
                data[task].setdefault(row, {})[n] = st
                rows.append([task, label, n] + [_cell(st[k]) for k, _ in SAMPLE_COLUMNS])
    md = (common.markdown_table(["task", "model", "N"] + [lab for _, lab in SAMPLE_COLUMNS], rows)
          + f"\nrad; N held-out via-points per demonstration (at most the grid's points), the model's default "
            f"conditioning as the server's default Condition runs it (refine={goal_metrics.server_default_refine()}), "
            "mean over the test demonstrations of the max over via-points and joints; K = the scale's samples. "
            "Spread: RMS of sample − via-point.\n")
    return md, data


def goal5(results: dict, shipped: dict | None) -> tuple[str, dict]:
    """Goal 5: share of random planner via-point sets met to 1e-6 rad by the executed mean."""
    data, rows = {}, []
    for task, res in results.items():
        data[task] = {}
        for row, label in ROWS:
            st = stat(res["runs"], row, lambda m, g: g["via_met"]["share"])
            med = stat(res["runs"], row, lambda m, g: g["via_met"]["median_error"])
            if not st["n"]:
                continue
            data[task][row] = {"share": st, "median_error": med}
            rows.append([task, label, _cell(st, pct=True), common.fmt(med["mean"])])
    if shipped is not None:
        data["shipped"] = shipped
        s, p = shipped["server"], shipped["promp"]
        rows.append([f"shipped `{shipped['model']['file']}`",
                     f"server Condition (refine={s['refine']}), {s['n']} sets", f"{s['share']:.0%}",
                     common.fmt(s["median_error"])])
        o = shipped["server_other_refine"]
        rows.append(["", f"server Condition with refine={o['refine']} (not the default), same sets",
                     f"{o['share']:.0%}", common.fmt(o["median_error"])])
        rows.append(["", f"ProMP on its {shipped['n_train_demos']} training demos, same sets", f"{p['share']:.0%}",
                     common.fmt(p["median_error"])])
    md = (common.markdown_table(["task", "model", "sets met (1e-6 rad)", "median max error (rad)"], rows)
          + f"\n1–5 via-points per set at random phases, each joint uniform in the training demonstrations' range "
            f"at that phase ± {goal_metrics.RANGE_MARGIN:.0%} of its span, inside the joint limits; the context of a "
            "held-out demonstration; the model's default conditioning as the server's default Condition runs it "
            f"(refine={goal_metrics.server_default_refine()}). Goal: 100 %.\n")
    return md, data


def goal6(results: dict) -> tuple[str, dict]:
    """Goal 6: a partial via-point's free joints wider than a full one's; MAP counting the via-points once."""
    data, rows = {}, []
    for task, res in results.items():
        data[task] = {}
        for row, label in ROWS:
            if row == "promp_full":
                continue
            if row == "ablation":
                rows.append([task, label, "— (no encoder)", "— (no encoder)"])
                continue
            a = stat(res["runs"], row, lambda m, g: g["uncertainty"]["partial_over_full"])
            b = stat(res["runs"], row, lambda m, g: g["uncertainty"]["map_double_count"])
            data[task][row] = {"partial_over_full": a, "map_double_count": b}
            rows.append([task, label, f"{a['mean']:.3g}" if a["n"] else "— (one joint)",
                         f"{b['mean']:.3g}" if b["n"] else "—"])
    md = (common.markdown_table(["task", "model", "free joints' std: partial / full via-point (goal > 1)",
                                 "MAP variance: posterior prior / evidence once (goal 1)"], rows)
          + "\nMean over the test demonstrations (and seeds): a via-point at x = 0.5 constraining the first half of "
            "the joints vs all of them; MAP refinement (prior = posterior) from q(z | 5 via-points, context) vs "
            "from q(z | context).\n")
    return md, data


def goal7(tables: dict) -> str:
    """Goal 7: where DeepProMP does not beat its ablation or the other objective, per goal and task."""
    checks = []  # (goal, task, metric, higher_is_better, stats of the three deep rows)
    for task, rows in tables["goal1"].items():
        for c, lab in VIA_CONDITIONINGS:
            checks.append(("1", task, lab, False, {k: rows[k][c] for k in DEEP_ROWS}))
    for task, rows in tables["goal2"].items():
        for c, lab in CONTEXT_CONDITIONINGS:
            if c in rows["deepprompt"]:
                checks.append(("2", task, lab, False, {k: rows[k][c] for k in DEEP_ROWS}))
    g3 = tables["goal3"]
    if all(k in g3 for k in DEEP_ROWS):
        for k, lab, _ in MODE_COLUMNS:
            if k in ("on_mode", "3 via-points", "12 via-points"):
                checks.append(("3", "bimodal_sine", lab, True, {r: g3[r][k] for r in DEEP_ROWS}))
    for task, rows in tables["goal4"].items():
        for n in N_VIAS:
            if all(n in rows.get(r, {}) for r in DEEP_ROWS):
                checks.append(("4", task, f"K-sample mean error, N = {n}", False,
                               {r: rows[r][n]["sample_mean_error"] for r in DEEP_ROWS}))
    for task, rows in tables["goal5"].items():
        if task != "shipped" and all(r in rows for r in DEEP_ROWS):
            checks.append(("5", task, "sets met", True, {r: rows[r]["share"] for r in DEEP_ROWS}))
    out = []
    for goal, task, metric, hib, st in checks:
        out.append([goal, task, metric, compare(st["deepprompt"], st["ablation"], hib) or "—",
                    compare(st["deepprompt"], st["deepprompt_np"], hib) or "—"])
    counts = {w: sum(r[3] == w for r in out) for w in ("better", "within 1 SE", "worse")}
    paper = {w: sum(r[4] == w for r in out) for w in ("better", "within 1 SE", "worse")}
    return (common.markdown_table(["goal", "task", "measure", "DeepProMP vs its ablation",
                                   "DeepProMP vs objective: np"], out)
            + f"\nOf {len(out)} measures, DeepProMP beats its ablation by more than one standard error on "
              f"{counts['better']}, is within one standard error on {counts['within 1 SE']} and worse on "
              f"{counts['worse']}: where it is not better, the trained network adds nothing measurable to that number "
              "(within) or makes it worse. "
              f"Against the Neural-Process objective: better on {paper['better']}, within on {paper['within 1 SE']}, worse "
              f"on {paper['worse']}.\n")


def models_table(results: dict, meta: dict) -> str:
    """What produced each row: per task the first seed's model labels, demos and updates."""
    rows = []
    for task, res in results.items():
        s = res["sizes"]
        for row, label in ROWS:
            recs = records(res["runs"], row)
            if recs and recs[0][1]:
                labels = sorted({g["label"] for _, g in recs if g})
                rows.append([task, label, "; ".join(labels), f"{s['train']} / {s['val']} / {s['test']}",
                             str(meta["steps"].get(task, meta["steps"]["default"])) if row != "promp_full" else "—"])
    return common.markdown_table(["task", "row", "what produced it (per seed where they differ)",
                                  "train / val / test demos", "updates"], rows)


# ------------------------------------------------------------------------------------------------
# Run
# ------------------------------------------------------------------------------------------------

def shipped_rows(scale: Scale, log: Callable[[str], None] = print) -> tuple[dict, dict]:
    """Goal 3's row of ``models/bimodal_sine.safetensors`` and goal 5's rows of the shipped reach
    primitive through the server (:func:`goal_metrics.shipped_reach_via_met`, ``scale.goal_sets`` sets)."""
    path = common.MODELS / "bimodal_sine.safetensors"
    model = DeepProMPModel.load(path)
    tc = model.primitive.metadata.get("train_config", {})
    bim = {"file": f"models/{path.name}", "modes": goal_metrics.mode_shares(model),
           "training": f"{tc.get('steps', '?')} updates, objective {tc.get('objective', '?')}, "
                       f"{goal_metrics.model_label(model).split(', objective')[0]}"}
    reach = goal_metrics.shipped_reach_via_met(common.ROOT, scale.goal_sets)
    log(f"  shipped bimodal_sine: on a mode {bim['modes']['ambiguous']['on_mode']:.0%} (ambiguous); shipped reach "
        f"through the server: {reach['server']['share']:.0%} of {reach['server']['n']} sets met, ProMP "
        f"{reach['promp']['share']:.0%}")
    return bim, reach


def run(scale: Scale, out: pathlib.Path, tasks: Sequence[str] | None = None, base: TrainConfig | None = None,
        log: Callable[[str], None] = print, cache: UnitCache | None = None, jobs: int = 1) -> dict:
    """The goals' tables at ``scale``; writes ``goals.{json,md}`` under ``out``. ``cache``: the
    reconstruction experiment's unit cache (``<out>/units/reconstruction``), whose units are read or
    computed (``jobs`` worker processes) and stored; the returned dict's ``units`` is the
    :class:`UnitReport` (not in the JSON)."""
    base = base or common.base_train_config()
    tasks = tuple(tasks) if tasks else common.default_tasks(scale)
    datas, units = [], []
    for name in tasks:
        t0 = time.perf_counter()
        d = common.load_task(name, scale)
        log(f"  task {name}: {len(d.train)} train / {len(d.val)} val / {len(d.test)} test "
            f"({time.perf_counter() - t0:.1f} s to load)")
        datas.append(d)
        units += reconstruction.task_units(d, base, scale, variants=VARIANTS)
    if "bimodal_sine" not in tasks:  # goal 3: DeepProMP's variants and ProMP only
        d = common.load_task("bimodal_sine", scale)
        datas.append(d)
        units += reconstruction.task_units(d, base, scale, kinds=reconstruction.GOAL_KINDS, variants=VARIANTS)
    small = small_data_task(scale)
    datas.append(small)
    small_steps = (scale.small_steps, max(1, scale.small_steps // 8))
    units += reconstruction.task_units(small, base, scale, kinds=reconstruction.GOAL_KINDS, variants=VARIANTS,
                                       seeds=range(scale.small_seeds), steps=small_steps)
    log(f"  small-data study as task 'small_data': {len(small.train)} train / {len(small.val)} val / "
        f"{len(small.test)} test demos of {common.small_data_task(scale)}")
    results, report = reconstruction.run_task_units(datas, units, log, cache, jobs)
    shipped_bim, shipped_reach = shipped_rows(scale, log)
    md1, t1 = goal1(results)
    md2, t2 = goal2(results)
    md3, t3 = goal3(results, shipped_bim)
    md4, t4 = goal4(results)
    md5, t5 = goal5(results, shipped_reach)
    md6, t6 = goal6(results)
    tables = {"goal1": t1, "goal2": t2, "goal3": t3, "goal4": t4, "goal5": t5, "goal6": t6}
    md7 = goal7(tables)
    meta = {"scale": scale.name, "seeds": scale.recon_seeds, "small_seeds": scale.small_seeds,
            "steps": {"default": scale.recon_steps, "small_data": scale.small_steps},
            "base_config": dataclasses.asdict(base), "tasks": [d.name for d in datas],
            "goal_params": reconstruction.goal_params(scale)}
    md = (f"# Goals of the model family ({scale.name} size)\n\nMean ± standard error over seeds ({scale.recon_seeds}; "
          f"small data {scale.small_seeds}); ✓ / ✗: at most the reference within one standard error of the "
          "difference (goal 1: ProMP; goal 2: the best of ProMP and the four deep baselines). DeepProMP: the base "
          "configuration as `train` runs it (its own model selection on the training demos); ProMP: on the whole "
          "training split with its automatic selection.\n\n## What produced each row\n\n"
          + models_table(results, meta)
          + "\n## Goal 1: via-points, never worse than ProMP (MSE, rad²)\n\n" + md1
          + "\n## Goal 2: context, the best of all (MSE, rad²)\n\n" + md2
          + "\n## Goal 3: modes kept (bimodal sine)\n\n" + md3
          + "\n## Goal 4: samples honour the via-points\n\n" + md4
          + "\n## Goal 5: any reasonable via-point is met\n\n" + md5
          + "\n## Goal 6: honest uncertainty\n\n" + md6
          + "\n## Goal 7: the trained network earns its place\n\n" + md7)
    files = common.write_outputs(out, "goals", {"meta": meta, "tables": tables, "tasks": results}, md)
    return {"meta": meta, "tables": tables, "files": [str(f) for f in files], "units": report.to_json()}

