"""Services answered by one thread of their own instead of an executor.

The thread waits on the services' handles with an rcl wait set (rclpy's private
``rclpy.impl.implementation_singleton`` WaitSet), takes a request, runs the service's callback
and sends the response, one request at a time. Compared with a multi-threaded executor this
saves, per call, the wait set the executor rebuilds over every entity of the node and the
hand-over to a pool thread: in Python both cost more than a small request's handler on a loaded
machine. The services stay on the node (in a :class:`~deepprompt_ros.ros.fastpath.polled.NotExecuted`
callback group that executors leave alone), so their names and ``ros2 node info`` are those of
ordinary services of that node.
"""
from __future__ import annotations

import contextlib
import threading
import time
from typing import Callable

from rclpy.exceptions import InvalidHandle
from rclpy.guard_condition import GuardCondition
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

from deepprompt_ros.ros.fastpath import realtime
from deepprompt_ros.ros.fastpath.polled import NotExecuted

__all__ = ["ServiceThread"]


class ServiceThread:
    """Creates services on ``node`` and answers them in a thread named ``name``.

    Parameters
    ----------
    node : rclpy Node
    name : str
        Name of the thread (also in the OS, see :func:`~deepprompt_ros.ros.fastpath.realtime.name_os_thread`).
    on_queued : callable (seconds) -> None, optional
        Receives, per request, the time from its reception by the middleware to its taking here.

    Create every service with :meth:`create_service`, then :meth:`start`; :meth:`stop` before the
    node is destroyed. A callback's exception is logged (throttled) and the thread keeps serving.
    """

    def __init__(self, node, name: str = "services", on_queued: Callable[[float], None] | None = None):
        self._node = node
        self._name = name
        self._on_queued = on_queued or (lambda seconds: None)
        self._group = NotExecuted()
        self._services: list = []
        self._wake = GuardCondition(None, None, context=node.context)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def create_service(self, srv_type, srv_name: str, callback, *, qos_profile=None):
        """``node.create_service`` for this thread; callback(request, response) -> response;
        ``qos_profile``: an rclpy QoSProfile (None: rclpy's default for services)."""
        if self._thread is not None:
            raise RuntimeError("services are created before ServiceThread.start()")
        qos = {} if qos_profile is None else {"qos_profile": qos_profile}
        srv = self._node.create_service(srv_type, srv_name, callback, callback_group=self._group, **qos)
        self._services.append(srv)
        return srv

    def start(self) -> None:
        self._thread = threading.Thread(target=self._serve, name=self._name, daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        self._wake.trigger()
        if self._thread is not None:
            self._thread.join(timeout)

    def _serve(self) -> None:
        realtime.name_os_thread(self._name)
        services, wake, ctx = self._services, self._wake, self._node.context
        wait_set = _rclpy.WaitSet(0, 1, 0, 0, len(services), 0, ctx.handle)  # 1 guard, n services
        while not self._stop.is_set() and ctx.ok():
            try:
                with contextlib.ExitStack() as stack:
                    for entity in (*services, wake):
                        stack.enter_context(entity.handle)
                    stack.enter_context(ctx.handle)
                    wait_set.clear_entities()
                    for srv in services:
                        wait_set.add_service(srv.handle)
                    wait_set.add_guard_condition(wake.handle)
                    wait_set.wait(-1)
                    ready = wait_set.get_ready_entities("service")
            except (InvalidHandle, _rclpy.RCLError):  # shutting down
                return
            for srv in services:
                if srv.handle.pointer not in ready:
                    continue
                try:
                    with srv.handle:
                        request, header = srv.handle.service_take_request(srv.srv_type.Request)
                    if header is None:
                        continue
                    if header.received_timestamp:  # middleware reception -> taken here
                        self._on_queued(max(time.time_ns() - header.received_timestamp, 0) * 1e-9)
                    srv.send_response(srv.callback(request, srv.srv_type.Response()), header)
                except Exception as exc:  # e.g. the client went away; the thread keeps serving
                    self._node.get_logger().warn(f"service {srv.srv_name}: {type(exc).__name__}: {exc}",
                                                 throttle_duration_sec=1.0)
