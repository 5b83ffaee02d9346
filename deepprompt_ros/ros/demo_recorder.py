"""demo_recorder: record kinesthetic demonstrations from topics into the dataset format.

Run: ``ros2 run deepprompt_ros demo_recorder --ros-args --params-file config/demo_recorder.yaml``
(or ``python -m deepprompt_ros.ros.demo_recorder ...``).

* services ``start_recording`` (deepprompt_msgs/StartRecording) and ``stop_recording``
  (deepprompt_msgs/StopRecording);
* subscribes ``joint_states`` (sensor_msgs/JointState) all the time (to know it is alive) and
  the context topics (``context_topics`` or the request's list) once they have a publisher. The
  subscriptions are raw (``raw=True``: the serialized bytes, written to the bag as received and
  deserialized only for the demonstration) and every message comes with the time it was received
  (its message info). Parameter ``fast_path``: true, they sit in a callback group that no executor
  waits on (:mod:`deepprompt_ros.ros.fastpath.polled`), their messages queue in the middleware and
  a timer takes them in batches ``poll_rate_hz`` times a second (at 1 kHz an executor wake-up per
  message is a sizeable share of a core in Python); false, the executor hands each message to a
  callback.

One node per process: the subscriptions and services above are this node's own (``ros2 node info``).

Between start and stop, every joint state and context message is written, as received, to a
rosbag2 bag (MCAP storage), and converted for the demonstration: the joint positions of
``joint_names`` with their header stamps (receive time when the stamp is 0); per low-dimensional
context topic the latest message at the start (or the first one after it) as the context
``ctx/<name>`` (see :data:`~deepprompt_ros.ros.conversions.CONTEXT_TYPES`); from one
sensor_msgs/Image topic (rgb8 / bgr8) ``max_images`` images spread over the recording, resized to
``image_height`` x ``image_width``. Context topics of other types go to the bag only.

On stop: ``<output_directory>/<name>.npz`` (:func:`~deepprompt_ros.data.io.save_demo`,
atomic) and the bag folder ``<bag_directory>/<name>/`` (``metadata.yaml`` + ``<name>_0.mcap``,
renamed into place when complete; see :mod:`deepprompt_ros.recording.bag_writer`). A recorder killed
mid-recording leaves the finished demonstrations intact and only a hidden ``.part`` folder.

Bad requests (start while recording, stop while not recording, no recent joint state, missing
context publisher, unwritable folder, existing name) get ``success=false`` and a message; the
node keeps serving.

The node is wiring (recording logic: :mod:`deepprompt_ros.recording`); it passes 400 lines by this description and
its two subscription modes (``fast_path`` true / false).
"""
from __future__ import annotations

import dataclasses
import pathlib
import sys
import time
from typing import Any

import rclpy
from deepprompt_msgs.msg import ResultCode
from deepprompt_msgs.srv import StartRecording, StopRecording
from rclpy.exceptions import InvalidHandle
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rclpy.subscription import Subscription
from sensor_msgs.msg import JointState

from deepprompt_ros.data.io import save_demo
from deepprompt_ros.ros.shutdown import spin_until_shutdown
from deepprompt_ros.recording.bag_writer import BagWriter, qos_profile_yaml
from deepprompt_ros.recording.checks import (
    RecordingError,
    check_writable_directory,
    default_demo_name,
    parse_context_spec,
    validate_demo_name,
)
from deepprompt_ros.recording.demo_buffer import DemoBuffer
from deepprompt_ros.common.params import ConfigError
from deepprompt_ros.recording.config import RecorderConfig
from deepprompt_ros.ros import conversions as conv
from deepprompt_ros.ros.fastpath import polled
from deepprompt_ros.ros.parameters import declare_config

__all__ = ["DemoRecorder", "main"]

IMAGE_TYPE = "sensor_msgs/msg/Image"
JOINT_STATE_TYPE = "sensor_msgs/msg/JointState"


def _unused(*_args) -> None:
    """Callback of the polled subscriptions; never called (no executor runs their group)."""


def _msg_class(type_name: str):
    """'pkg/msg/Type' -> the Python message class."""
    import importlib

    pkg, _, name = type_name.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


@dataclasses.dataclass
class _ContextTopic:
    """A subscribed context topic and its latest raw message."""

    topic: str
    type_name: str
    msg_class: type
    qos_text: str
    last: tuple[bytes, int] | None = None  # (CDR bytes, receive time ns)
    subscription: Any = None


@dataclasses.dataclass
class _Recording:
    buffer: DemoBuffer
    bag: BagWriter | None
    contexts: dict[str, str]  # topic -> context name (image topic: "image")
    bag_only: list[str]
    output: pathlib.Path
    start_ns: int  # messages received (system clock) before this are not part of the recording
    stop_ns: int | None = None  # ... nor those received after this
    invalid_joint_states: int = 0
    invalid_contexts: int = 0


class DemoRecorder(Node):
    """The demo_recorder node; see the module docstring. Raises :class:`ConfigError`."""

    def __init__(self, **node_kwargs):
        super().__init__("demo_recorder", **node_kwargs)
        self._p = p = declare_config(self, RecorderConfig)  # every bad value is reported at once
        self._default_specs = p.context_specs()
        self._out_dir = pathlib.Path(p.output_directory).expanduser()
        self._bag_dir = (pathlib.Path(p.bag_directory).expanduser() if p.bag_directory
                         else self._out_dir / "bags")
        self._js_topic = self.resolve_topic_name(p.joint_states_topic)
        self._js_qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self._last_js: tuple[int, bytes] | None = None  # (receive time ns, CDR bytes)
        self._contexts: dict[str, _ContextTopic] = {}
        self._rec: _Recording | None = None
        # fast path: the subscriptions' group (no executor waits on it; _poll takes their messages)
        self._polled = polled.NotExecuted() if p.fast_path else None
        self._polled_subs: list[tuple[Subscription, Any]] = []  # (subscription, handle(data, info))
        self._tap(JointState, p.joint_states_topic, self._js_qos, self._on_joint_state)
        self.create_service(StartRecording, "start_recording", self._on_start)
        self.create_service(StopRecording, "stop_recording", self._on_stop)
        if self._polled is not None:
            self.create_timer(1.0 / p.poll_rate_hz, self._poll)
        self.create_timer(0.5, self._subscribe_default_contexts)
        self.get_logger().info(
            f"recording {self._js_topic} into {self._out_dir}"
            + (f" (bags in {self._bag_dir})" if p.record_bag else " (no bags)")
            + f"; default contexts {[t for _, t in self._default_specs]}")

    # ------------------------------------------------------------------------------------------
    # subscriptions
    # ------------------------------------------------------------------------------------------
    def _tap(self, msg_class, topic: str, qos: QoSProfile, handle) -> Subscription:
        """A raw subscription of this node to ``topic`` whose messages reach ``handle(data, info)``
        (serialized bytes, message info): taken by :meth:`_poll` (fast path) or through the
        executor (plain rclpy; a callback of two parameters receives the message info)."""
        if self._polled is None:
            return self.create_subscription(msg_class, topic, handle, qos, raw=True)
        sub = self.create_subscription(msg_class, topic, _unused, qos, raw=True, callback_group=self._polled)
        self._polled_subs.append((sub, handle))
        return sub

    def _on_joint_state(self, data: bytes, info: dict) -> None:
        self._last_js = (info.get("received_timestamp") or time.time_ns(), data)
        if self._rec is not None:
            self._record_joint_state(self._rec, data, info)

    def _record_joint_state(self, rec: _Recording, data: bytes, info: dict) -> None:
        recv = info.get("received_timestamp") or time.time_ns()
        if recv < rec.start_ns or (rec.stop_ns is not None and recv > rec.stop_ns):
            return  # queued before the start while this node was busy, or after the stop
        sent = info.get("source_timestamp") or recv
        if rec.bag is not None:
            rec.bag.write(self._js_topic, data, recv, sent)
        try:
            js = conv.joint_state_to_arrays(deserialize_message(data, JointState))
        except ValueError as exc:
            rec.invalid_joint_states += 1
            self.get_logger().warn(f"joint state not recorded: {exc}", throttle_duration_sec=2.0)
            return
        rec.buffer.add_joint_state(js.stamp_ns or sent, js.names, js.position)

    def _on_context(self, ctx: _ContextTopic, data: bytes, info: dict) -> None:
        recv = info.get("received_timestamp") or time.time_ns()
        ctx.last = (data, recv)
        rec = self._rec
        if rec is not None and recv >= rec.start_ns and (rec.stop_ns is None or recv <= rec.stop_ns):
            self._record_context(rec, ctx, data, recv)

    def _record_context(self, rec: _Recording, ctx: _ContextTopic, data: bytes, t_ns: int) -> None:
        if ctx.topic not in rec.contexts and ctx.topic not in rec.bag_only:
            return
        if rec.bag is not None:
            rec.bag.write(ctx.topic, data, t_ns)
        name = rec.contexts.get(ctx.topic)
        if name is None or (name != "image" and rec.buffer.has_context(name)):
            return
        try:
            msg = deserialize_message(data, ctx.msg_class)
            if name == "image":
                rec.buffer.add_image(conv.image_to_array(msg))
            else:
                rec.buffer.add_context(name, conv.context_vector(msg, pose_fields=self._p.context_pose_fields))
        except (ValueError, RecordingError) as exc:
            rec.invalid_contexts += 1
            self.get_logger().warn(f"message on {ctx.topic} not usable as context: {exc}",
                                   throttle_duration_sec=2.0)

    def _poll(self) -> None:
        """Fast path: hand the queued messages of every subscription to its handler, subscription
        by subscription (timer callback; also before a recording starts and stops). Plain rclpy:
        nothing (the executor delivers them)."""
        for sub, handle in list(self._polled_subs):
            try:
                for data, info in polled.take_all(sub):
                    handle(data, info)
            except InvalidHandle:  # destroyed during shutdown
                pass

    def _subscribe(self, topic: str) -> _ContextTopic:
        """Subscribe to a context topic (raw); its type and QoS come from its publishers.

        Raises
        ------
        RecordingError
            No publisher, or publishers of several types.
        """
        name, topic = topic, self.resolve_topic_name(topic)  # as given (the subscription resolves it)
        if topic in self._contexts:
            return self._contexts[topic]
        pubs = self.get_publishers_info_by_topic(topic)
        if not pubs:
            raise RecordingError(f"context topic {topic} has no publisher (is the sim_bridge or the "
                                 f"camera / object tracker running?)")
        types = sorted({i.topic_type for i in pubs})
        if len(types) != 1:
            raise RecordingError(f"context topic {topic} has publishers of several types {types}")
        best_effort = any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in pubs)
        qos = QoSProfile(depth=10, reliability=(ReliabilityPolicy.BEST_EFFORT if best_effort
                                                else ReliabilityPolicy.RELIABLE))
        try:
            cls = _msg_class(types[0])
        except (ImportError, AttributeError, ValueError) as exc:
            raise RecordingError(f"context topic {topic}: message type {types[0]} is not installed "
                                 f"({exc})") from None
        ctx = _ContextTopic(topic, types[0], cls, qos_profile_yaml(
            reliability="best_effort" if best_effort else "reliable", depth=10))
        ctx.subscription = self._tap(cls, name, qos, lambda d, i, c=ctx: self._on_context(c, d, i))
        self._contexts[topic] = ctx
        return ctx

    def _subscribe_default_contexts(self) -> None:
        for _, topic in self._default_specs:
            try:
                self._subscribe(topic)
            except RecordingError:
                pass  # not published yet; start_recording reports it

    # ------------------------------------------------------------------------------------------
    # services
    # ------------------------------------------------------------------------------------------
    def _on_start(self, req: StartRecording.Request, res: StartRecording.Response) -> StartRecording.Response:
        try:
            return self._start(req, res)
        except Exception as exc:  # never let a callback kill the node
            self.get_logger().error(f"start_recording failed: {type(exc).__name__}: {exc}")
            res.success, res.code.value = False, ResultCode.INTERNAL_ERROR
            res.message = f"internal error: {type(exc).__name__}: {exc}"
            return res

    def _start(self, req, res):
        def fail(code: int, message: str):
            res.success, res.code.value, res.message = False, code, message
            return res

        if self._rec is not None:
            return fail(ResultCode.RECORDING_ACTIVE, f"recording '{self._rec.buffer.name}' is running; "
                        f"call stop_recording first")
        problems: list[tuple[int, str]] = []
        name = req.demo_name or default_demo_name()
        try:
            validate_demo_name(name)
        except RecordingError as exc:
            return fail(ResultCode.INVALID_REQUEST, str(exc))
        try:
            specs = [parse_context_spec(s) for s in req.context_topics] or self._default_specs
        except RecordingError as exc:
            return fail(ResultCode.INVALID_REQUEST, str(exc))
        p = self._p
        joint_names = p.joint_names
        self._poll()  # up to date: the freshness check below and the context seeds need it
        if self._last_js is None:
            problems.append((ResultCode.ROBOT_STATE_STALE, f"no JointState received on {self._js_topic} "
                             f"yet (is the robot driver or sim_bridge running?)"))
        else:
            age = (time.time_ns() - self._last_js[0]) * 1e-9
            if age > p.joint_states_timeout:
                problems.append((ResultCode.ROBOT_STATE_STALE, f"the latest JointState on {self._js_topic} "
                                 f"is {age:.2f} s old (joint_states_timeout {p.joint_states_timeout:g} s)"))
            names = tuple(deserialize_message(self._last_js[1], JointState).name)
            missing = [j for j in joint_names if j not in names]
            if missing:
                problems.append((ResultCode.INVALID_REQUEST, f"JointState on {self._js_topic} has joints "
                                 f"{list(names)}; parameter joint_names asks for missing {missing}"))
            joint_names = joint_names or list(names)
        try:
            check_writable_directory(self._out_dir)
            if (self._out_dir / f"{name}.npz").exists():
                problems.append((ResultCode.INVALID_REQUEST, f"demonstration '{name}' exists in "
                                 f"{self._out_dir}; choose another demo_name"))
        except RecordingError as exc:
            problems.append((ResultCode.INVALID_REQUEST, f"{exc}; set parameter output_directory"))
        if p.record_bag:
            try:
                check_writable_directory(self._bag_dir, "bag directory")
                if (self._bag_dir / name).exists():
                    problems.append((ResultCode.INVALID_REQUEST, f"bag '{name}' exists in {self._bag_dir}; "
                                     f"choose another demo_name"))
            except RecordingError as exc:
                problems.append((ResultCode.INVALID_REQUEST, f"{exc}; set parameter bag_directory"))
        contexts: dict[str, str] = {}
        bag_only: list[str] = []
        for cname, topic in specs:
            try:
                ctx = self._subscribe(topic)
            except RecordingError as exc:
                problems.append((ResultCode.INVALID_REQUEST, str(exc)))
                continue
            if ctx.type_name == IMAGE_TYPE:
                if "image" in contexts.values():
                    problems.append((ResultCode.INVALID_REQUEST, f"several image topics ({ctx.topic} and "
                                     f"{[t for t, n in contexts.items() if n == 'image']}); one is supported"))
                contexts[ctx.topic] = "image"
            elif ctx.type_name in conv.CONTEXT_TYPES:
                contexts[ctx.topic] = cname
            else:
                bag_only.append(ctx.topic)
        if problems:
            return fail(problems[0][0], "cannot start recording: " + "; ".join(m for _, m in problems))

        buffer = DemoBuffer(name, joint_names, max_images=p.max_images, image_height=p.image_height,
                            image_width=p.image_width, phase_type=p.phase_type)
        bag = None
        if p.record_bag:
            bag = BagWriter(self._bag_dir, name, compression=p.bag_compression)
            bag.add_topic(self._js_topic, JOINT_STATE_TYPE,
                          offered_qos_profiles=qos_profile_yaml(depth=self._js_qos.depth))
            for topic in list(contexts) + bag_only:
                ctx = self._contexts[topic]
                bag.add_topic(topic, ctx.type_name, offered_qos_profiles=ctx.qos_text)
        rec = _Recording(buffer, bag, contexts, bag_only, self._out_dir, time.time_ns())
        for topic in contexts:  # the scene as the demonstration starts: latest message so far
            ctx = self._contexts[topic]
            if ctx.last is not None:
                self._record_context(rec, ctx, *ctx.last)
        self._rec = rec
        res.success, res.code.value = True, ResultCode.SUCCESS
        res.message = (f"recording '{name}': {len(joint_names)} joints from {self._js_topic}"
                       + (f"; contexts {dict((t, n) for t, n in contexts.items())}" if contexts else "")
                       + (f"; bag only: {bag_only}" if bag_only else ""))
        self.get_logger().info(res.message)
        return res

    def _on_stop(self, req: StopRecording.Request, res: StopRecording.Response) -> StopRecording.Response:
        rec = self._rec
        if rec is None:
            res.success, res.code.value = False, ResultCode.NOT_RECORDING
            res.message = "no recording is running; call start_recording first"
            return res
        rec.stop_ns = time.time_ns()
        if not req.discard:
            self._poll()  # everything received before the stop belongs to the recording
        self._rec = None
        try:
            return self._stop(rec, req, res)
        except Exception as exc:  # never let a callback kill the node
            self.get_logger().error(f"stop_recording failed: {type(exc).__name__}: {exc}")
            res.success, res.code.value = False, ResultCode.INTERNAL_ERROR
            res.message = f"internal error: {type(exc).__name__}: {exc}"
            return res

    def _stop(self, rec: _Recording, req, res):
        name = rec.buffer.name
        stats = rec.buffer.stats()
        res.n_samples = stats.n_samples
        if req.discard:
            if rec.bag is not None:
                rec.bag.abort()
            res.success, res.code.value = True, ResultCode.SUCCESS
            res.message = f"recording '{name}' discarded ({stats.n_samples} samples)"
            return res
        notes = []
        missing = [f"{n} ({t})" for t, n in rec.contexts.items()
                   if n != "image" and not rec.buffer.has_context(n)]
        if missing:
            notes.append(f"no message arrived on context topic(s) {missing}: context missing")
        if "image" in rec.contexts.values() and stats.n_images == 0:
            notes.append("no image arrived: demonstration has no images")
        if stats.missing_joints or stats.not_increasing or stats.non_finite:
            notes.append(f"dropped joint states: {stats.missing_joints} without all joints, "
                         f"{stats.not_increasing} with non-increasing stamps, {stats.non_finite} non-finite")
        try:
            demo = rec.buffer.to_demonstration()
            demo_error = None
        except RecordingError as exc:
            demo, demo_error = None, exc
        if rec.bag is not None:
            try:
                res.bag_path = str(rec.bag.close())
            except RecordingError as exc:
                notes.append(str(exc))
        if demo_error is not None:
            res.success, res.code.value = False, ResultCode.ROBOT_STATE_STALE
            res.message = f"{demo_error}; nothing added to the dataset" + "".join(f"; {n}" for n in notes)
            return res
        path = rec.output / f"{name}.npz"
        try:
            save_demo(demo, path)
        except OSError as exc:
            res.success, res.code.value = False, ResultCode.INTERNAL_ERROR
            res.message = f"could not write {path}: {exc}" + "".join(f"; {n}" for n in notes)
            return res
        res.success, res.code.value, res.dataset_path = True, ResultCode.SUCCESS, str(path)
        imgs = "" if demo.images is None else f", {len(demo.images)} images"
        res.message = (f"demonstration '{name}': {stats.n_samples} samples over {stats.duration:.2f} s, "
                       f"contexts {sorted(demo.contexts)}{imgs}"
                       + (f"; bag {res.bag_path} ({rec.bag.message_count} messages)" if res.bag_path else "")
                       + "".join(f"; {n}" for n in notes))
        self.get_logger().info(res.message)
        return res

    def shutdown_recording(self) -> None:
        """On node shutdown: an unfinished recording is left like after a crash (raw data kept)."""
        if self._rec is not None and self._rec.bag is not None:
            self.get_logger().warn(f"recording '{self._rec.buffer.name}' was not stopped; nothing added "
                                   f"to the dataset, raw messages left in {self._rec.bag.tmp_dir}")


def main(args=None) -> int:
    """Entry point of ``ros2 run deepprompt_ros demo_recorder``; returns the exit code."""
    rclpy.init(args=args)
    node = None
    code = 0
    try:
        node = DemoRecorder()
        spin_until_shutdown(lambda: rclpy.spin(node))
    except ConfigError as exc:
        rclpy.logging.get_logger("demo_recorder").fatal(f"invalid configuration: {exc}")
        code = 2
    except KeyboardInterrupt:
        pass
    finally:
        if node is not None:
            node.shutdown_recording()
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
