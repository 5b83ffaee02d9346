"""primitive_server: serves trained DeepProMPs and streams their execution at control rate.

Run: ``ros2 run deepprompt_ros primitive_server [--ros-args --params-file config/primitive_server.yaml]``
(or ``python -m deepprompt_ros.ros.primitive_server``). Parameters: the fields of
:class:`deepprompt_ros.server.config.ServerConfig` (``python -m deepprompt_ros.server.config`` prints them).

Interfaces (``~`` = the node's name, ``/primitive_server`` by default):

* services ``~/condition`` (Condition), ``~/blend`` (Blend), ``~/sample`` (Sample),
  ``~/list_primitives`` (ListPrimitives), ``~/set_phase_rate`` (SetPhaseRate);
* action ``~/execute`` (Execute): feedback phase / cycle / phase rate / tracking error, result
  code + message, cancelable, a new goal preempts the running one;
* subscribes ``joint_states`` (sensor_msgs/JointState, the measured robot state) and
* publishes ``<controller>/joint_trajectory`` (trajectory_msgs/JointTrajectory: a few future
  samples of the command stream with positions, velocities, accelerations, then a braking tail to
  rest) and ``joint_command`` (sensor_msgs/JointState, one per control tick: names = the robot's
  joints, position + velocity; what sim_bridge consumes). With ``loop_process: true`` (the
  default) these topics belong to the control process's node ``<node name>_control`` (``ros2
  node info /primitive_server_control`` lists them), resolved in this node's namespace with its remappings.

Processes and threads: by default (``loop_process: true``) the command stream runs in a child
process, ``python -m deepprompt_ros.ros.control_process`` (threads ``control_loop`` and
``jtc_publisher`` of execution.stream_loop, its own rclpy context, node and interpreter lock; see
that module for the link, its lifetime and crash handling). With ``loop_process: false`` or
``loop_mode: timer`` those threads run in this process. Here: ``services`` (``fast_path: true``:
waits on the five services and answers each request itself, see ros.fastpath.service_thread;
``fast_path: false``: the executor dispatches them, one at a time), the executor's (action,
parameters) and ``control_link`` (the child's status and outcomes). One node per process: this
one, ``<name>_control`` in the child. Start-up objects are frozen out of the garbage collector
(``gc.freeze``, see ros.fastpath.realtime): a full collection over them stalls every thread.

Start-up: invalid parameters or no servable primitive -> a log line per problem and exit code 2.
Primitives that cannot be served (missing file, joints that are not the robot's, corrupt model)
are refused one by one with a log line; the server starts with the others.
Every callback is wrapped: a bad request gets success=false, a ResultCode and a message; an
unexpected exception gets INTERNAL_ERROR (traceback in the log), and the node keeps serving.
"""
from __future__ import annotations

import os

# One OpenBLAS thread, set before numpy loads it: the decoder's small matrix products (100 x 128 by
# 128 x 128) are many times slower with several OpenBLAS threads on a busy machine than with one.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import collections  # noqa: E402
import functools  # noqa: E402
import itertools  # noqa: E402
import math  # noqa: E402
import pathlib  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402

import numpy as np  # noqa: E402
import rclpy
from deepprompt_msgs.action import Execute
from deepprompt_msgs.srv import Blend, Condition, ListPrimitives, Sample, SetPhaseRate
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from deepprompt_ros import paths
from deepprompt_ros.common.params import ConfigError
from deepprompt_ros.common.results import Code, RequestError
from deepprompt_ros.ros.parameters import declare_config
from deepprompt_ros.ros.shutdown import spin_until_shutdown
from deepprompt_ros.server.config import ServerConfig, robot_limits
from deepprompt_ros.server.primitives_file import load_primitives, read_primitives_file
from deepprompt_ros.server.requests import BlendRequest, ConditionRequest, ExecuteRequest, SampleRequest
from deepprompt_ros.server.service import PrimitiveServerCore
from deepprompt_ros.ros import conversions as conv
from deepprompt_ros.execution.commands import LoopSetup
from deepprompt_ros.ros.control_process import ControlProcess
from deepprompt_ros.ros.fastpath.service_thread import ServiceThread
from deepprompt_ros.ros.loop_io import LoopIO
from deepprompt_ros.execution.controller import ExecutionController, ExecutionGoal
from deepprompt_ros.execution.stream_loop import StreamLoop
from deepprompt_ros.ros.fastpath import realtime

__all__ = ["PrimitiveServer", "main"]

#: s a finished Execute goal stays known to the action server (its result kept, its entry in the goal
#: status array). Clients ask for the result when the goal is accepted (rclpy's and rclcpp's action
#: clients do), so a minute is ample; rclpy's default, 15 minutes, makes every status message (sent to
#: every client at each state change of any goal) list every goal of the last 15 minutes, which a
#: planner that replans a few times a second grows to thousands of entries per message.
RESULT_TIMEOUT = 60

#: QoS of the five services and of the Execute action's goal, cancel and result services: reliable,
#: keep-last 100 instead of rmw's 10, because a keep-last reader drops the oldest unanswered requests
#: of a burst larger than its depth without a trace.
SERVICE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)


class PrimitiveServer(Node):
    """The node: wiring only (logic in deepprompt_ros.server and deepprompt_ros.execution)."""

    def __init__(self, **kwargs):
        super().__init__("primitive_server", **kwargs)
        log = self.get_logger()
        self.cfg = cfg = self._read_parameters()
        realtime.set_switch_interval(cfg.gil_switch_interval)
        from deepprompt_ros.robots.spec import load_robot  # pinocchio: after the parameters are checked

        try:
            self.robot = load_robot(cfg.robot)
        except (ValueError, FileNotFoundError, OSError) as exc:
            raise ConfigError(f"robot '{cfg.robot}' cannot be loaded: {exc}") from None
        self.limits = robot_limits(self.robot, cfg)
        self.names = list(self.robot.joint_names)
        rate = cfg.control_rate_hz or self.robot.control_rate_hz
        topic = f"{cfg.controller}/joint_trajectory"
        self._io = None
        self._in_process = not (cfg.loop_process and cfg.loop_mode == "thread")
        if not self._in_process:
            # the loop in a child process with its own interpreter (ros.control_process), started
            # now so that its start-up overlaps the loading of the primitives; topic names resolved
            # here so that this node's namespace and remappings apply
            self.loop = ControlProcess(LoopSetup(
                limits=self.limits, dt=1.0 / rate, config=cfg, joint_names=tuple(self.names),
                command_topic=self.resolve_topic_name(cfg.command_topic) if cfg.command_topic else "",
                trajectory_topic=self.resolve_topic_name(topic) if cfg.controller else "",
                joint_states_topic=self.resolve_topic_name(cfg.joint_states_topic),
                node_name=f"{self.get_name()}_control", namespace=self.get_namespace()), log)
        try:
            prims = self._load_primitives(cfg)
        except BaseException:
            if not self._in_process:
                self.loop.shutdown()
            raise
        self.core = PrimitiveServerCore(prims, cfg, self.limits)
        if self._in_process:
            # the loop's publishers and joint_states reader on this node (see ros.loop_io)
            self._io = LoopIO(self, self.names, self.limits, cfg, cfg.command_topic,
                              topic if cfg.controller else "", cfg.joint_states_topic)
            self.loop = StreamLoop(ExecutionController(self.limits, 1.0 / rate, cfg), cfg, self._io.publish_command,
                                   self._io.publish_trajectory,
                                   on_error=lambda m: log.error(m, throttle_duration_sec=1.0),
                                   poll_measured=self._io.poll_joint_state,
                                   thread_setup=realtime.prepare_thread)
            self._io.on_measured, self._io.on_refused = self.loop.update_measured, self.loop.refuse_measured
        elif not self.loop.wait_ready(60.0):
            # its publishers exist before this node offers Execute (subscribers discover them meanwhile)
            self.loop.shutdown()
            raise ConfigError("the control process did not start within 60 s (see the log above)")
        # time spent inside each service callback (s), the latest 4096 calls: the server's share of a round trip
        self._handled = {name: collections.deque(maxlen=4096)
                         for name in ("condition", "blend", "sample", "list_primitives", "set_phase_rate")}
        # time from a request's reception by DDS to its handling (any service), latest 4096
        self._queued: collections.deque = collections.deque(maxlen=4096)
        # the five services: answered one at a time, by a thread of their own (fast path) or by the
        # executor in one mutually exclusive callback group (plain rclpy)
        if cfg.fast_path:
            self._srv_thread = ServiceThread(self, "services", on_queued=self._queued.append)
            create_service = self._srv_thread.create_service
        else:
            self._srv_thread = None
            create_service = functools.partial(self.create_service, callback_group=MutuallyExclusiveCallbackGroup())
        for srv, name, fn in ((Condition, "condition", self._condition), (Blend, "blend", self._blend),
                              (Sample, "sample", self._sample), (ListPrimitives, "list_primitives", self._list),
                              (SetPhaseRate, "set_phase_rate", self._set_rate)):
            create_service(srv, f"~/{name}", self._guard(name, fn), qos_profile=SERVICE_QOS)
        # goals numbered as they are accepted: a newer goal preempts an older one, whichever plan is ready first
        self._accepted, self._accept_order = itertools.count(1), {}
        self._action = ActionServer(self, Execute, "~/execute", self._execute, callback_group=ReentrantCallbackGroup(),
                                    goal_callback=lambda goal: GoalResponse.ACCEPT,
                                    handle_accepted_callback=self._on_accepted,
                                    cancel_callback=lambda goal: CancelResponse.ACCEPT,
                                    goal_service_qos_profile=SERVICE_QOS, result_service_qos_profile=SERVICE_QOS,
                                    cancel_service_qos_profile=SERVICE_QOS, result_timeout=RESULT_TIMEOUT)
        if cfg.loop_mode == "timer":
            self.create_timer(1.0 / rate, self.loop.timer_tick, callback_group=MutuallyExclusiveCallbackGroup())
        self.gc = realtime.GcMonitor()
        if self._in_process:
            self.loop.start(threaded=cfg.loop_mode == "thread")
            if cfg.loop_mode == "thread":
                self.loop.started.wait(2.0)  # its priority has been set (or refused)
        if self._srv_thread is not None:
            self._srv_thread.start()
        if self._in_process and self.loop.priority_error:
            log.warn(self.loop.priority_error)
        where = "in this process" if self._in_process else f"in child process {self.loop.pid}"
        log.info(f"serving {len(prims)} primitive(s) [{', '.join(sorted(prims))}] for robot '{self.robot.name}' "
                 f"({len(self.names)} joints), control loop {rate:g} Hz ({cfg.loop_mode}, {where}), commands on "
                 f"{cfg.command_topic or '(off)'} and {topic if cfg.controller else '(no JointTrajectory)'}")

    # ------------------------------------------------------------------ start-up
    def _read_parameters(self) -> ServerConfig:
        """Declare the parameters (ros.parameters); ConfigError names every invalid one."""
        return declare_config(self, ServerConfig)

    def _load_primitives(self, cfg: ServerConfig) -> dict:
        log = self.get_logger()
        try:
            file = cfg.primitives_file or str(paths.find_data_file("config", "primitives.yaml"))
        except FileNotFoundError as exc:
            raise ConfigError(f"no primitives file: {exc}; set the parameter primitives_file") from None
        entries, errors = read_primitives_file(file)
        if cfg.models_dir:
            def resolve(name):
                path = pathlib.Path(name)
                path = path if path.is_absolute() else pathlib.Path(cfg.models_dir) / path
                if not path.is_file():
                    raise FileNotFoundError(f"model file '{path}' does not exist (models_dir '{cfg.models_dir}')")
                return path
        else:
            resolve = functools.partial(paths.find_data_file, "models")
        prims, load_errors = load_primitives(entries, self.robot.joint_names, resolve)
        for msg in errors + load_errors:
            log.error(msg)
        if not prims:
            raise ConfigError(f"no servable primitive in '{file}' ({len(entries)} entries, "
                              f"{len(errors) + len(load_errors)} refused, see above)")
        return prims

    # ------------------------------------------------------------------ services
    def _guard(self, name, fn):
        """Wrap a service callback: RequestError -> its code; anything else -> INTERNAL_ERROR."""
        handled = self._handled[name]

        def callback(request, response):
            t0 = time.perf_counter()
            try:
                fn(request, response)
                response.success = response.code.value == Code.SUCCESS
                return response
            except RequestError as exc:
                code, msg = exc.code, exc.message
            except Exception as exc:  # never let an exception escape a callback
                self.get_logger().error(f"{name} failed:\n{traceback.format_exc()}")
                code, msg = Code.INTERNAL_ERROR, f"internal error in {name}: {type(exc).__name__}: {exc}"
            finally:
                handled.append(time.perf_counter() - t0)
            response = type(response)()
            response.success, response.code.value, response.message = False, int(code), msg
            return response
        return callback

    def handling_summary(self, name: str = "condition") -> str:
        """'<name> handled in p50 / p99 ms over n calls' (time inside the callback, latest 4096 calls)
        and the time requests waited between their reception and their handling."""
        # deque.copy() is atomic under the interpreter lock (the service thread appends meanwhile)
        t, q = np.array(self._handled[name].copy()) * 1e3, np.array(self._queued.copy()) * 1e3
        if t.size == 0:
            return f"no {name} calls yet"
        return (f"{name} handled in p50 {np.percentile(t, 50):.3f} ms, p99 {np.percentile(t, 99):.3f} ms "
                f"over {t.size} calls" + (f" (requests waited p50 {np.percentile(q, 50):.3f} ms, p99 "
                                          f"{np.percentile(q, 99):.3f} ms from reception to handling)" if q.size else ""))

    def _condition(self, req, res) -> None:
        self.core.check_condition_sizes(len(req.via_points), len(req.contexts),
                                        [len(c.images) for c in req.contexts], req.preview_points)
        r = self.core.condition(ConditionRequest(
            req.primitive, conv.via_points_from_msgs(req.via_points), conv.contexts_from_msgs(req.contexts),
            bool(req.refine), int(req.refine_max_iterations), float(req.refine_tolerance), int(req.preview_points)))
        res.code.value, res.message, res.handle, res.handle_expires_in = int(r.code), r.message, r.handle, r.expires_in
        res.preview = conv.preview_to_msg(r.preview)
        res.refine_max_error, res.refine_iterations, res.reachable = r.refine_max_error, r.refine_iterations, r.reachable

    def _blend(self, req, res) -> None:
        r = self.core.blend(BlendRequest(req.handle_a, req.handle_b, req.schedule_phases, req.schedule_weights,
                                         int(req.preview_points), bool(req.sample), int(req.seed)))
        res.handle, res.handle_expires_in, res.preview = r.handle, r.expires_in, conv.preview_to_msg(r.preview)
        res.message = f"blended into handle '{r.handle}'"

    def _sample(self, req, res) -> None:
        r = self.core.sample(SampleRequest(req.handle, req.primitive, int(req.n_samples), int(req.n_points),
                                           int(req.seed)))
        conv.samples_to_response(r, res)
        res.message = f"{res.n_samples} trajectories of {res.n_points} points"

    def _list(self, req, res) -> None:
        res.primitives = [conv.primitive_info_to_msg(d) for d in self.core.describe()]
        res.message = f"{len(res.primitives)} primitive(s)"

    def _set_rate(self, req, res) -> None:
        rate = req.phase_rate
        if not math.isfinite(rate) or abs(rate) > 1.0 / self.core.MIN_DURATION:
            raise RequestError(Code.INVALID_REQUEST, f"phase_rate {rate!r} is invalid; expected a finite "
                               f"number with |phase_rate| <= {1.0 / self.core.MIN_DURATION:g} /s")
        goal = self.loop.active_goal
        if goal is not None and self.cfg.check_feasibility:
            self.core.check_rate(goal.plan.reference, rate)
        self.loop.set_rate(rate)
        res.message = f"phase rate set to {rate:g} /s (ramp {self.cfg.phase_rate_ramp_time:g} s)"

    # ------------------------------------------------------------------ action
    def _on_accepted(self, goal_handle):
        self._accept_order[bytes(goal_handle.goal_id.uuid)] = next(self._accepted)
        goal_handle.execute()

    def _execute(self, goal_handle):
        g = goal_handle.request
        order = self._accept_order.pop(bytes(goal_handle.goal_id.uuid), None)
        result = Execute.Result()
        try:
            plan = self.core.plan_execution(ExecuteRequest(g.handle, g.duration, g.phase_rate, g.cycles, g.reverse))
            age = self.loop.measured_age()
            if age > self.cfg.stale_timeout and self.loop.active_goal is None:
                refused = self.loop.state_refusal()
                what = "valid joint_states" if refused else "joint_states"
                raise RequestError(Code.ROBOT_STATE_STALE, (
                    f"no {what} on '{self.cfg.joint_states_topic}' for {age:.3f} s" if math.isfinite(age)
                    else f"no {what} received on '{self.cfg.joint_states_topic}'")
                    + f" (stale_timeout {self.cfg.stale_timeout:g} s); "
                    + (f"the latest were refused: {refused}" if refused else "is the robot running?"))
            goal = self.loop.execute(ExecutionGoal(plan, str(bytes(goal_handle.goal_id.uuid).hex()), order))
            period, canceled = 1.0 / self.cfg.feedback_rate_hz, False
            while not goal.done.wait(period):
                if goal_handle.is_cancel_requested and not canceled:
                    self.loop.cancel(goal)
                    canceled = True
                p = goal.progress
                goal_handle.publish_feedback(Execute.Feedback(phase=float(p.phase), cycle=int(p.cycle),
                                                              phase_rate=float(p.phase_rate),
                                                              tracking_error=float(p.tracking_error)))
            out = goal.outcome
            result.code.value, result.message = int(out.code), out.message
            result.max_tracking_error, result.final_phase = out.max_tracking_error, out.final_phase
            result.cycles_completed = int(out.cycles_completed)
        except RequestError as exc:
            result.code.value, result.message = int(exc.code), exc.message
        except Exception as exc:
            self.get_logger().error(f"execute failed:\n{traceback.format_exc()}")
            result.code.value, result.message = int(Code.INTERNAL_ERROR), f"internal error: {exc!r}"
        result.success = result.code.value == Code.SUCCESS
        self.get_logger().info(
            f"execute '{g.handle}': code {result.code.value} ({result.message}); control loop so far: "
            f"{self.loop.summary()}; {self.handling_summary()}; {self.gc.summary()}")
        try:
            if result.success:
                goal_handle.succeed()
            elif result.code.value == Code.CANCELED and goal_handle.is_cancel_requested:
                goal_handle.canceled()
            else:
                goal_handle.abort()
        except Exception as exc:  # e.g. the goal was already terminated
            self.get_logger().warn(f"execute: could not set the goal state: {exc}")
        return result

    def shutdown(self) -> None:
        if self._handled["condition"]:
            self.get_logger().info(self.handling_summary())
        if self._srv_thread is not None:
            self._srv_thread.stop(2.0)
        self.loop.shutdown()
        if self._io is not None:
            self._io.destroy()


def main(args=None) -> int:
    """Entry point of ``ros2 run deepprompt_ros primitive_server``; returns the exit code."""
    rclpy.init(args=args)
    node, code = None, 0
    # One torch thread, like one OpenBLAS thread: the conditioning's small triangular solves
    # (primitive/linear_conditioning.py) take tens of times longer with a second intra-op thread.
    import torch
    torch.set_num_threads(1)
    try:
        node = PrimitiveServer()
        n = realtime.freeze_startup_objects()  # no collection scans them again (see realtime.GcMonitor)
        node.gc.reset()
        node.get_logger().info(f"{n} start-up objects frozen (gc.freeze)")
        executor = MultiThreadedExecutor(num_threads=6)
        executor.add_node(node)
        spin_until_shutdown(executor.spin)
    except ConfigError as exc:
        rclpy.logging.get_logger("primitive_server").fatal(f"refusing to start: {exc}")
        code = 2
    except KeyboardInterrupt:
        pass
    finally:
        if node is not None:
            node.shutdown()
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
