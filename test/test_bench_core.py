"""Smoke run of bench/bench_core.py --quick: every figure is measured, finite and printed on the last
line, and the figures agree with what they claim to be (speed itself is judged by `make bench`, not
by tests)."""
import math
import pathlib
import subprocess
import sys

import pytest

BENCH = pathlib.Path(__file__).resolve().parent.parent / "bench" / "bench_core.py"
#: --quick: 10 refinements, alternating sets built to be reachable and held-out sets
N_BUILT = N_HELDOUT = 5


@pytest.fixture(scope="module")
def last():
    out = subprocess.run([sys.executable, str(BENCH), "--quick"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    return {k: float(v) for k, v in (kv.split("=") for kv in out.stdout.strip().splitlines()[-1].split())}


def test_core_benchmark_quick_mode_reports_every_figure(last):
    assert set(last) == {"condition_ms", "promp_condition_ms", "condition_ratio", "handler_ms", "handler_gap_ms",
                         "handler_gap_cpu_ms", "refine_max_err_rad", "refine_met_share", "refine_start_err_rad",
                         "refine_steps", "refine_ms", "refine_ms_p90", "refine_heldout_max_err_rad",
                         "refine_heldout_met_share", "train_samples_per_s"}
    assert all(math.isfinite(v) for v in last.values()), last  # no figure is NaN for want of data
    assert last["condition_ratio"] == pytest.approx(last["condition_ms"] / last["promp_condition_ms"], rel=1e-4)
    # the server handler does more than the bare conditioning (request checks, handle, preview)
    assert last["handler_ms"] > last["condition_ms"]
    # CPU time of the handler's thread cannot exceed its wall time by more than clock granularity
    assert last["handler_gap_cpu_ms"] <= 1.5 * last["handler_gap_ms"]


def test_refinement_figures_cover_every_set_built_to_be_reachable(last):
    share, err = last["refine_met_share"], last["refine_max_err_rad"]
    for name, n in (("refine_met_share", N_BUILT), ("refine_heldout_met_share", N_HELDOUT)):
        assert last[name] * n == pytest.approx(round(last[name] * n), abs=1e-6), (name, last[name])  # k of n sets
        assert 0.0 <= last[name] <= 1.0
    # the max error is over EVERY built set, met or not: above the tolerance exactly when one was missed
    assert (share < 1.0) == (err > 1e-6), (share, err)
    # refinement moves every built set far closer than the posterior's mean left it, or to the tolerance
    # when the conditioning left it near (a split latent's exact conditioning: ~1e-6 rad already)
    assert err < max(0.1 * last["refine_start_err_rad"], 1e-6), (err, last["refine_start_err_rad"])
    # iterations are counted over the met sets only (-1: none met)
    assert (1 <= last["refine_steps"] <= 200) if share > 0 else last["refine_steps"] == -1, last["refine_steps"]
    # held-out sets are reported on their own: their error is not folded into the built sets' figure
    assert (last["refine_heldout_met_share"] < 1.0) == (last["refine_heldout_max_err_rad"] > 1e-6)
