"""Parameters of the demo_recorder node (:mod:`deepprompt_ros.ros.demo_recorder`), declared once.

:class:`RecorderConfig` is a frozen dataclass made with :func:`~deepprompt_ros.common.params.param`:
the node declares its ROS parameters from it (:mod:`deepprompt_ros.ros.parameters`),
``docs/parameters.md`` is generated from it and ``config/demo_recorder.yaml`` shows its defaults.
No rclpy here.
"""
from __future__ import annotations

import dataclasses

from deepprompt_ros.common.params import ConfigError, param, validate
from deepprompt_ros.recording.checks import RecordingError, parse_context_spec

__all__ = ["RecorderConfig"]


@dataclasses.dataclass(frozen=True)
class RecorderConfig:
    """Parameters of demo_recorder (ROS parameters of the same names; ranges are inclusive)."""

    joint_states_topic: str = param("joint_states", "sensor_msgs/JointState input")
    joint_names: tuple[str, ...] = param((), "joints to record, in this order; empty = all joints of the "
                                         "latest joint state, in its order")
    context_topics: tuple[str, ...] = param((), "context topics, 'topic' or 'name=topic' (e.g. "
                                            "'object=objects/cube/pose', 'camera/image_raw'); default of "
                                            "StartRecording")
    context_pose_fields: str = param("position", "pose contexts: 'position' (3 values) or 'pose' (position + "
                                     "quaternion xyzw, 7)", choices=("position", "pose"))
    output_directory: str = param("~/deepprompt_demos", "dataset folder receiving <name>.npz")
    record_bag: bool = param(True, "also write the raw messages as a rosbag2 MCAP bag")
    bag_directory: str = param("", "folder of the bags; empty = <output_directory>/bags")
    bag_compression: str = param("zstd", "MCAP chunk compression", choices=("zstd", "lz4", "none"))
    max_images: int = param(4, "images kept per demonstration", min=1, max=64)
    image_width: int = param(64, "width of the kept images", min=1, max=1024, unit="pixels")
    image_height: int = param(64, "height of the kept images", min=1, max=1024, unit="pixels")
    joint_states_timeout: float = param(1.0, "start_recording fails when the latest joint state is older "
                                        "than this", min=0.01, max=3600.0, unit="s")
    phase_type: str = param("linear", "phase type of the demonstrations", choices=("linear", "rhythmic"))
    fast_path: bool = param(True, "How the node talks to ROS. true: no executor waits on the subscriptions; "
                            "their messages queue in the middleware and are taken in batches poll_rate_hz "
                            "times a second (deepprompt_ros.ros.fastpath; parts of it use rclpy internals). "
                            "false: plain rclpy only (an executor callback per message; a message still queued "
                            "when stop_recording is handled is not recorded); slower, for comparison or when an "
                            "rclpy release breaks the fast path. Same topics, services, bags and demonstrations "
                            "otherwise.")
    poll_rate_hz: float = param(100.0, "with fast_path: how often queued messages are taken from the "
                                "subscriptions (they keep 1000 joint states)", min=1.0, max=1000.0, unit="Hz")

    def __post_init__(self):
        validate(self)
        try:
            for spec in self.context_topics:
                parse_context_spec(spec)
        except RecordingError as exc:
            raise ConfigError(f"context_topics: {exc}") from None

    def context_specs(self) -> list[tuple[str, str]]:
        """(context name, topic) of every entry of ``context_topics``."""
        return [parse_context_spec(s) for s in self.context_topics]
