"""``train --data DIR`` with no configuration: the model selection of ``auto_select`` runs on the
training demonstrations, every choice is printed and stored in the checkpoint, and the loaded model
conditions on via-points and meets them."""
import json
import os
import subprocess
import sys

import numpy as np

from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.data.demonstration import Demonstration
from deepprompt_ros.model.checkpoint import load_checkpoint
from deepprompt_ros.primitive.deep_promp import DeepProMP
from deepprompt_ros.primitive.latent import PLANNER_VIA_NOISE
from deepprompt_ros.training.basis import cv_basis_hyperparameters

N, T = 30, 80


def reach_family(n: int, seed: int) -> DemoDataset:
    """3 joints moving from a common start to a goal-dependent end (minimum-jerk-like profile) with a
    goal-dependent bump; context 'goal' (2,)."""
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, 1.0, T)
    s = 10 * x ** 3 - 15 * x ** 4 + 6 * x ** 5
    demos = []
    for i in range(n):
        g = rng.uniform(-1, 1, 2)
        q = np.stack([0.8 * g[0] * s + 0.2 * np.sin(np.pi * x) * g[1],
                      0.1 + 0.5 * g[1] * s,
                      -0.3 + 0.4 * (g[0] + g[1]) * s ** 2], 1) + 0.002 * rng.standard_normal((T, 3))
        demos.append(Demonstration(f"reach_{i:02d}", 3.0 * x, q, ("j1", "j2", "j3"), {"goal": g[None]}))
    return DemoDataset(tuple(demos), f"reach_family(seed={seed})")


def test_train_with_no_configuration_selects_records_and_the_model_meets_via_points(tmp_path):
    ds = reach_family(N, seed=0)
    folder = ds.save(tmp_path / "demos")
    out = tmp_path / "m.safetensors"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")  # the numpy of the cross-validation
    proc = subprocess.run([sys.executable, "-m", "deepprompt_ros.training.cli", "--data", str(folder),
                           "--out", str(out), "--steps", "120"], capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    summary = json.loads(lines[-1])
    chosen = [ln for ln in lines if ln.startswith("selected on the training demos: ")]
    assert len(chosen) == 1, proc.stdout
    ck = load_checkpoint(out)
    sel, cfg = ck.metadata["selection"], ck.config
    lin, res = sel["linear_part"], sel["residual"]
    # the linear part: the cross-validation's argmin on the 27 training demos (3 are the validation split)
    cv = lin["cross_validation"]
    assert cv["n_demos"] == ck.metadata["provenance"]["n_train"] == 27 and cv["folds"] == 5
    # structure and noise scored together by the executed mean (met as a planner's): ProMP's form or the row
    # that departs from it
    ref = cv["reference"]
    assert cv["meet"] and cv["cv_mse"] == (ref["departure_row"] if ref["best_kept"] else ref["row"])[5]
    train_ds, _ = ds.split(3, seed=0)  # train()'s split
    again = cv_basis_hyperparameters(train_ds, 100, folds=5, seed=0, meet=True, whole_noise=PLANNER_VIA_NOISE)
    # made on the training demos alone: the same rows, the same choices and scores up to the last bits (this
    # process and train's subprocess may run BLAS with different thread counts, which sum in another order:
    # up to 4e-9 relative measured on the worst-conditioned rows)
    assert [r[:5] for r in again["table"]] == [r[:5] for r in cv["table"]]
    np.testing.assert_allclose(np.array([r[5:] for r in again["table"]], dtype=float),
                               np.array([r[5:] for r in cv["table"]], dtype=float), rtol=1e-7, atol=0.0)
    for key in ("decoder_basis", "latent_linear", "basis_cov_reg", "basis_cov_reg_units", "via_noise"):
        assert lin[key] == cv[key] == ck.metadata["train_config"][key] == summary["selected"][key], key
    for key in ("decoder_basis", "latent_linear", "basis_cov_reg", "via_noise"):  # the log line names each
        assert f"{key} {cv[key]:g}" in chosen[0], (key, chosen[0])
    assert f"({cv['basis_cov_reg_units']})" in chosen[0]
    assert (cfg.decoder_basis, cfg.latent_linear, cfg.via_noise) == (lin["decoder_basis"], lin["latent_linear"],
                                                                     lin["via_noise"])
    assert cfg.latent_dim == cfg.latent_linear + 8  # a nonlinear block of 8 dimensions beside the linear one
    # the goals spread over a square: one mode, the PPCA of all training demos
    assert lin["linear_modes"] == lin["modes"]["n_modes"] == summary["selected"]["linear_modes"] == 1
    assert "linear_modes 1" in chosen[0] and "modes_fallback" not in sel
    # the residual: judged on the 3 validation demos, the decision in the file and in the model
    assert res["n_val"] == 3 and set(res["mse_with"]) == {"start", "5 via-points", "start + contexts"}
    assert res["kept"] == (res["relative_difference"] + res["standard_error"] < 0 and res["via_mean_ok"])
    assert cfg.residual_scale == (1.0 if res["kept"] else 0.0) == summary["selected"]["residual_scale"]
    assert ("residual kept" if res["kept"] else "residual dropped") in chosen[0]
    # the loaded model conditions on via-points of a held-out demo and meets them
    prim = DeepProMP.from_checkpoint(out)
    test = reach_family(1, seed=9).demos[0]
    y = test.resampled(100)
    x = np.linspace(0.0, 1.0, 100)
    sel_idx = np.array([0, 30, 55, 80, 99])
    lat = prim.condition(x[sel_idx], y[sel_idx], contexts=test.contexts)
    mean = prim.mean_trajectory(lat, x)
    assert np.abs(mean[sel_idx] - y[sel_idx]).max() < 0.01 * np.ptp(y, 0).max()
    assert np.sqrt(((mean - y) ** 2).mean()) < 0.05
    refined = prim.refine(lat, x[sel_idx], y[sel_idx])
    assert refined.reachable and np.abs(prim.mean_trajectory(refined.latent, x[sel_idx]) - y[sel_idx]).max() <= 1e-6
    # a planner's via-point off the demonstrations' family (the linear block keeps every direction: λ > 0)
    off = (y[50] + np.array([0.03, -0.02, 0.02]))[None]
    refined = prim.refine(prim.condition([0.5], off, contexts=test.contexts), [0.5], off)
    assert refined.reachable and np.abs(prim.mean_trajectory(refined.latent, np.array([0.5])) - off).max() <= 1e-6
    assert lin["basis_cov_reg"] > 0 and cfg.latent_linear >= 5 * 3
