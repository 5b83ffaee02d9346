"""Experiment 3 — rhythmic primitive (paper Sec. IV "Real-Robot Make Mojito", figure "demonstrated
motion and learned cyclical behavior").

The shipped WAM shaking primitive (``models/wam_shake.safetensors``, rhythmic phase
[sin 2πx, cos 2πx]; trained here for ``rhythmic_train_steps`` updates if the file is missing) is
conditioned on a held-out shaking demonstration whose end does not meet its start: a linear drift
adds ``gap`` rad at the end of the cycle (the paper: "a smooth transition even if the gap between
the demonstration's starting point and the endpoint is large"). Played back cycle after cycle, the
demonstration jumps by the gap at every seam; the learned primitive is decoded over the same cycles.

Seam continuity, per trajectory sampled at P points per cycle (x_k = k/P) over C cycles, dt = T/P:
position step at the seam |y(0) − y((P−1)/P)| against the largest in-cycle step, and the velocity
change at the seam |v_seam − v_before| against the largest in-cycle velocity change (max over joints).
A ProMP with the periodic von Mises basis, conditioned on the same via-points, is the reference.
"""
from __future__ import annotations

import dataclasses
import pathlib
from typing import Callable

import numpy as np

from deepprompt_ros.baselines.promp_model import ProMPModel
from deepprompt_ros.data.builtin import wam_shake
from deepprompt_ros.primitive.deep_promp import DeepProMP

from . import common
from .common import Scale

N_VIA = 21  # via-points on x = 0, 0.05, ..., 1: both ends of the gapped cycle are given
POINTS_PER_CYCLE = 100


def load_primitive(scale: Scale, log: Callable[[str], None] = print) -> tuple[DeepProMP, str]:
    path = common.MODELS / "wam_shake.safetensors"
    if path.is_file():
        return DeepProMP.from_checkpoint(str(path)), str(path.relative_to(common.ROOT))
    from deepprompt_ros.training.config import TrainConfig
    from deepprompt_ros.training.loop import train

    cfg = TrainConfig.from_yaml(common.ROOT / "config" / "train_wam_shake.yaml")
    cfg = dataclasses.replace(cfg, steps=scale.rhythmic_train_steps, threads=1,
                              val_every=min(cfg.val_every, scale.rhythmic_train_steps))
    log(f"  {path.name} missing: training {cfg.steps} updates on wam_shake(seed=0)")
    ds = wam_shake(seed=0)
    net, norm, _ = train(ds, cfg, log=lambda s: None)
    return DeepProMP(net, norm, ds.joint_names, name="wam_shake"), f"trained here ({cfg.steps} updates)"


def seam_metrics(f: Callable[[np.ndarray], np.ndarray], cycles: int, period: float) -> dict:
    """Continuity of y = f(x) repeated over ``cycles`` cycles (P points per cycle).

    Returns max over joints of: seam position step, largest in-cycle step, seam velocity change,
    largest in-cycle velocity change (rad, rad/s), and the trajectory (C·P, d).
    """
    p = POINTS_PER_CYCLE
    y1 = f(np.arange(p) / p)  # (P, d), x in [0, 1)
    y = np.tile(y1, (cycles, 1))
    dt = period / p
    step = np.abs(np.diff(y, axis=0))  # step k: y[k] -> y[k+1]
    seam_idx = np.arange(1, cycles) * p - 1  # steps crossing a seam
    inner = np.setdiff1d(np.arange(step.shape[0]), seam_idx)
    v = np.diff(y, axis=0) / dt
    dv = np.abs(np.diff(v, axis=0))  # change k: v[k] -> v[k+1]; around seam s: k = s-1 and k = s
    dv_seam_idx = np.concatenate([seam_idx - 1, seam_idx])
    dv_inner = np.setdiff1d(np.arange(dv.shape[0]), dv_seam_idx)
    return {"seam_step": float(step[seam_idx].max()), "max_inner_step": float(step[inner].max()),
            "seam_dv": float(dv[dv_seam_idx].max()), "max_inner_dv": float(dv[dv_inner].max()),
            "trajectory": y}


def run(scale: Scale, out: pathlib.Path, gap: float = 0.08, log: Callable[[str], None] = print) -> dict:
    """Experiment 3; writes ``rhythmic_cycles.png``, ``rhythmic_seam.png``, ``rhythmic.{json,md}``."""
    prim, source = load_primitive(scale, log)
    held = wam_shake(seed=common.DATA_SEED, n_demos=1).demos[0]
    period = float(held.t[-1] - held.t[0])
    x_demo = held.phase()
    q_gap = held.q + gap * x_demo[:, None]  # end − start ≈ gap on every joint

    def demo_f(x):
        return np.stack([np.interp(x, x_demo, q_gap[:, j]) for j in range(q_gap.shape[1])], 1)

    xv = np.linspace(0.0, 1.0, N_VIA)
    yv = demo_f(xv)
    lat = prim.condition(xv, yv)
    train_ds = wam_shake(seed=0)
    cfg = common.train_config(common.base_train_config(), 1, 1, 0)
    promp = ProMPModel().fit(train_ds, cfg)
    promp_cond = promp.condition(xv, yv)
    cases = {"demonstration (played back)": demo_f,
             "DeepProMP (conditioned on it)": lambda x: prim.mean_trajectory(lat, x),
             "ProMP, von Mises basis (conditioned on it)": lambda x: promp.mean_trajectory(promp_cond, x)}
    metrics = {k: seam_metrics(f, scale.rhythmic_cycles, period) for k, f in cases.items()}
    fit_err = float(np.abs(prim.mean_trajectory(lat, x_demo) - q_gap).max())
    for k, m in metrics.items():
        log(f"  {k:44s} seam step {m['seam_step']:.2e} rad (in-cycle max {m['max_inner_step']:.2e}); "
            f"seam Δv {m['seam_dv']:.2e} rad/s (in-cycle max {m['max_inner_dv']:.2e})")
    files = plot(metrics, held.joint_names, period, scale.rhythmic_cycles, out)
    table = {k: {kk: vv for kk, vv in m.items() if kk != "trajectory"} for k, m in metrics.items()}
    meta = {"model": source, "gap_rad": gap, "cycles": scale.rhythmic_cycles, "period_s": period,
            "points_per_cycle": POINTS_PER_CYCLE, "n_via": N_VIA,
            "max_abs_error_to_gapped_demo_rad": fit_err}
    rows = [[k, common.fmt(m["seam_step"]), common.fmt(m["max_inner_step"]),
             f"{m['seam_step'] / m['max_inner_step']:.2f}", common.fmt(m["seam_dv"]), common.fmt(m["max_inner_dv"]),
             f"{m['seam_dv'] / m['max_inner_dv']:.2f}"] for k, m in table.items()]
    md = (f"# Rhythmic primitive: continuity at the cycle seam\n\nModel: {source}; held-out shaking demo with a "
          f"{gap} rad gap between its end and start; {scale.rhythmic_cycles} cycles of {period:.1f} s, "
          f"{POINTS_PER_CYCLE} points per cycle; max over the 7 joints. The learned cycle stays within "
          f"{fit_err:.3f} rad of the gapped demonstration.\n\n"
          + common.markdown_table(["trajectory", "seam step (rad)", "max in-cycle step", "ratio",
                                   "seam Δv (rad/s)", "max in-cycle Δv", "ratio"], rows))
    files += common.write_outputs(out, "rhythmic", {"meta": meta, "seam": table}, md)
    return {"meta": meta, "seam": table, "files": [str(f) for f in files]}


def plot(metrics: dict, joint_names, period: float, cycles: int, out: pathlib.Path) -> list[pathlib.Path]:
    import matplotlib.pyplot as plt

    p = POINTS_PER_CYCLE
    t = np.arange(cycles * p) * period / p
    keys = list(metrics)
    styles = {keys[0]: dict(color="0.55", lw=2.2), keys[1]: dict(color="C0", lw=1.3),
              keys[2]: dict(color="C1", lw=1.0, ls="--")}
    d = len(joint_names)
    fig, axes = plt.subplots(d, 1, figsize=(8, 1.35 * d), sharex=True)
    for j, ax in enumerate(axes):
        for k in keys:
            ax.plot(t, metrics[k]["trajectory"][:, j], label=k, **styles[k])
        for c in range(1, cycles):
            ax.axvline(c * period, color="0.8", lw=0.8, ls=":")
        ax.set_ylabel(joint_names[j], fontsize=7)
        ax.tick_params(labelsize=7)
    axes[0].legend(fontsize=7, ncol=3, loc="lower left", bbox_to_anchor=(0, 1.02))
    axes[-1].set_xlabel("time (s)")
    fig.tight_layout()
    f1 = out / "rhythmic_cycles.png"
    fig.savefig(f1, dpi=90)
    plt.close(fig)

    # zoom on the seam of the most moving joint (the paper shows the WAM's second joint)
    j = int(np.argmax(np.ptp(metrics[keys[1]]["trajectory"], axis=0)))
    sl = slice(p - 12, p + 12)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3))
    for k in keys:
        y = metrics[k]["trajectory"][:, j]
        a1.plot(t[sl], y[sl], marker=".", label=k, **styles[k])
        v = np.diff(y) / (period / p)
        a2.plot(t[:-1][sl], v[sl], marker=".", **styles[k])
    for a in (a1, a2):
        a.axvline(period, color="0.6", ls=":", lw=1)
        a.set_xlabel("time (s)")
    a1.set_ylabel(f"{joint_names[j]} (rad)")
    a2.set_ylabel(f"{joint_names[j]} velocity (rad/s)")
    a1.set_title("position around the first seam", fontsize=9)
    a2.set_title("velocity around the first seam", fontsize=9)
    a1.legend(fontsize=6)
    fig.tight_layout()
    f2 = out / "rhythmic_seam.png"
    fig.savefig(f2, dpi=90)
    plt.close(fig)
    return [f1, f2]
