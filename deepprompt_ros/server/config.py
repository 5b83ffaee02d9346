"""Parameters of the primitive server, declared once.

:class:`ServerConfig` is a frozen dataclass whose fields are made with
:func:`~deepprompt_ros.common.params.param` (type, default, description, inclusive range or
choices, unit); the control loop's settings are the fields of its base class
:class:`~deepprompt_ros.execution.settings.LoopSettings`, declared there. The node declares its
ROS parameters from :data:`PARAMETERS`, the values are checked by
:mod:`deepprompt_ros.common.params` (every invalid one reported at once in a
:class:`~deepprompt_ros.common.params.ConfigError`), and
``python -m deepprompt_ros.server.config`` prints the Markdown table of them.
:func:`robot_limits` applies the velocity / acceleration / jerk scales to a robot's limits.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import numpy as np

from deepprompt_ros.common import params
from deepprompt_ros.common.params import param
from deepprompt_ros.execution.limits import JointLimits
from deepprompt_ros.execution.settings import LoopSettings
from deepprompt_ros.primitive.latent import PLANNER_VIA_NOISE

__all__ = ["ServerConfig", "PARAMETERS", "robot_limits"]


@dataclasses.dataclass(frozen=True)
class ServerConfig(LoopSettings):
    """Parameters of the primitive server (ROS parameters of the same names).

    Every field is one parameter: its annotation is the type, its default the default, and its
    metadata the description and the valid range (inclusive) or the allowed choices. The control
    loop's settings are the fields of the base class
    :class:`~deepprompt_ros.execution.settings.LoopSettings` (declared there, parameters of the
    server like the others); a ServerConfig is what the server hands to the loop.
    """

    # -- robot and primitives
    robot: str = param("gen3_lite", "Robot whose joint names and limits are used (robots.spec.load_robot: "
                       "'gen3_lite', 'wam' or an example-robot-data arm). Position limits come from its URDF.")
    primitives_file: str = param("", "YAML file listing the primitives to serve; '' = config/primitives.yaml "
                                 "of the package (installed share folder first, then the source tree).")
    models_dir: str = param("", "Folder of relative model paths in the primitives file; '' = the package's "
                            "models/ folders (installed share first, then the source tree).")
    # -- control loop
    control_rate_hz: float = param(0.0, "Rate of the phase clock and of the command stream; 0 = the robot's "
                                   "control rate (1000 Hz for the Gen3 lite).", min=0.0, max=10000.0, unit="Hz")
    loop_mode: str = param("thread", "Pacing of the control loop: 'thread' (dedicated thread, absolute "
                           "perf_counter deadlines) or 'timer' (ROS timer in its own callback group).",
                           choices=("thread", "timer"))
    gil_switch_interval: float = param(0.0002, "sys.setswitchinterval of the node process: the longest "
                                       "another Python thread keeps the interpreter lock while the control "
                                       "loop waits for it (Python's default is 0.005 s).",
                                       min=1e-5, max=0.1, unit="s")
    control_cpu: int = param(-1, "loop_process: pin the control process (all its threads) to this CPU "
                             "(os.sched_setaffinity, like ros2_control's cpu_affinity); -1 = any CPU. A CPU "
                             "the machine does not have -> a warning, not pinned.", min=-1, max=1023)
    loop_process: bool = param(True, "'thread' mode: run the control loop (command stream, JointTrajectory "
                               "output, joint_states reader) in a child process with its own interpreter, "
                               "so that service handlers and the 1 kHz loop do not share one interpreter "
                               "lock; false = a thread of the server's process. 'timer' mode is always "
                               "in-process.")
    fast_path: bool = param(True, "How the node talks to ROS. true: the services are answered by a thread of "
                            "their own that waits on them directly (not by the executor), commands and "
                            "JointTrajectory messages are published as pre-serialized bytes, and the control "
                            "thread takes joint_states from its subscription itself (deepprompt_ros.ros."
                            "fastpath; parts of it use rclpy internals). false: plain rclpy only (services "
                            "dispatched by the executor, messages built and published as rclpy messages, "
                            "joint_states through an executor callback); slower, for comparison or when an "
                            "rclpy release breaks the fast path. Same services, topics and behaviour either way.")
    velocity_scale: float = param(1.0, "Fraction of the robot's velocity limits used.", min=1e-3, max=1.0)
    acceleration_scale: float = param(1.0, "Fraction of the robot's acceleration limits used.", min=1e-3, max=1.0)
    jerk_scale: float = param(1.0, "Fraction of the robot's jerk limits used.", min=1e-3, max=1.0)
    execution_grid_points: int = param(4001, "The executed mean trajectory is decoded once per Execute on this "
                                       "many phases and interpolated at every control tick.", min=101, max=200001)
    derivative_step: float = param(0.005, "Phase step of the central differences that give the reference "
                                   "velocity and acceleration from the decoded grid.", min=1e-4, max=0.1)
    check_feasibility: bool = param(True, "Refuse Execute / SetPhaseRate (LIMIT_VIOLATION) when the mean "
                                    "trajectory leaves the position limits or needs more than the velocity "
                                    "limits at the requested phase rate.")
    default_duration: float = param(5.0, "Execute duration when the goal sets neither duration nor phase_rate "
                                     "(a primitive's own default in the primitives file wins).",
                                     min=0.01, max=86400.0, unit="s")
    feedback_rate_hz: float = param(20.0, "Rate of Execute feedback messages.", min=0.1, max=1000.0, unit="Hz")
    # -- outputs
    joint_states_topic: str = param("joint_states", "sensor_msgs/JointState input (measured robot state).")
    controller: str = param("joint_trajectory_controller", "JointTrajectory output goes to "
                            "'<controller>/joint_trajectory'; '' = no JointTrajectory output.")
    command_topic: str = param("joint_command", "sensor_msgs/JointState per control tick (names, positions, "
                               "velocities in the robot's joint order; what sim_bridge follows); '' = off.")
    trajectory_stamp: str = param("now", "header.stamp of JointTrajectory messages: 'now' (the time of the "
                                  "first sample, exact timing) or 'zero' (start on receipt).",
                                  choices=("now", "zero"))
    # -- handles and request bounds
    max_handles: int = param(64, "Number of stored conditioned distributions.", min=1, max=100000)
    handle_ttl: float = param(600.0, "A handle unused for this long is dropped; 0 = never.",
                              min=0.0, max=1e7, unit="s")
    evict_when_full: bool = param(True, "Full store: drop the least recently used handle (true) or refuse "
                                  "with HANDLE_LIMIT (false).")
    preview_points: int = param(100, "Default number of preview / sample phases.", min=2, max=100000)
    max_preview_points: int = param(10000, "Largest preview_points / n_points accepted.", min=2, max=1000000)
    preview_std_method: str = param("linearized", "Standard deviation of the preview: 'linearized' (first "
                                    "order in z: |∂μ_y/∂z| σ_z at the mean latent, one decoder Jacobian; exact "
                                    "where the decoder is linear in z) or 'sampled' (Monte Carlo over "
                                    "preview_std_samples trajectories: the decoder runs on preview_std_samples "
                                    "x preview_std_points phases). Blended handles are always sampled.",
                                    choices=("linearized", "sampled"))
    preview_std_samples: int = param(32, "Monte-Carlo trajectories behind a sampled standard deviation.",
                                     min=2, max=10000)
    preview_std_points: int = param(26, "The preview's standard deviation is estimated at this many evenly "
                                    "spaced phases (at most preview_points) and interpolated linearly in "
                                    "between (it varies slowly with the phase).", min=2, max=100000)
    max_via_points: int = param(1000, "Largest number of via-points (and blending-schedule knots) accepted.",
                                min=1, max=1000000)
    max_images: int = param(16, "Largest number of images in one image context.", min=1, max=1000)
    max_blend_parts: int = param(16, "Largest number of conditioned distributions one blended handle is made "
                                 "of, counted with repeats (a blend of a handle with itself has twice its "
                                 "parts): every part is evaluated at every phase the handle is decoded at.",
                                 min=2, max=1024)
    max_samples: int = param(1000, "Largest Sample.n_samples accepted.", min=1, max=1000000)
    max_sample_points: int = param(20000, "Largest n_samples x n_points of one Sample request: the trajectory "
                                   "points the decoder evaluates, which its time grows with.",
                                   min=100, max=100000000)
    refine_max_iterations: int = param(200, "Default refinement iteration budget (Condition."
                                       "refine_max_iterations = 0).", min=1, max=10000)
    refine_time_budget: float = param(0.5, "Wall time after which a Condition's refinement starts no further "
                                      "iteration: it ends with the best fit found and, unmet, with "
                                      "REFINEMENT_UNREACHABLE and a message saying the time budget ended it. The "
                                      "service thread answers one request at a time, so this bounds how long "
                                      "one Condition holds up the others.", min=0.01, max=600.0, unit="s")
    via_noise: float = param(PLANNER_VIA_NOISE, "Standard deviation of a planner's via-point in the exact "
                             "conditioning of a primitive with a linear latent block (latent_linear > 0), in units "
                             "of each joint's normalization std (the demonstrations' spread): via-points are hard "
                             "constraints, met to refine_tolerance by the conditioning (conditioned again with a "
                             "smaller noise when not). 0 = the primitive's own noise from training. Primitives "
                             "without a linear block do not use it.", min=0.0, max=1.0)
    refine_tolerance: float = param(1e-6, "Default refinement tolerance on the via-point error.",
                                    min=1e-12, max=1.0, unit="rad")
    max_cycles: int = param(100000, "Largest Execute.cycles accepted (rhythmic primitives).", min=1, max=10**9)

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> "ServerConfig":
        """Build from {name: value}; unknown names and invalid values are all reported at once."""
        return params.from_mapping(cls, values)


#: The specs of every field of :class:`ServerConfig`, in declaration order.
PARAMETERS: tuple[params.ParamSpec, ...] = params.specs_of(ServerConfig)


def robot_limits(spec, config: ServerConfig) -> JointLimits:
    """JointLimits in the robot's joint order from a RobotSpec (URDF position limits) and the
    velocity / acceleration / jerk scales of ``config``."""
    return JointLimits(lower=spec.lower, upper=spec.upper,
                       max_velocity=np.asarray(spec.velocity) * config.velocity_scale,
                       max_acceleration=np.asarray(spec.acceleration) * config.acceleration_scale,
                       max_jerk=np.asarray(spec.jerk) * config.jerk_scale, names=spec.joint_names)


if __name__ == "__main__":  # python -m deepprompt_ros.server.config: the parameter table (Markdown)
    print(params.markdown_table(PARAMETERS))
