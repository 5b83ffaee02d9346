"""Spinning a node process until it is asked to stop (SIGINT / SIGTERM, ``rclpy.shutdown``).

rclpy's signal handler shuts the context down asynchronously. An executor that is building its wait set
at that moment raises ``RCLError`` ("failed to initialize wait set: the given context is not valid")
instead of ``ExternalShutdownException`` (ros2/rclpy#398, ros2/ros2cli#854): a clean stop that would
otherwise end the process with a traceback and exit code 1.

A SIGINT that arrives while a callback is inside rclpy's C++ code (``deserialize_message`` building
the message's Python object) raises ``KeyboardInterrupt`` there, and pybind11 turns it into another
error (a ``TypeError`` "Unable to convert function return value") whose ``__cause__`` or
``__context__`` is the ``KeyboardInterrupt``: that is a stop too.
"""
from __future__ import annotations

from typing import Callable

import rclpy
from rclpy.executors import ExternalShutdownException

__all__ = ["spin_until_shutdown"]


def _interrupted(exc: BaseException) -> bool:
    """Whether ``exc`` was raised by, or while handling, a ``KeyboardInterrupt``."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def spin_until_shutdown(spin: Callable[[], None], context=None) -> None:
    """Run ``spin`` (``lambda: rclpy.spin(node)``, ``executor.spin``); return normally when the process
    is asked to stop: ``KeyboardInterrupt`` (also as the cause of another error), ``ExternalShutdownException``,
    or a ``RuntimeError`` (rclpy's ``RCLError``) raised once ``context`` (the default one when None) is shut
    down. Any other error, and a ``RuntimeError`` while the context is still running, is raised."""
    try:
        spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as exc:
        if _interrupted(exc):
            return
        if not isinstance(exc, RuntimeError) or rclpy.ok(context=context):
            raise
