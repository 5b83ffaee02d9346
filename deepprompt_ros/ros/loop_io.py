"""The control loop's ROS side: command and JointTrajectory publishers, the joint_states reader.

Used by primitive_server both when the loop runs in its own interpreter
(:mod:`deepprompt_ros.ros.control_process`, the default) and in the node's process
(``loop_process: false``). Each :class:`LoopIO` belongs to one rclpy node; its callables are what
:class:`~deepprompt_ros.execution.stream_loop.StreamLoop` takes.

Two ways to talk to ROS (parameter ``fast_path``), with the same topics and messages:

* fast path: messages are published as bytes written into serialized templates
  (:mod:`deepprompt_ros.ros.fastpath.wire`), and the joint_states subscription sits in a callback
  group that no executor waits on: the control thread takes the newest message itself every
  ``StreamLoop.state_poll`` s (:attr:`LoopIO.poll_joint_state`);
* plain rclpy: messages are built and published as rclpy messages, and joint_states arrive
  through an executor callback (the node must be spun; ``poll_joint_state`` is then None).
"""
from __future__ import annotations

import math
import time

import numpy as np
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

from deepprompt_ros.execution.brake_tail import BrakeTail, trajectory_points
from deepprompt_ros.ros import conversions as conv
from deepprompt_ros.ros.fastpath import polled, wire

__all__ = ["LoopIO"]


class LoopIO:
    """Publishers and the joint_states subscription of the control loop, on ``node``.

    Parameters
    ----------
    node : rclpy Node
        Owns the publishers and the subscription.
    names : joint names (robot order)
    limits : JointLimits (for the braking tail of JointTrajectory messages)
    cfg : ServerConfig
        ``fast_path`` selects how messages are published and taken (module docstring).
    command_topic, trajectory_topic, joint_states_topic : str
        Resolved names; '' = that output is off.
    """

    #: s between two log lines of the same refusal reason (a new reason is logged at once)
    REFUSAL_LOG_PERIOD = 2.0

    def __init__(self, node, names, limits, cfg, command_topic: str, trajectory_topic: str,
                 joint_states_topic: str):
        self.node = node
        self.cfg = cfg
        self.names = list(names)
        self._fast = bool(cfg.fast_path)
        self._log = node.get_logger()
        self._tail = BrakeTail(limits)
        if self._fast:
            self._cmd_cdr = wire.JointStateSerializer(self.names)
            self._traj_cdr = wire.TrajectorySerializer(self.names)
        # deep history: a reliable subscriber that stalls for < 0.2 s loses no command
        self._cmd_pub = node.create_publisher(JointState, command_topic, 200) if command_topic else None
        self._traj_pub = node.create_publisher(JointTrajectory, trajectory_topic, 10) if trajectory_topic else None
        qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
        if self._fast:  # taken by the control thread (no executor dispatch per message)
            self._state_sub = node.create_subscription(JointState, joint_states_topic, lambda msg: None, qos,
                                                       callback_group=polled.NotExecuted())
        else:
            self._state_sub = node.create_subscription(JointState, joint_states_topic, self._use_joint_state, qos)
        self._state_index: tuple | None = None
        self._perf_to_ros = node.get_clock().now().nanoseconds - int(time.perf_counter() * 1e9)
        self.on_measured = lambda q, qd: None   #: set by the owner: receives (q, qd) in robot order
        self.on_refused = lambda reason: None   #: set by the owner: receives why a message was refused
        self.received_any = False
        self._refusal: tuple[str, float] = ("", -math.inf)  # the reason logged last, when

    @property
    def publish_command(self):
        return self._publish_command if self._cmd_pub is not None else None

    @property
    def publish_trajectory(self):
        return self._publish_trajectory if self._traj_pub is not None else None

    @property
    def poll_joint_state(self):
        """What the control thread calls to read the robot state (fast path), else None."""
        return self._poll_joint_state if self._fast else None

    def _publish_command(self, q, qd, qdd, due: float) -> None:
        # header.stamp = the tick's nominal time
        stamp = self._perf_to_ros + int(due * 1e9)
        if self._fast:  # the numbers written into a serialized JointState
            self._cmd_pub.publish(self._cmd_cdr(q, qd, stamp))
        else:
            self._cmd_pub.publish(conv.arrays_to_joint_state(self.names, q, qd, stamp_ns=stamp))

    def _publish_trajectory(self, snap) -> None:
        times, q, qd, qdd = trajectory_points(snap, self._tail)
        late = time.perf_counter() - snap.t0  # seconds since the snapshot's time origin
        if self.cfg.trajectory_stamp == "now":
            stamp = max(self.node.get_clock().now().nanoseconds - int(late * 1e9), 0)
        else:
            stamp, keep = 0, times > late
            times, q, qd, qdd = times[keep] - late, q[keep], qd[keep], qdd[keep]
            if times.size == 0:
                return
        if self._fast:
            self._traj_pub.publish(self._traj_cdr(times, q, qd, qdd, stamp_ns=stamp))
        else:
            self._traj_pub.publish(conv.joint_trajectory(self.names, times, q, qd, qdd, stamp_ns=stamp))

    def _poll_joint_state(self) -> None:
        """Take the newest joint_states message (control thread) and use it."""
        msg = polled.take_newest(self._state_sub)
        if msg is not None:
            self._use_joint_state(msg)

    def _use_joint_state(self, msg: JointState) -> None:
        """Check ``msg`` and pass (q, qd) to ``on_measured``; a refused message goes to ``on_refused``
        with the reason, which is logged (each new reason at once, a repeated one every
        ``REFUSAL_LOG_PERIOD`` s)."""
        try:
            q, qd = self._read_joint_state(msg)
        except (ValueError, IndexError) as exc:
            reason = str(exc)
            now = time.monotonic()
            if reason != self._refusal[0] or now - self._refusal[1] >= self.REFUSAL_LOG_PERIOD:
                self._refusal = (reason, now)
                self._log.warn(f"joint_states ignored: {reason}")
            self.on_refused(reason)
            return
        if not self.received_any:
            self.received_any = True
            self._log.info(f"receiving joint_states on '{self._state_sub.topic_name}'")
        self.on_measured(q, qd)

    def _read_joint_state(self, msg: JointState):
        """(q, qd or None) of the robot's joints in robot order; ValueError saying what is wrong.

        A message must name every joint of the robot (others are ignored) once, with one position per
        name, velocities and efforts one per name or none, and finite positions and velocities for the
        robot's joints. The name layout is looked up once; the sizes and values of every message are
        checked."""
        key = tuple(msg.name)
        n = len(key)
        if self._state_index is None or self._state_index[0] != key:  # a new layout: names checked once
            js = conv.joint_state_to_arrays(msg)
            order = conv.reorder_joints(js.names, np.arange(n), self.names, label="joint_states")
            self._state_index = (key, order.astype(int))
        elif len(msg.position) != n or len(msg.velocity) not in (0, n) or len(msg.effort) not in (0, n):
            conv.joint_state_to_arrays(msg)  # raises with the one wording of a wrong size
        idx = self._state_index[1]
        q = np.asarray(msg.position, dtype=np.float64)[idx]
        qd = np.asarray(msg.velocity, dtype=np.float64)[idx] if len(msg.velocity) else None
        for field, values in (("position", q), ("velocity", qd)):
            if values is not None and not np.all(np.isfinite(values)):
                j = int(np.argmin(np.isfinite(values)))
                raise ValueError(f"{field} of {self.names[j]} is {values[j]}; expected a finite value for every "
                                 f"joint of the robot")
        return q, qd

    def destroy(self) -> None:
        """Destroy the publishers and the subscription (the node stays)."""
        for entity in (self._cmd_pub, self._traj_pub):
            if entity is not None:
                self.node.destroy_publisher(entity)
        self.node.destroy_subscription(self._state_sub)
