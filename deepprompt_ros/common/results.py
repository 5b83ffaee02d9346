"""The result codes of the package's services and actions, and the error that carries one.

:class:`Code` has the values of the constants of ``deepprompt_msgs/msg/ResultCode``, the one set
of result codes of every service and action of the package. Code that cannot carry out a request
(the primitive server's logic, its control loop) raises :class:`RequestError` with a code and a
message that says what was wrong and what is expected; the node turns it into the response's
``ResultCode`` and message. Plain Python: nothing here needs rclpy or the message packages.
"""
from __future__ import annotations

import enum

__all__ = ["Code", "RequestError"]


class Code(enum.IntEnum):
    """Result codes; the same values as the constants of ``deepprompt_msgs/msg/ResultCode``."""

    SUCCESS = 0
    INVALID_REQUEST = 1
    UNKNOWN_PRIMITIVE = 2
    UNKNOWN_HANDLE = 3
    INVALID_VIA_POINT = 4
    INVALID_CONTEXT = 5
    INVALID_IMAGE = 6
    REFINEMENT_UNREACHABLE = 7
    HANDLE_LIMIT = 8
    ROBOT_STATE_STALE = 9
    LIMIT_VIOLATION = 10
    CANCELED = 11
    PREEMPTED = 12
    NO_ACTIVE_EXECUTION = 13
    RECORDING_ACTIVE = 14
    NOT_RECORDING = 15
    INTERNAL_ERROR = 99


class RequestError(Exception):
    """A request that cannot be carried out: ``code`` and an actionable ``message``."""

    def __init__(self, code: Code, message: str):
        super().__init__(message)
        self.code = Code(code)
        self.message = message
