"""Process and thread settings for the control-rate paths: real-time scheduling (SCHED_FIFO), CPU
affinity, the interpreter's switch interval, garbage-collector freezing and OS thread names.

Every such setting of primitive_server, its control process and sim_bridge goes through this
module, in one style: a function that applies it to the calling thread (or the process) and
returns ``''`` or why it was refused (the setting is then unchanged); nothing raises for a
refusal. No rclpy import: the ROS-free stream loop
(:class:`~deepprompt_ros.execution.stream_loop.StreamLoop`) receives :func:`prepare_thread` as its
``thread_setup`` callable.
"""
from __future__ import annotations

import gc
import os
import sys
import threading
import time

__all__ = ["GcMonitor", "freeze_startup_objects", "name_os_thread", "set_fifo_priority", "set_switch_interval",
           "set_cpu_affinity", "prepare_thread"]


class GcMonitor:
    """Counts the interpreter's cyclic garbage collections and the time they took (``gc.callbacks``).

    A collection holds the interpreter lock: a full one over a node's start-up objects (torch,
    numpy, rclpy, the models: hundreds of thousands of objects in primitive_server) stalls every
    thread for as long as the scan takes. Nodes therefore call ``gc.freeze()`` once started
    (:func:`freeze_startup_objects`), after which collections only scan what was allocated since.
    """

    def __init__(self):
        self.count = [0, 0, 0]      # per generation
        self.total_s = 0.0
        self.max_s = 0.0
        self._t0 = 0.0
        gc.callbacks.append(self._callback)

    def _callback(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._t0 = time.perf_counter()
            return
        dt = time.perf_counter() - self._t0
        self.count[info["generation"]] += 1
        self.total_s += dt
        self.max_s = max(self.max_s, dt)

    def reset(self) -> None:
        self.count, self.total_s, self.max_s = [0, 0, 0], 0.0, 0.0

    def close(self) -> None:
        if self._callback in gc.callbacks:
            gc.callbacks.remove(self._callback)

    def summary(self) -> str:
        return (f"{sum(self.count)} garbage collections (generations 0/1/2: {'/'.join(map(str, self.count))}), "
                f"{self.total_s * 1e3:.1f} ms in total, longest {self.max_s * 1e3:.2f} ms")


def freeze_startup_objects() -> int:
    """Collect once, then move every object alive to the permanent generation (``gc.freeze``):
    later collections skip them (see :class:`GcMonitor`). Returns the number of objects frozen."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def name_os_thread(name: str) -> None:
    """Give the calling thread ``name`` (<= 15 bytes) in the OS too (``top -H``, /proc/<pid>/task/*/comm),
    so that per-thread CPU can be read from outside; Linux only, silently nothing elsewhere."""
    try:
        import ctypes

        ctypes.CDLL(None).prctl(15, name.encode()[:15], 0, 0, 0)  # PR_SET_NAME
    except (OSError, AttributeError):
        pass


def set_fifo_priority(priority: int) -> str:
    """SCHED_FIFO ``priority`` for the calling thread; '' or why it was refused (then unchanged)."""
    if not hasattr(os, "sched_setscheduler"):
        return "SCHED_FIFO is not available on this platform; normal scheduling"
    try:
        os.sched_setscheduler(threading.get_native_id(), os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, PermissionError) as exc:
        return f"SCHED_FIFO priority {priority} refused ({exc}); normal scheduling"
    return ""


def set_switch_interval(seconds: float) -> float:
    """sys.setswitchinterval(seconds); returns the previous value."""
    old = sys.getswitchinterval()
    sys.setswitchinterval(seconds)
    return old


def set_cpu_affinity(cpu: int, what: str = "this process") -> str:
    """Pin the calling process to CPU ``cpu`` (``os.sched_setaffinity``; threads created afterwards
    inherit it); '' or why it was refused (then unchanged). ``what`` names the process in the
    message."""
    try:
        os.sched_setaffinity(0, {cpu})
    except (OSError, ValueError, AttributeError) as exc:
        where = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else "all"
        return f"control_cpu {cpu} refused ({exc}); {what} runs on any of CPUs {where}"
    return ""


def prepare_thread(name: str, fifo_priority: int = 0) -> str:
    """Name the calling thread (:func:`name_os_thread`) and, if ``fifo_priority`` > 0, ask for
    SCHED_FIFO at that priority; '' or why the priority was refused."""
    name_os_thread(name)
    return set_fifo_priority(fifo_priority) if fifo_priority > 0 else ""
