"""Smoke run of bench/bench_core.py --quick: every figure is measured and printed on the last line
(speed itself is judged by `make bench`, not by tests)."""
import pathlib
import subprocess
import sys

BENCH = pathlib.Path(__file__).resolve().parent.parent / "bench" / "bench_core.py"


def test_core_benchmark_quick_mode_reports_every_figure():
    out = subprocess.run([sys.executable, str(BENCH), "--quick"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    last = {k: float(v) for k, v in (kv.split("=") for kv in out.stdout.strip().splitlines()[-1].split())}
    assert set(last) == {"condition_ms", "promp_condition_ms", "condition_ratio", "handler_ms", "handler_gap_ms",
                         "handler_gap_cpu_ms", "refine_max_err_rad", "refine_steps", "refine_ms", "refine_ms_p90",
                         "refine_unreachable", "refine_met_constructed", "train_samples_per_s"}
    # the server handler does more than the bare conditioning (request checks, handle, preview)
    assert last["handler_ms"] > last["condition_ms"] > 0
    assert last["handler_gap_ms"] > 0 and 0 < last["handler_gap_cpu_ms"] <= 1.5 * last["handler_gap_ms"]
    assert last["refine_max_err_rad"] <= 1e-6 and last["train_samples_per_s"] > 0
