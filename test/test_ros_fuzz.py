"""bench/bench_fuzz.py: its classification of answers (each bad answer is counted) and a short run
(``--quick``: 400 requests from 2 client processes against real sim_bridge and primitive_server
processes) whose figures must meet their targets."""
import importlib.util
import os
import pathlib
import subprocess
import sys
import time

import pytest

from deepprompt_ros.common.results import Code

BENCH = pathlib.Path(__file__).resolve().parent.parent / "bench" / "bench_fuzz.py"


@pytest.fixture(scope="module")
def fuzz():
    spec = importlib.util.spec_from_file_location("bench_fuzz", BENCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("answer,outcome", [
    (dict(answered=False), "unanswered"),
    (dict(answered=True, success=True, code=Code.SUCCESS, message=""), "ok"),
    (dict(answered=True, success=False, code=Code.UNKNOWN_HANDLE, message="unknown handle 'x'"), "refused"),
    (dict(answered=True, success=False, code=Code.INVALID_REQUEST, message=""), "no_message"),
    (dict(answered=True, success=False, code=Code.INVALID_VIA_POINT, message=" \n"), "no_message"),
    (dict(answered=True, success=False, code=Code.SUCCESS, message="refused"), "no_message"),
    (dict(answered=True, success=True, code=Code.LIMIT_VIOLATION, message="too fast"), "no_message"),
    (dict(answered=True, success=None, code=None), "no_message"),
    (dict(answered=True, success=False, code=Code.INTERNAL_ERROR, message="internal error: ..."), "internal_error"),
], ids=["no answer", "success", "refusal with code and message", "empty message", "blank message",
        "refusal with code SUCCESS", "success with a failure code", "no fields", "internal error"])
def test_every_answer_is_classified_and_a_refusal_without_message_is_counted(fuzz, answer, outcome):
    assert fuzz.classify(**answer) == outcome


def test_figures_count_the_outcomes_and_refuse_unknown_ones(fuzz):
    outcomes = ("ok", "refused", "refused", "no_message", "unanswered", "internal_error")
    records = [{"outcome": o, "answer_s": s} for o, s in zip(outcomes, (0.1, 2.5, 0.2, 0.3, 30.0, 0.4))]
    fig = fuzz.figures(records, crashes=2, wall_s=3.0)
    # the longest answer is over the answered requests (not the unanswered one's 30 s of waiting)
    assert fig == dict(fuzz_requests=6, fuzz_unanswered=1, fuzz_crashes=2, fuzz_no_message=1, fuzz_internal_errors=1,
                       fuzz_longest_answer_s=2.5, fuzz_wall_s=3.0, fuzz_requests_per_s=2.0)
    with pytest.raises(ValueError, match="unknown outcomes"):
        fuzz.figures([{"outcome": "lost"}], crashes=0, wall_s=1.0)


def test_a_process_that_ended_counts_as_not_alive(fuzz):
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()  # reaped: no /proc entry left
    assert fuzz._alive(os.getpid()) and not fuzz._alive(proc.pid)
    zombie = subprocess.Popen([sys.executable, "-c", "pass"])
    try:
        deadline = time.monotonic() + 30
        while fuzz._alive(zombie.pid) and time.monotonic() < deadline:  # exited, not yet reaped: a zombie
            time.sleep(0.05)
        assert not fuzz._alive(zombie.pid)
    finally:
        zombie.wait()


def test_quick_fuzzing_run_leaves_no_request_unanswered_no_crash_and_no_silent_refusal():
    out = subprocess.run([sys.executable, str(BENCH), "--quick"], capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    lines = out.stdout.strip().splitlines()
    last = {k: float(v) for k, v in (kv.split("=") for kv in lines[-1].split())}
    report = "\n".join(lines[-40:])
    assert last["fuzz_requests"] >= 400, report
    assert last["fuzz_unanswered"] == 0, report
    assert last["fuzz_crashes"] == 0, report
    assert last["fuzz_no_message"] == 0, report
    assert last["fuzz_internal_errors"] == 0, report
    # every accepted request is bounded (at most about refine_time_budget + 1 s of work): with 2 clients an
    # answer waits for at most the other client's request and its own, far from the 30 s timeout
    assert 0 < last["fuzz_longest_answer_s"] <= 5.0, report
    # every service and the action were called, and malformed requests met the server's checks
    table = {line.split()[0]: int(line.split()[1]) for line in lines if line.split()[:1] and line.split()[0] in (
        "condition", "blend", "sample", "list_primitives", "set_phase_rate", "goal", "cancel")}
    assert set(table) == {"condition", "blend", "sample", "list_primitives", "set_phase_rate", "goal", "cancel"}, report
    assert all(n > 0 for n in table.values()), report
    codes = next(line for line in lines if line.startswith("codes: "))
    for name in ("SUCCESS", "INVALID_REQUEST", "UNKNOWN_HANDLE", "INVALID_VIA_POINT", "PREEMPTED"):
        assert f"{name} " in codes, codes
