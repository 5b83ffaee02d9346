"""ros/fastpath/realtime.py: thread names, SCHED_FIFO requests (granted or refused with a reason),
CPU affinity, the switch interval, gc freezing and the collection monitor; and that the stream
loop's threads take their name and priority through the injected ``thread_setup``."""
import gc
import os
import sys
import threading

import pytest

from deepprompt_ros.ros.fastpath import realtime


def _comm(native_id: int) -> str:
    with open(f"/proc/self/task/{native_id}/comm") as f:
        return f.read().strip()


def _in_thread(fn):
    out = {}

    def run():
        out["native_id"] = threading.get_native_id()
        out["result"] = fn()
        out["comm"] = _comm(out["native_id"])

    t = threading.Thread(target=run)
    t.start()
    t.join()
    return out


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="thread names through prctl: Linux")
def test_name_os_thread_sets_the_kernel_name_truncated_to_15_bytes():
    out = _in_thread(lambda: realtime.name_os_thread("a_rather_long_thread_name"))
    assert out["comm"] == "a_rather_long_t"


def test_set_fifo_priority_is_granted_or_says_why_and_leaves_the_thread_unchanged():
    def ask():
        why = realtime.set_fifo_priority(1)
        return why, os.sched_getscheduler(0)

    out = _in_thread(ask)
    why, policy = out["result"]
    if why:
        assert "SCHED_FIFO priority 1 refused" in why and "normal scheduling" in why
        assert policy == os.SCHED_OTHER
    else:
        assert policy == os.SCHED_FIFO


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="thread names through prctl: Linux")
def test_prepare_thread_names_and_asks_for_a_priority_only_when_positive():
    out = _in_thread(lambda: (realtime.prepare_thread("worker_x", 0), os.sched_getscheduler(0)))
    assert out["result"] == ("", os.SCHED_OTHER)
    assert out["comm"] == "worker_x"
    out = _in_thread(lambda: realtime.prepare_thread("worker_y", 1))
    assert out["comm"] == "worker_y"
    assert out["result"] == "" or "refused" in out["result"]


def test_set_cpu_affinity_refuses_a_cpu_that_does_not_exist_and_keeps_the_mask():
    before = os.sched_getaffinity(0)
    why = realtime.set_cpu_affinity(10_000, "the test process")
    assert why.startswith("control_cpu 10000 refused (") and "the test process runs on any of CPUs" in why
    assert os.sched_getaffinity(0) == before


def test_set_switch_interval_returns_the_previous_value():
    old = sys.getswitchinterval()
    try:
        assert realtime.set_switch_interval(0.0002) == old
        assert sys.getswitchinterval() == pytest.approx(0.0002)
    finally:
        sys.setswitchinterval(old)


def test_freeze_startup_objects_freezes_and_the_monitor_counts_collections():
    try:
        n = realtime.freeze_startup_objects()
        assert n == gc.get_freeze_count() and n > 0
    finally:
        gc.unfreeze()
    mon = realtime.GcMonitor()
    try:
        gc.collect(0)
        gc.collect(2)
        assert mon.count[0] >= 1 and mon.count[2] >= 1
        assert mon.total_s >= mon.max_s > 0.0
        assert "garbage collections (generations 0/1/2:" in mon.summary()
        mon.reset()
        assert mon.count == [0, 0, 0] and mon.total_s == 0.0
    finally:
        mon.close()
    assert mon._callback not in gc.callbacks
    mon.close()  # twice: nothing happens


def test_stream_loop_threads_use_the_injected_thread_setup():
    from deepprompt_ros.execution.controller import ExecutionController
    from deepprompt_ros.execution.stream_loop import StreamLoop
    from deepprompt_ros.execution.limits import JointLimits
    from deepprompt_ros.server.config import ServerConfig

    import numpy as np

    cfg = ServerConfig(realtime_priority=7)
    limits = JointLimits(np.full(2, -3.0), np.full(2, 3.0), np.full(2, 1.0), np.full(2, 5.0), np.full(2, 50.0))
    calls = []
    loop = StreamLoop(ExecutionController(limits, 0.001, cfg), cfg, publish_trajectory=lambda snap: None,
                      thread_setup=lambda name, prio: calls.append((name, prio)) or f"refused {name}")
    loop.start(threaded=True)
    try:
        assert loop.started.wait(5.0)
    finally:
        loop.shutdown()
    assert ("control_loop", 7) in calls and ("jtc_publisher", 0) in calls
    assert loop.priority_error == "refused control_loop"
