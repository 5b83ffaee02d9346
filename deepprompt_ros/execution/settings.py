"""The control loop's settings, declared once as parameters.

:class:`LoopSettings` is a frozen dataclass whose fields are made with
:func:`~deepprompt_ros.common.params.param` (type, default, description, inclusive range, unit),
checked on construction (every invalid value reported at once in a
:class:`~deepprompt_ros.common.params.ConfigError`). It holds every setting that
:class:`~deepprompt_ros.execution.controller.ExecutionController` and
:class:`~deepprompt_ros.execution.stream_loop.StreamLoop` read, and nothing else, so that
execution depends on no caller's configuration. The primitive server's configuration
(:class:`deepprompt_ros.server.config.ServerConfig`) is a subclass: these fields are ROS parameters
of primitive_server under the same names, declared here only.
"""
from __future__ import annotations

import dataclasses

from deepprompt_ros.common import params
from deepprompt_ros.common.params import param

__all__ = ["LoopSettings"]


@dataclasses.dataclass(frozen=True)
class LoopSettings:
    """Settings of the command stream and of the thread that runs it.

    Every field is one parameter: its annotation is the type, its default the default, and its
    metadata the description and the valid range (inclusive).
    """

    # -- the command stream
    lookahead_ticks: int = param(30, "The command stream is computed this many control periods ahead; the "
                                 "JointTrajectory messages carry these future samples (and the reaction time "
                                 "to cancel / SetPhaseRate / a new goal is this long).", min=1, max=2000)
    tracking_horizon: float = param(0.01, "Look-ahead of the Ruckig tracking of the primitive.",
                                    min=0.001, max=0.5, unit="s")
    position_margin: float = param(0.01, "Targets are kept this far inside the URDF position limits.",
                                   min=0.0, max=0.5, unit="rad")
    approach_tolerance: float = param(0.01, "Farther than this (max over joints) from the primitive's start, "
                                      "the robot first moves to the start (time-optimal, within limits) and "
                                      "then starts the phase clock.", min=0.0, max=10.0, unit="rad")
    phase_rate_ramp_time: float = param(0.2, "SetPhaseRate changes the phase rate linearly over this time "
                                        "(continuous phase velocity).", min=0.0, max=60.0, unit="s")
    # -- faults: the goal brakes to rest
    stale_timeout: float = param(0.2, "No joint_states for this long: execution stops (brakes) with "
                                 "ROBOT_STATE_STALE; Execute is refused if the last message is older. A goal at most "
                                 "this long after the last published command starts from that command, "
                                 "else from the measured state.",
                                 min=0.001, max=60.0, unit="s")
    max_tracking_error: float = param(0.0, "Abort with LIMIT_VIOLATION (braking) when |commanded - measured| "
                                      "exceeds this on any joint; 0 = no bound.", min=0.0, max=10.0, unit="rad")
    # -- JointTrajectory output
    trajectory_rate_hz: float = param(50.0, "Rate of JointTrajectory messages.", min=1.0, max=1000.0, unit="Hz")
    trajectory_points: int = param(3, "Points of the look-ahead in each JointTrajectory message (evenly spaced "
                                    "over lookahead_ticks); a braking tail to rest follows them.", min=1, max=100)
    # -- pacing of the control thread
    spin_wait: float = param(0.0, "'thread' mode: busy-wait this long before each deadline instead of "
                             "sleeping up to it (a sleep can wake up late by the operating system's timer "
                             "slack); 0 = sleep only. The busy wait burns CPU and holds the interpreter lock "
                             "while it runs.", min=0.0, max=0.01, unit="s")
    realtime_priority: int = param(50, "SCHED_FIFO priority of the control thread ('thread' mode; with "
                                   "loop_process, of every thread of the control process, so that none "
                                   "holding the interpreter lock is preempted by another process); 0 = normal "
                                   "scheduling. Needs CAP_SYS_NICE (root, or rtprio in limits.conf); refused "
                                   "-> a warning, normal scheduling (as ros2_control's controller_manager).",
                                   min=0, max=99)

    def __post_init__(self):
        params.validate(self)
