"""sim_bridge: one simulated arm (PyBullet, :class:`~deepprompt_ros.sim.simulation.Simulation`) over ROS 2.

Run: ``ros2 run deepprompt_ros sim_bridge --ros-args --params-file config/sim_bridge.yaml``
(or ``python -m deepprompt_ros.ros.sim_bridge ...``).

Interfaces (names relative to the node's namespace; parameters: the fields of
:class:`~deepprompt_ros.sim.bridge_config.SimBridgeConfig`, ``docs/parameters.md``):

* publishes ``joint_states`` (sensor_msgs/JointState: name, position, velocity, effort) once per
  physics step, i.e. at ``rate_hz`` × ``real_time_factor`` per wall-clock second, or every n-th
  step with ``joint_states_rate_hz`` (n = round(rate_hz / joint_states_rate_hz));
* publishes ``/clock`` (rosgraph_msgs/Clock) with the simulation time when ``publish_clock``: the
  one global name (``/clock`` whatever the namespace); with several bridges one publishes it (the
  ``dual_arm`` launch: its first arm's);
* publishes ``robot_description`` (std_msgs/String) once: the URDF of the simulated robot,
  reliable and transient local with depth 1 (as robot_state_publisher offers it), so RViz's
  RobotModel display and subscribers that join later get it;
* publishes ``camera/image_raw`` (sensor_msgs/Image, rgb8) at ``camera.rate_hz`` (simulated time);
* publishes ``objects/<name>/pose`` (geometry_msgs/PoseStamped, frame ``world_frame``) for every
  object, at ``objects_rate_hz``;
* subscribes ``joint_command`` (sensor_msgs/JointState): ``name`` = exactly the robot's joints
  (any order), ``position`` = where the joints should be now (inside the limits), ``velocity`` =
  feed-forward velocities (optional, empty = 0), ``effort`` ignored. Each physics step tracks the
  latest command within the velocity / acceleration limits. A streamer publishes one per tick.
  Invalid commands (wrong names / count, NaN, outside the limits, or while kinesthetic) are
  dropped with a throttled warning;
* subscribes ``guide_target`` (geometry_msgs/PointStamped, frame ``world_frame`` or empty): pull
  the end effector towards the point with a spring (``guide_stiffness``, ``guide_max_force``)
  until a point with a NaN coordinate clears it — a hand guiding the arm in kinesthetic mode;
* services ``spawn_object`` (deepprompt_msgs/SpawnObject, replaces an object of the same name),
  ``set_kinesthetic`` (std_srvs/SetBool: gravity-compensated, torque-free arm; switching off
  holds the current configuration and clears the guide), ``reset`` (std_srvs/Trigger: back to
  the initial configuration, guide cleared).

Time: every message is stamped with the simulation time, ``t_start + sim_time`` where
``t_start`` is the wall-clock time when the simulation started; with ``real_time_factor`` 1 this
follows the wall clock, otherwise use ``use_sim_time`` with ``/clock`` in the consumers.

All PyBullet calls run on one simulation thread, paced with ``time.perf_counter`` (see
:meth:`Simulation.step <deepprompt_ros.sim.simulation.Simulation.step>`); ROS callbacks hand it work.

Before each physics step the simulation thread applies every joint command received since the
previous one, in order. How they reach it and how joint_states and /clock leave (parameter
``fast_path``, same topics and messages either way):

* fast path: the joint_command subscription sits in a callback group that no executor waits on
  (:mod:`deepprompt_ros.ros.fastpath.polled`): the simulation thread takes the serialized messages
  itself and reads the numbers straight from the bytes once a joint-name layout has been validated
  (:class:`~deepprompt_ros.ros.fastpath.wire.CommandReader`); joint_states and /clock are published
  as pre-serialized bytes with the numbers patched in (:mod:`deepprompt_ros.ros.fastpath.wire`). At
  1 kHz an executor callback per command and a message built per step cost a large share of a core
  in Python;
* plain rclpy: an executor callback queues each command for the simulation thread; joint_states and
  /clock are built and published as rclpy messages.

One node per process: every topic and service above is this node's own (``ros2 node info``).
The interpreter's switch interval and the garbage collector's frozen start-up objects (see
:mod:`deepprompt_ros.ros.fastpath.realtime`) keep the simulation thread from waiting long for the
interpreter lock, in both modes.

The node is wiring (simulation: :mod:`deepprompt_ros.sim`); it passes 400 lines by this description and
its two subscription modes (``fast_path`` true / false).
"""
from __future__ import annotations

import concurrent.futures
import queue
import sys
import threading
import time
from typing import Any, Callable, Iterator

import numpy as np
import rclpy
from deepprompt_msgs.msg import ResultCode
from deepprompt_msgs.srv import SpawnObject
from geometry_msgs.msg import PointStamped, PoseStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Image, JointState
from std_msgs.msg import String
from std_srvs.srv import SetBool, Trigger

from deepprompt_ros.common.params import ConfigError
from deepprompt_ros.ros import conversions as conv
from deepprompt_ros.ros.fastpath import polled, realtime, wire
from deepprompt_ros.ros.parameters import declare_config
from deepprompt_ros.sim.bridge_config import ObjectConfig, SimBridgeConfig
from deepprompt_ros.sim.camera import CameraPose
from deepprompt_ros.sim.simulation import Simulation
from deepprompt_ros.ros.shutdown import spin_until_shutdown

__all__ = ["SimBridge", "main"]

#: The interpreter's switch interval (s): how long another thread may keep the interpreter lock
#: once the simulation thread's sleep has ended (Python's default, 5 ms, is five physics steps).
SWITCH_INTERVAL = 5e-4


def _drain(q: queue.SimpleQueue) -> Iterator[Any]:
    """The items waiting in ``q``, oldest first (without blocking)."""
    while True:
        try:
            yield q.get_nowait()
        except queue.Empty:
            return


class SimBridge(Node):
    """The sim_bridge node; see the module docstring. Raises :class:`ConfigError` on bad parameters."""

    def __init__(self, **node_kwargs):
        super().__init__("sim_bridge", **node_kwargs)
        self.cfg = p = declare_config(self, SimBridgeConfig)  # every bad value is reported at once
        try:
            from deepprompt_ros.robots.spec import load_robot

            spec = load_robot(p.robot)
        except ValueError as exc:
            raise ConfigError(f"parameter 'robot': {exc}") from None
        rate = p.rate_hz or spec.control_rate_hz
        if 0.0 < p.joint_states_rate_hz < 1.0 or p.joint_states_rate_hz > rate:
            raise ConfigError(f"parameter 'joint_states_rate_hz' = {p.joint_states_rate_hz}; expected 0 "
                              f"(every physics step) or 1..{rate:g} Hz (the physics rate)")
        self._js_every = max(1, round(rate / p.joint_states_rate_hz)) if p.joint_states_rate_hz else 1
        camera = None
        if p.camera_eye or p.camera_target:
            try:
                camera = CameraPose(eye=tuple(p.camera_eye), target=tuple(p.camera_target),
                                    fov_deg=p.camera_fov_deg)
            except (ValueError, TypeError) as exc:
                raise ConfigError(f"parameters 'camera.eye' / 'camera.target': {exc} (both must be "
                                  f"[x, y, z])") from None
        try:
            self.sim = Simulation(spec, timestep=1.0 / rate, real_time_factor=p.real_time_factor,
                                  camera=camera, initial_q=p.initial_positions or None)
        except ValueError as exc:
            raise ConfigError(f"parameter 'initial_positions': {exc}") from None
        self.spec = spec
        self._names = list(spec.joint_names)
        self._calls: queue.SimpleQueue = queue.SimpleQueue()
        self._stop = threading.Event()
        self._failed = False
        self._object_pubs: dict[str, Any] = {}
        objects = {name: declare_config(self, ObjectConfig, prefix=f"objects.{name}.") for name in p.object_names}
        try:
            for name, o in objects.items():
                self._spawn(name, o.shape, o.size, o.position, o.orientation, o.mass, o.rgba or None)
        except ValueError as exc:
            raise ConfigError(f"parameter objects.{name}: {exc}") from None
        if p.kinesthetic:
            self.sim.set_kinesthetic(True)

        # A deep history: a reliable subscriber that stalls for up to 0.5 s (a busy recorder)
        # still gets every message.
        self._js_pub = self.create_publisher(JointState, p.joint_states_topic, 500)
        self._clock_pub = self.create_publisher(Clock, "/clock", 10) if p.publish_clock else None
        self._image_pub = (self.create_publisher(Image, p.camera_topic, 5)
                           if p.camera_enabled else None)
        # the simulated robot's URDF, latched as robot_state_publisher offers it: a subscriber that
        # joins later (RViz's RobotModel display, robot_state_publisher-style tools) still gets it
        self._description_pub = self.create_publisher(String, "robot_description", QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self._description_pub.publish(String(data=spec.urdf_path.read_text()))
        # joint commands: _pending_commands() yields those received since the last physics step,
        # _read_command turns one into (q, qd) in the robot's order (see the module docstring)
        if p.fast_path:  # taken by the simulation thread itself, read from the serialized bytes
            sub = self.create_subscription(JointState, p.command_topic, lambda msg: None, 10, raw=True,
                                           callback_group=polled.NotExecuted())
            self._pending_commands = lambda: (data for data, _ in polled.take_all(sub))
            self._read_command = wire.CommandReader(self._names, spec.joints_text())
        else:  # an executor callback queues them for the simulation thread
            commands: queue.SimpleQueue = queue.SimpleQueue()
            self.create_subscription(JointState, p.command_topic, lambda msg: commands.put(msg), 10)
            self._pending_commands = lambda: _drain(commands)
            joints_text = spec.joints_text()
            self._read_command = lambda msg: conv.joint_command_to_arrays(msg, self._names, joints_text)[:2]
        self.create_subscription(PointStamped, p.guide_topic, self._on_guide, 10)
        self.create_service(SpawnObject, "spawn_object", self._on_spawn)
        self.create_service(SetBool, "set_kinesthetic", self._on_set_kinesthetic)
        self.create_service(Trigger, "reset", self._on_reset)
        self._initial_q = self.sim.joint_state().position.copy()
        self._thread = threading.Thread(target=self._run, name="sim", daemon=True)
        self.get_logger().info(
            f"robot {spec.name} ({spec.joints_text()}), {rate:g} Hz, real_time_factor "
            f"{p.real_time_factor:g}; publishing {self.resolve_topic_name(p.joint_states_topic)}"
            + (f" every {self._js_every} steps ({rate / self._js_every:g} Hz)" if self._js_every > 1 else "")
            + (f", camera {p.camera_width}x{p.camera_height} at {p.camera_rate_hz:g} Hz"
               if p.camera_enabled else "") + f", objects {list(self.sim.objects)}")

    # ------------------------------------------------------------------------------------------
    # simulation thread
    # ------------------------------------------------------------------------------------------
    def start(self) -> None:
        """Start stepping the simulation."""
        self._thread.start()

    def stop(self) -> None:
        """Stop the simulation thread (blocks until it ended)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)

    @property
    def failed(self) -> bool:
        return self._failed

    def _in_sim(self, fn: Callable[[], Any], timeout: float = 5.0) -> Any:
        """Run ``fn`` on the simulation thread between two steps and return its result."""
        fut: concurrent.futures.Future = concurrent.futures.Future()
        self._calls.put((fn, fut))
        return fut.result(timeout=timeout)

    def _run(self) -> None:
        p, sim = self.cfg, self.sim
        dt_cam = 1.0 / p.camera_rate_hz
        dt_obj = 1.0 / p.objects_rate_hz
        next_cam = next_obj = 0.0
        t0_ns = time.time_ns()
        # state_msg(joint state, stamp ns) and clock_msg(stamp ns): what the publishers send
        if p.fast_path:  # the numbers written into serialized messages
            state_bytes = wire.JointStateSerializer(self._names, effort=True)

            def state_msg(js, stamp_ns: int) -> bytes:
                return state_bytes(js.position, js.velocity, stamp_ns, js.effort)

            clock_msg = wire.ClockSerializer()
        else:  # rclpy messages
            names = self._names

            def state_msg(js, stamp_ns: int) -> JointState:
                return conv.arrays_to_joint_state(names, js.position, js.velocity, js.effort, stamp_ns=stamp_ns)

            def clock_msg(stamp_ns: int) -> Clock:
                return Clock(clock=conv.ns_to_stamp(stamp_ns))
        js_pub, clock_pub, js_every = self._js_pub, self._clock_pub, self._js_every
        calls = self._calls
        steps = 0
        try:
            while not self._stop.is_set():
                while not calls.empty():
                    fn, fut = calls.get_nowait()
                    try:
                        fut.set_result(fn())
                    except Exception as exc:  # handed back to the waiting callback
                        fut.set_exception(exc)
                self._take_commands()
                sim.step()
                steps += 1
                stamp_ns = t0_ns + round(sim.time * 1e9)
                if steps % js_every == 0:
                    js_pub.publish(state_msg(sim.joint_state(), stamp_ns))
                if clock_pub is not None:
                    clock_pub.publish(clock_msg(stamp_ns))
                if self._object_pubs and sim.time >= next_obj:
                    next_obj = sim.time + dt_obj
                    stamp = conv.ns_to_stamp(stamp_ns)
                    for name, pub in self._object_pubs.items():
                        pose = sim.object_pose(name)
                        m = conv.pose_stamped(pose.position, pose.orientation_xyzw,
                                              frame_id=p.world_frame)
                        m.header.stamp = stamp
                        pub.publish(m)
                if self._image_pub is not None and sim.time >= next_cam:
                    next_cam = sim.time + dt_cam
                    img = sim.camera_image(p.camera_width, p.camera_height)
                    m = conv.array_to_image(img, frame_id=p.camera_frame_id)
                    m.header.stamp = conv.ns_to_stamp(stamp_ns)
                    self._image_pub.publish(m)
        except Exception as exc:  # a broken simulation ends the node with an error
            if self.context.ok():
                self._failed = True
                self.get_logger().fatal(f"simulation stopped: {type(exc).__name__}: {exc}")
                rclpy.try_shutdown(context=self.context)

    def _take_commands(self) -> None:
        """Apply every joint command received since the last step, in order (the newest valid
        one wins); invalid ones are dropped with a throttled warning."""
        for command in self._pending_commands():
            try:
                q, qd = self._read_command(command)
                if self.sim.kinesthetic:
                    self.get_logger().warn("joint command ignored: kinesthetic mode is on (set_kinesthetic "
                                           "false to command positions)", throttle_duration_sec=2.0)
                    continue
                self.sim.set_position_targets(q, qd)  # checks the limits
            except ValueError as exc:
                self.get_logger().warn(f"joint command rejected: {exc}", throttle_duration_sec=1.0)

    # ------------------------------------------------------------------------------------------
    # callbacks (executor thread)
    # ------------------------------------------------------------------------------------------
    def _on_guide(self, msg: PointStamped) -> None:
        frame = msg.header.frame_id
        if frame not in ("", self.cfg.world_frame):
            self.get_logger().warn(f"guide target rejected: frame '{frame}'; expected "
                                   f"'{self.cfg.world_frame}' or empty", throttle_duration_sec=1.0)
            return
        target = conv.point_to_array(msg.point)
        if np.any(np.isnan(target)):
            self._calls.put((self.sim.release, concurrent.futures.Future()))
            return
        if not np.all(np.isfinite(target)):
            self.get_logger().warn(f"guide target rejected: {target.tolist()} is not finite",
                                   throttle_duration_sec=1.0)
            return
        k, fmax = self.cfg.guide_stiffness, self.cfg.guide_max_force
        self._calls.put((lambda: self.sim.guide_towards(target, stiffness=k, max_force=fmax),
                         concurrent.futures.Future()))

    def _spawn(self, name: str, shape: str, size, position, orientation, mass: float, rgba) -> None:
        """Spawn (or replace) an object; create its pose publisher. Raises ValueError."""
        if not isinstance(name, str) or not name or not (name[0].isalpha() and
                                                         name.replace("_", "a").isalnum()):
            raise ValueError(f"object name {name!r} is not valid; expected letters, digits and '_', "
                             f"starting with a letter (it becomes part of a topic name)")
        q = np.asarray(orientation, dtype=np.float64)
        if q.shape == (4,) and np.all(q == 0.0):
            q = np.array([0.0, 0.0, 0.0, 1.0])
        kw = {} if rgba is None else {"rgba": rgba}

        def do():
            if name in self.sim.objects:
                self.sim.remove_object(name)
            self.sim.spawn_object(name, shape=shape, size=size, position=position,
                                  orientation_xyzw=q, mass=float(mass), **kw)

        if self._thread_started():
            self._in_sim(do)
        else:
            do()
        if name not in self._object_pubs:
            topic = f"{self.cfg.objects_topic_prefix}/{name}/pose"
            self._object_pubs = {**self._object_pubs, name: self.create_publisher(PoseStamped, topic, 10)}

    def _thread_started(self) -> bool:
        return hasattr(self, "_thread") and self._thread.is_alive()

    def _on_spawn(self, req: SpawnObject.Request, res: SpawnObject.Response) -> SpawnObject.Response:
        try:
            pos, quat = conv.pose_to_arrays(req.pose)
            self._spawn(req.name, req.shape, list(req.size), pos, quat, req.mass,
                        list(req.rgba) if len(req.rgba) else None)
        except (ValueError, TypeError) as exc:
            res.success, res.code.value, res.message = False, ResultCode.INVALID_REQUEST, str(exc)
            return res
        except Exception as exc:
            res.success, res.code.value = False, ResultCode.INTERNAL_ERROR
            res.message = f"spawning '{req.name}' failed: {type(exc).__name__}: {exc}"
            return res
        res.success, res.code.value = True, ResultCode.SUCCESS
        res.message = (f"spawned {req.shape} '{req.name}'; pose on "
                       f"{self.resolve_topic_name(self.cfg.objects_topic_prefix + '/' + req.name + '/pose')}")
        return res

    def _on_set_kinesthetic(self, req: SetBool.Request, res: SetBool.Response) -> SetBool.Response:
        def do():
            if not req.data:
                self.sim.release()
            self.sim.set_kinesthetic(req.data)

        try:
            self._in_sim(do)
        except Exception as exc:
            res.success, res.message = False, f"{type(exc).__name__}: {exc}"
            return res
        res.success = True
        res.message = ("kinesthetic mode on: the arm is gravity compensated and follows guide_target"
                       if req.data else "kinesthetic mode off: holding the current configuration")
        return res

    def _on_reset(self, req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        try:
            self._in_sim(lambda: self.sim.reset(self._initial_q))
        except Exception as exc:
            res.success, res.message = False, f"{type(exc).__name__}: {exc}"
            return res
        res.success, res.message = True, "arm reset to the initial configuration, guide cleared"
        return res


def main(args=None) -> int:
    """Entry point of ``ros2 run deepprompt_ros sim_bridge``; returns the exit code."""
    realtime.set_switch_interval(SWITCH_INTERVAL)
    rclpy.init(args=args)
    node = None
    code = 0
    try:
        node = SimBridge()
        # start-up objects (pybullet, pinocchio, rclpy) out of the collector's way: a full collection
        # over them holds the interpreter lock long enough to stall the simulation thread
        realtime.freeze_startup_objects()
        node.start()
        spin_until_shutdown(lambda: rclpy.spin(node))
    except ConfigError as exc:
        rclpy.logging.get_logger("sim_bridge").fatal(f"invalid configuration: {exc}")
        code = 2
    except KeyboardInterrupt:
        pass
    finally:
        if node is not None:
            node.stop()
            if node.failed:
                code = 1
            node.sim.close()
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
