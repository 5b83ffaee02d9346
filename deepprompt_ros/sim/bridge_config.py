"""Parameters of the sim_bridge node (:mod:`deepprompt_ros.ros.sim_bridge`), declared once.

:class:`SimBridgeConfig` holds the node's parameters and :class:`ObjectConfig` the parameters
``objects.<name>.<field>`` of each object named in ``object_names``. Both are frozen dataclasses
made with :func:`~deepprompt_ros.common.params.param`: the node declares its ROS parameters from
them (:mod:`deepprompt_ros.ros.parameters`), ``docs/parameters.md`` is generated from them and
``config/sim_bridge.yaml`` shows their defaults. No rclpy here.
"""
from __future__ import annotations

import dataclasses

from deepprompt_ros.common.params import ConfigError, param, validate
from deepprompt_ros.sim.simulation import SHAPES

__all__ = ["SimBridgeConfig", "ObjectConfig", "MIN_RATE_HZ"]

#: Lowest physics rate other than 0 (= the robot's control rate).
MIN_RATE_HZ = 10.0


@dataclasses.dataclass(frozen=True)
class SimBridgeConfig:
    """Parameters of sim_bridge (ROS parameters of the same names; ranges are inclusive)."""

    robot: str = param("gen3_lite", "gen3_lite, wam, or a fixed-base arm of example-robot-data (panda, ur5, ...)")
    rate_hz: float = param(0.0, "physics steps and joint_states per simulated second; 0 = the robot's control "
                           "rate (1000 for gen3_lite and wam), else at least 10", min=0.0, max=5000.0, unit="Hz")
    real_time_factor: float = param(1.0, "simulated seconds per wall-clock second; 0 = as fast as possible",
                                    min=0.0, max=100.0)
    command_topic: str = param("joint_command", "sensor_msgs/JointState position targets with velocity "
                               "feed-forward")
    joint_states_topic: str = param("joint_states", "sensor_msgs/JointState output")
    joint_states_rate_hz: float = param(0.0, "joint_states messages per simulated second: every n-th physics "
                                        "step, n = round(rate_hz / joint_states_rate_hz); 0 = every step",
                                        min=0.0, max=5000.0, unit="Hz")
    publish_clock: bool = param(True, "publish the simulation time on /clock")
    fast_path: bool = param(True, "How the node talks to ROS. true: the simulation thread takes the joint "
                            "commands from their subscription itself (not through the executor) and reads the "
                            "numbers from the serialized message, and joint_states and /clock are published as "
                            "pre-serialized bytes (deepprompt_ros.ros.fastpath; parts of it use rclpy "
                            "internals). false: plain rclpy only (joint commands through an executor callback, "
                            "joint_states and /clock built and published as rclpy messages); slower, for "
                            "comparison or when an rclpy release breaks the fast path. Same topics, services "
                            "and behaviour either way.")
    initial_positions: tuple[float, ...] = param((), "start configuration, one value per joint; empty = the "
                                                 "robot's home", unit="rad")
    kinesthetic: bool = param(False, "start in kinesthetic (gravity-compensated) mode")
    guide_topic: str = param("guide_target", "geometry_msgs/PointStamped the end effector is pulled to "
                             "(NaN clears)")
    guide_stiffness: float = param(200.0, "guide spring stiffness", min=1.0, max=1e4, unit="N/m")
    guide_max_force: float = param(30.0, "bound on the guide force", min=0.1, max=1000.0, unit="N")
    camera_enabled: bool = param(True, "render and publish camera images", name="camera.enabled")
    camera_topic: str = param("camera/image_raw", "sensor_msgs/Image output (rgb8)", name="camera.topic")
    camera_frame_id: str = param("camera", "header.frame_id of the images", name="camera.frame_id")
    camera_rate_hz: float = param(5.0, "images per simulated second", min=0.1, max=60.0, unit="Hz",
                                  name="camera.rate_hz")
    camera_width: int = param(64, "image width", min=1, max=1024, unit="pixels", name="camera.width")
    camera_height: int = param(64, "image height", min=1, max=1024, unit="pixels", name="camera.height")
    camera_eye: tuple[float, ...] = param((), "camera position [x, y, z]; empty = a default view of the arm",
                                          unit="m", name="camera.eye")
    camera_target: tuple[float, ...] = param((), "point the camera looks at [x, y, z]; with camera.eye",
                                             unit="m", name="camera.target")
    camera_fov_deg: float = param(50.0, "vertical field of view, with camera.eye", min=1.0, max=179.0,
                                  unit="degrees", name="camera.fov_deg")
    objects_topic_prefix: str = param("objects", "object poses go to <prefix>/<name>/pose")
    objects_rate_hz: float = param(30.0, "object pose messages per simulated second", min=0.1, max=1000.0,
                                   unit="Hz")
    world_frame: str = param("world", "frame of object poses and guide targets")
    object_names: tuple[str, ...] = param((), "objects spawned at start, each described by "
                                          "objects.<name>.{shape, size, position, orientation, mass, rgba}")

    def __post_init__(self):
        validate(self)
        if 0.0 < self.rate_hz < MIN_RATE_HZ:
            raise ConfigError(f"rate_hz = {self.rate_hz!r} Hz: expected 0 "
                              f"(the robot's control rate) or a value in [{MIN_RATE_HZ:g}, 5000] Hz")


@dataclasses.dataclass(frozen=True)
class ObjectConfig:
    """Parameters ``objects.<name>.<field>`` of one object spawned at start."""

    shape: str = param("box", "one of " + ", ".join(SHAPES))
    size: tuple[float, ...] = param((0.05, 0.05, 0.05), "box [x, y, z] edges, sphere [radius], cylinder "
                                    "[radius, length]", unit="m")
    position: tuple[float, ...] = param((0.4, 0.0, 0.025), "centre [x, y, z] in the world", unit="m")
    orientation: tuple[float, ...] = param((0.0, 0.0, 0.0, 1.0), "quaternion [x, y, z, w]")
    mass: float = param(0.1, "0 = static", min=0.0, max=1000.0, unit="kg")
    rgba: tuple[float, ...] = param((), "colour [r, g, b, a] in [0, 1]; empty = default")

    def __post_init__(self):
        validate(self)
