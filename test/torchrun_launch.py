"""Launching ``torchrun`` (``python -m torch.distributed.run``) from the tests: a free port for its
rendezvous, and runs whose whole process tree is stopped when they overrun their time (``torchrun``
starts the training processes as its children; killing ``torchrun`` alone would leave them running).

Imported by the test files as ``torchrun_launch`` (pytest puts ``test/`` on ``sys.path``).
"""
from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys

TORCHRUN = [sys.executable, "-m", "torch.distributed.run"]


def free_port() -> int:
    """A TCP port on 127.0.0.1 free now (the OS's choice; another program could take it before torchrun binds
    it, which the OS's ephemeral-port rotation makes unlikely)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start(cmd: list[str], **kw) -> subprocess.Popen:
    """``cmd`` in its own process group (stopped as a whole by :func:`stop`), its output captured as text."""
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            **kw)


def stop(proc: subprocess.Popen) -> None:
    """Kill ``proc``'s process group (torchrun and the processes it started) if ``proc`` is still running."""
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()


def run(cmd: list[str], timeout: float, **kw) -> subprocess.CompletedProcess:
    """:func:`subprocess.run` with captured text output, its whole process group killed when it overruns
    ``timeout`` (then :class:`subprocess.TimeoutExpired` is raised)."""
    proc = start(cmd, **kw)
    try:
        out, err = proc.communicate(timeout=timeout)
    finally:
        stop(proc)
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)
