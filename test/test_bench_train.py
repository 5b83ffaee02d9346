"""Smoke run of bench/bench_train.py --quick: one `train` run of 2 processes under torchrun and two of one
process; every figure is measured, finite and printed on the last line, and the ratios are those of the
figures (speed itself is judged by `make bench`, not by tests)."""
import math
import pathlib
import subprocess
import sys

import pytest

BENCH = pathlib.Path(__file__).resolve().parent.parent / "bench" / "bench_train.py"


def test_train_benchmark_quick_mode_reports_every_figure():
    out = subprocess.run([sys.executable, str(BENCH), "--quick"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-6000:]  # (a failed run's message: up to ~4500 chars)
    last = {k: float(v) for k, v in (kv.split("=") for kv in out.stdout.strip().splitlines()[-1].split())}
    assert set(last) == {"train_single_samples_per_s", "train_ddp_samples_per_s", "train_ddp_speedup",
                         "train_single_1t_samples_per_s", "train_ddp_over_1t"}
    assert all(math.isfinite(v) and v > 0 for v in last.values()), last
    # the printed ratios are the figures' (4 significant digits on the line)
    assert last["train_ddp_speedup"] == pytest.approx(
        last["train_ddp_samples_per_s"] / last["train_single_samples_per_s"], rel=1e-3)
    assert last["train_ddp_over_1t"] == pytest.approx(
        last["train_ddp_samples_per_s"] / last["train_single_1t_samples_per_s"], rel=1e-3)
