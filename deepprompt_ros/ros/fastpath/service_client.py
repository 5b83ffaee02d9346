"""A service client whose caller blocks on a wait set of its own: the client-side mirror of
:mod:`~deepprompt_ros.ros.fastpath.service_thread`.

:meth:`BlockingClient.call` sends the request and waits for its response on an rcl wait set that
holds this client alone (rclpy's private ``rclpy.impl.implementation_singleton`` WaitSet), then
takes the response in the calling thread. An executor would, per wake, rebuild its wait set over
every entity of the node and hand the response over through a future; a caller that only needs
the answer saves both. The client stays on its node (in a
:class:`~deepprompt_ros.ros.fastpath.polled.NotExecuted` callback group that executors leave alone),
so ``ros2 node info`` lists it and names and remappings resolve as for any other client.

Used by bench/bench_ros.py's Condition client, which measures round trips as a planner calling
from its own thread sees them.
"""
from __future__ import annotations

import time

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.qos import QoSProfile, qos_profile_services_default

from deepprompt_ros.ros.fastpath.polled import NotExecuted

__all__ = ["BlockingClient"]


class BlockingClient:
    """A client of service ``srv_name`` (type ``srv_type``) on ``node``, called synchronously.

    Parameters
    ----------
    node : rclpy Node
    srv_type : service type
    srv_name : str
        Resolved like ``node.create_client``'s name (relative names, ``~``, remappings).
    qos_profile : QoSProfile
        Default: rclpy's default for services.
    wait_slice : float
        Seconds of one wait on the wait set before the deadline is checked again.

    One caller at a time: :meth:`call` is not meant to be entered by two threads at once.
    :meth:`destroy` before the node is destroyed.
    """

    def __init__(self, node, srv_type, srv_name: str, qos_profile: QoSProfile = qos_profile_services_default,
                 wait_slice: float = 0.1):
        self._node = node
        self._srv_type = srv_type
        self._wait_ns = int(wait_slice * 1e9)
        self.client = node.create_client(srv_type, srv_name, qos_profile=qos_profile,
                                         callback_group=NotExecuted())
        # subscriptions, guard conditions, timers, clients, services, events: one client
        self._wait_set = _rclpy.WaitSet(0, 0, 0, 1, 0, 0, node.context.handle)

    @property
    def srv_name(self) -> str:
        return self.client.srv_name

    def wait_for_service(self, timeout: float) -> bool:
        """True once a server of the service is available, False after ``timeout`` s without one."""
        return self.client.wait_for_service(timeout_sec=timeout)

    def call(self, request, timeout: float = 30.0):
        """Send ``request``, wait for its response in the calling thread and return it.

        A response to an earlier request (one whose call timed out) that arrives meanwhile is
        taken and dropped.

        Raises
        ------
        TimeoutError
            No response to this request within ``timeout`` s (e.g. no server, or it did not answer).
        """
        cli, ctx, wait_set = self.client, self._node.context, self._wait_set
        with cli.handle:
            seq = cli.handle.send_request(request)
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            with cli.handle, ctx.handle:
                wait_set.clear_entities()
                wait_set.add_client(cli.handle)
                wait_set.wait(self._wait_ns)
                header, response = cli.handle.take_response(self._srv_type.Response)
            if header is not None and header.request_id.sequence_number == seq:
                return response
        raise TimeoutError(f"no {self.srv_name} response within {timeout} s")

    def destroy(self) -> None:
        """Remove the client from its node."""
        self._node.destroy_client(self.client)

