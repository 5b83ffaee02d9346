"""Smoke run of bench/bench_method.py --quick: every figure of its last line is there, finite and in
its range, and agrees with the table it summarizes (the figures themselves are judged by `make bench`)."""
import math
import pathlib
import subprocess
import sys

import pytest

BENCH = pathlib.Path(__file__).resolve().parent.parent / "bench" / "bench_method.py"
LAST = {"small_data_ratio", "context_ratio", "bimodal_on_mode", "via_met_share", "promp_via_met_share"}
VIA_SETS, BIMODAL_SAMPLES = 12, 100  # bench_method.QUICK


@pytest.fixture(scope="module")
def run():
    out = subprocess.run([sys.executable, str(BENCH), "--quick"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    lines = out.stdout.strip().splitlines()
    last = {k: float(v) for k, v in (kv.split("=") for kv in lines[-1].split())}
    table = {ln.split()[0]: float(ln.split()[1]) for ln in lines[1:-1]}
    return last, table


def test_last_line_has_every_figure_finite_and_in_range(run):
    last, _ = run
    assert set(last) == LAST
    assert all(math.isfinite(v) for v in last.values()), last
    assert last["small_data_ratio"] > 0 and last["context_ratio"] > 0
    for name, n in (("bimodal_on_mode", BIMODAL_SAMPLES), ("via_met_share", VIA_SETS), ("promp_via_met_share", VIA_SETS)):
        assert 0.0 <= last[name] <= 1.0, (name, last[name])
        assert last[name] * n == pytest.approx(round(last[name] * n), abs=1e-6), (name, last[name])  # k of n


def test_ratios_are_the_table_s_mses(run):
    last, t = run
    assert last["small_data_ratio"] == pytest.approx(t["small_data_deepprompt_mse"] / t["small_data_promp_mse"],
                                                     rel=1e-3)
    others = [t[f"context_{k}_mse"] for k in ("promp", "cnmp", "cnmp_indep", "vae_cnmp", "vae_cnmp_indep")]
    assert all(v > 0 for v in others)
    # the denominator is the BEST of ProMP and the four deep baselines
    assert last["context_ratio"] == pytest.approx(t["context_deepprompt_mse"] / min(others), rel=1e-3)
    # on a mode = on the + mode or on the − mode (disjoint)
    assert last["bimodal_on_mode"] == pytest.approx(t["bimodal_on_pos"] + t["bimodal_on_neg"], abs=1e-9)
    # a share of 1 means every set's error is within 1e-6 rad, so is its median; a median above means a miss
    for share, med in (("via_met_share", "via_met_median_err_rad"), ("promp_via_met_share", "promp_via_met_median_err_rad")):
        if t[med] > 1e-6:
            assert last[share] <= 0.5, (share, last[share], t[med])
        else:
            assert last[share] >= 0.5, (share, last[share], t[med])
