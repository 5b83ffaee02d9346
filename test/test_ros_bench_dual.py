"""Smoke run of bench/bench_dual.py --quick (its own processes over real DDS): one Gen3 lite streaming
alone, then two in their own namespaces at once, every figure measured and the last line's two figures
what they claim to be (speed itself is judged by `make bench`, not by tests)."""
import pathlib
import subprocess
import sys

import pytest
from deepprompt_msgs.msg import ResultCode

BENCH = pathlib.Path(__file__).resolve().parent.parent / "bench" / "bench_dual.py"


def test_dual_benchmark_quick_mode_measures_both_arms_against_one_alone():
    out = subprocess.run([sys.executable, str(BENCH), "--quick"], capture_output=True, text=True, timeout=600,
                         start_new_session=True)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    last = {k: float(v) for k, v in (kv.split("=") for kv in out.stdout.strip().splitlines()[-1].split())}
    assert set(last) == {"dual_stream_hz_min", "dual_missed_ratio"}
    table = {row[0]: row[1] for row in map(str.split, out.stdout.splitlines()) if len(row) == 2}
    arms = ("arm_a", "arm_b")
    # each arm streamed in phase 2 (2 s recorded at 1 kHz), and so did the arm alone in phase 1
    assert all(int(table[f"dual_{arm}_missed"]) >= 0 and float(table[f"dual_{arm}_stream_hz"]) > 0 for arm in arms)
    assert float(table["alone_stream_hz"]) > 0 and int(table["alone_missed"]) >= 0
    assert last["dual_stream_hz_min"] == pytest.approx(min(float(table[f"dual_{arm}_stream_hz"]) for arm in arms),
                                                       rel=1e-3)
    assert last["dual_missed_ratio"] == pytest.approx(
        (max(int(table[f"dual_{arm}_missed"]) for arm in arms) + 1) / (int(table["alone_missed"]) + 1), rel=1e-3)
    # every goal ran until the planner canceled it after the recording
    assert {int(table[k]) for k in ("alone_code", "dual_arm_a_code", "dual_arm_b_code")} == {ResultCode.CANCELED}
    assert table["goals_through"] == "3"
    assert table["foreign_nodes"] == "0", table["foreign_node_names"]
