"""The messages between primitive_server and its control process (``loop_process: true``).

The server sends :data:`LoopCommand` messages, the control process answers with
:data:`LoopReport` messages, each a frozen dataclass pickled over one Unix socket pair
(``multiprocessing.connection.Connection``; see :mod:`deepprompt_ros.ros.control_process` for the
link's lifetime). A goal is named on the link by an integer key that the server gives it.

server -> control process:

* :class:`LoopSetup` once, first: what the process needs to build its node and loop;
* :class:`StartGoal` (an Execute goal's plan; it preempts the running goal), :class:`CancelGoal`,
  :class:`SetGoalRate` (SetPhaseRate), :class:`StopLoop` (the server is shutting down).

control process -> server:

* :class:`LoopReady` once its node, publishers and control thread run;
* :class:`LoopStatus` every status period: the newest joint_states' reception time and the
  running goal's stage and progress (Execute feedback, SetPhaseRate's check, the stale check of
  a new Execute);
* :class:`GoalDone` when a goal's last sample has been published.
"""
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Union

if TYPE_CHECKING:  # annotations only: this module imports nothing at run time
    from deepprompt_ros.execution.limits import JointLimits
    from deepprompt_ros.execution.plan import ExecutionPlan
    from deepprompt_ros.execution.controller import Outcome, Progress, Stage
    from deepprompt_ros.execution.settings import LoopSettings

__all__ = ["LoopSetup", "StartGoal", "CancelGoal", "SetGoalRate", "StopLoop", "LoopReady", "LoopStatus",
           "GoalDone", "LoopCommand", "LoopReport"]


# ------------------------------------------------------------------------------------------------
# server -> control process
# ------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class LoopSetup:
    """Everything the control process builds its node and loop from.

    Attributes
    ----------
    limits : JointLimits
    dt : float
        Control period (s).
    config : LoopSettings
        The loop's settings. The server sends its ServerConfig (a LoopSettings subclass): the
        control process also reads the settings of its process and node from it (``control_cpu``,
        ``gil_switch_interval``, ``fast_path``, ``trajectory_stamp``).
    joint_names : tuple of str
        The robot's joints, in its order.
    command_topic, trajectory_topic, joint_states_topic : str
        Resolved by the server (its namespace and remappings apply); '' = that output is off.
    node_name, namespace : str
        Of the control process's node.
    """

    limits: JointLimits
    dt: float
    config: LoopSettings
    joint_names: tuple[str, ...]
    command_topic: str
    trajectory_topic: str
    joint_states_topic: str
    node_name: str
    namespace: str


@dataclasses.dataclass(frozen=True)
class StartGoal:
    """Execute ``plan`` as goal ``key``; it preempts the running goal unless that one is newer
    (``order``: the goal's acceptance order, see ExecutionGoal)."""

    key: int
    plan: ExecutionPlan
    order: int | None = None


@dataclasses.dataclass(frozen=True)
class CancelGoal:
    """Brake goal ``key`` to rest (nothing if it no longer runs)."""

    key: int


@dataclasses.dataclass(frozen=True)
class SetGoalRate:
    """Change the phase rate of goal ``key`` (nothing if it no longer runs)."""

    key: int
    phase_rate: float


@dataclasses.dataclass(frozen=True)
class StopLoop:
    """Stop the loop, destroy the node and exit."""


LoopCommand = Union[LoopSetup, StartGoal, CancelGoal, SetGoalRate, StopLoop]


# ------------------------------------------------------------------------------------------------
# control process -> server
# ------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class LoopReady:
    """The process runs (``pid``); ``warnings``: its start-up warnings joined by '; ' (a refused
    priority or CPU), '' = none."""

    pid: int
    warnings: str


@dataclasses.dataclass(frozen=True)
class LoopStatus:
    """The newest joint_states' reception (time.monotonic() of the control process; None = none
    yet), the running goal (key None = none runs; then stage and progress are None too) and why the
    joint_states received since the newest accepted one were refused ('' = none was)."""

    joint_states_stamp: float | None
    key: int | None
    stage: Stage | None
    progress: Progress | None
    refused: str = ""


@dataclasses.dataclass(frozen=True)
class GoalDone:
    """Goal ``key`` ended with ``outcome``; ``loop_summary``: the loop's statistics so far."""

    key: int
    outcome: Outcome
    loop_summary: str


LoopReport = Union[LoopReady, LoopStatus, GoalDone]
