"""Experiment 5 — the bimodal sine figure (paper Fig. "DeepProMPs used in different situations").

(a)/(b) conditioning on 3 and on many via-points: :mod:`bench.plot_bimodal` draws them (its figure is
written to ``bimodal_sine.png`` and its printed fractions are parsed into the table);
(c) conflicting via-points, added here: y(0.25) = +1 says "positive mode", y(0.75) = +1 says
"negative mode" (the modes are ±A sin 2πx). The paper: "with inconsistent via-points, the model
chooses to violate one of them staying close to the given dataset". Measured at x = 0.25 with
:func:`bench.plot_bimodal.fractions`: samples on the positive mode, on the negative mode, between
(|y| < 0.4); and the mean absolute miss of each via-point.
"""
from __future__ import annotations

import contextlib
import importlib
import io
import pathlib
import re
from typing import Callable

import numpy as np

from deepprompt_ros.data.synthetic import bimodal_sine
from deepprompt_ros.primitive.deep_promp import DeepProMP
from deepprompt_ros.baselines.promp import ProMP

from . import common
from .common import Scale

N_SAMPLES = 200
CONFLICT_X = np.array([0.25, 0.75])
CONFLICT_Y = np.array([[1.0], [1.0]])
_LINE = re.compile(r"^(DeepProMP|ProMP)\s+(.+?)\s+on\+ ([\d.]+) on- ([\d.]+) between ([\d.]+)\s*$")


def _plot_bimodal():
    return importlib.import_module("bench.plot_bimodal")


def run(scale: Scale, out: pathlib.Path, log: Callable[[str], None] = print) -> dict:
    """Experiment 5; writes ``bimodal_sine.png`` (bench/plot_bimodal.py), ``bimodal_conflict.png`` and
    ``bimodal.{json,md}`` under ``out``."""
    pb = _plot_bimodal()
    model_path = common.MODELS / "bimodal_sine.safetensors"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = pb.main(["--out", str(out / "bimodal_sine.png"), "--model", str(model_path)])
    if rc != 0:
        raise RuntimeError(f"bench/plot_bimodal.py failed (exit {rc}): {buf.getvalue()}")
    cases = []
    for line in buf.getvalue().splitlines():
        m = _LINE.match(line.strip())
        if m:
            cases.append({"model": m[1], "case": m[2], "on_pos": float(m[3]), "on_neg": float(m[4]),
                          "between": float(m[5])})
    for c in cases:
        log(f"  {c['model']:10s} {c['case']:18s} +mode {c['on_pos']:.0%}  −mode {c['on_neg']:.0%}  "
            f"between {c['between']:.0%}")

    # (c) conflicting via-points
    x = np.linspace(0.0, 1.0, 101)
    deep = DeepProMP.from_checkpoint(str(model_path))
    ds = bimodal_sine(200, seed=0)
    Y = np.stack([d.resampled(101) for d in ds.demos])
    promp = ProMP(1, n_basis=15).fit(Y, x)
    samples = {"DeepProMP": deep.sample(deep.condition(CONFLICT_X, CONFLICT_Y), x, N_SAMPLES, rng=0),
               "ProMP": promp.condition(CONFLICT_X, CONFLICT_Y, noise_var=1e-4).sample(x, N_SAMPLES,
                                                                                    np.random.default_rng(0))}
    idx = np.rint(CONFLICT_X * 100).astype(int)
    conflict = {}
    for name, s in samples.items():
        pos, neg, gap = pb.fractions(s)
        miss = np.abs(s[:, idx, 0] - CONFLICT_Y[:, 0]).mean(0)
        # distance of each sample to the nearest demonstration (is it "close to the given dataset"?)
        near = np.sqrt(((s[:, None, :, 0] - Y[None, :, :, 0]) ** 2).mean(-1)).min(1)
        conflict[name] = {"on_pos": float(pos), "on_neg": float(neg), "between": float(gap),
                          "miss_x025": float(miss[0]), "miss_x075": float(miss[1]),
                          "rms_to_nearest_demo_median": float(np.median(near))}
        log(f"  {name:10s} conflicting        +mode {pos:.0%}  −mode {neg:.0%}  between {gap:.0%}  miss at "
            f"0.25 {miss[0]:.2f}, at 0.75 {miss[1]:.2f}; RMS to nearest demo {np.median(near):.2f}")
    files = [out / "bimodal_sine.png", plot_conflict(x, Y, samples, out / "bimodal_conflict.png")]
    rows = [[c["model"], c["case"], f"{c['on_pos']:.0%}", f"{c['on_neg']:.0%}", f"{c['between']:.0%}", "", ""]
            for c in cases]
    rows += [[k, "conflicting (0.25 → +1, 0.75 → +1)", f"{v['on_pos']:.0%}", f"{v['on_neg']:.0%}",
              f"{v['between']:.0%}", f"{v['miss_x025']:.2f} / {v['miss_x075']:.2f}",
              f"{v['rms_to_nearest_demo_median']:.2f}"] for k, v in conflict.items()]
    md = ("# Bimodal sine: fractions of 200 samples at x = 0.25 (on the + mode: y > 0.6, on the − mode: y < −0.6, "
          "between: |y| < 0.4)\n\nModel `models/bimodal_sine.safetensors`; ProMP with 15 RBF on the same 200 demos. "
          "Miss = mean |sample − via-point| (rad); RMS to the nearest demonstration (median over samples).\n\n"
          + common.markdown_table(["model", "via-points", "+ mode", "− mode", "between", "miss 0.25 / 0.75",
                                   "RMS to nearest demo"], rows))
    files += common.write_outputs(out, "bimodal", {"cases": cases, "conflict": conflict}, md)
    return {"cases": cases, "conflict": conflict, "files": [str(f) for f in files]}


def plot_conflict(x, Y, samples: dict, path: pathlib.Path) -> pathlib.Path:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(samples), figsize=(4.2 * len(samples), 3), sharey=True)
    for ax, (name, s), color in zip(np.atleast_1d(axes), samples.items(), ("C0", "C1")):
        ax.plot(x, Y[:40, :, 0].T, color="0.85", lw=0.6)
        ax.plot(x, s[:60, :, 0].T, color=color, lw=0.6, alpha=0.6)
        ax.plot(CONFLICT_X, CONFLICT_Y[:, 0], "kx", ms=8, mew=2)
        ax.set_title(f"{name}: conflicting via-points", fontsize=9)
        ax.set_xlabel("phase x")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
