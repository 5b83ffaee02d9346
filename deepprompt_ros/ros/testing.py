"""Utilities for tests that run nodes as real processes talking over real DDS.

Isolation (every test that starts nodes must have it):

* a random ``ROS_DOMAIN_ID`` in 1..101, so parallel test runs do not see each other;
* ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``: discovery stays on the loopback interface;
* ``ROS_LOG_DIR`` in a temporary folder (``rclpy.init`` fails without a log folder when HOME is unset);
* nodes start in a new session (``start_new_session=True``) and are stopped by signalling their
  whole process group: SIGINT, then SIGKILL after a timeout, so no node outlives its test.

Typical use in a test module::

    from deepprompt_ros.ros.testing import NodeProcess, RosTestClient, isolated_ros_env

    @pytest.fixture(scope="module")
    def env(tmp_path_factory):
        return isolated_ros_env(tmp_path_factory.mktemp("ros"))

    @pytest.fixture(scope="module")
    def sim(env):
        with NodeProcess.start_module("deepprompt_ros.ros.sim_bridge", env,
                                      params={"rate_hz": 500.0}) as proc:
            yield proc

    @pytest.fixture(scope="module")
    def client(env):
        with RosTestClient(env) as c:
            yield c

    def test_joint_states(sim, client):
        log = client.subscribe("joint_states", JointState)
        assert client.wait_for(lambda: len(log) >= 100, timeout=10.0), sim.output_tail()

:class:`RosTestClient` is the test's own rclpy node in its own ``Context`` (domain from the
environment); it spins only inside its helper calls, so a test reads its results without threads.

One module (about 500 lines) because every node test uses these pieces together: the isolated
environment, the node processes, the test client and its joint-state tap.
"""
from __future__ import annotations

import os
import pathlib
import random
import signal
import subprocess
import sys
import tempfile
import time
from typing import Any, Callable, Mapping, NamedTuple, Sequence

__all__ = [
    "isolated_ros_env",
    "write_params_file",
    "NodeProcess",
    "Received",
    "MessageLog",
    "RosTestClient",
    "JointStateTap",
]

#: Environment variables that select the ROS 2 network and logging of a process.
ROS_ENV_KEYS = ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOG_DIR", "ROS_STATIC_PEERS",
                "ROS_LOCALHOST_ONLY")


def isolated_ros_env(log_dir: str | os.PathLike, domain_id: int | None = None,
                     base: Mapping[str, str] | None = None) -> dict[str, str]:
    """Environment for an isolated ROS 2 test network.

    Parameters
    ----------
    log_dir : path
        Becomes ``ROS_LOG_DIR`` (created if missing); node output files also go here.
    domain_id : int, optional
        Default: random in 1..101 (from the OS entropy source, independent of test seeds).
    base : mapping, optional
        Environment to start from; default ``os.environ``.

    Returns
    -------
    dict
        A full environment for :class:`NodeProcess` and :class:`RosTestClient`.
    """
    env = dict(os.environ if base is None else base)
    log_dir = pathlib.Path(log_dir)
    log_dir.mkdir(parents=True, exist_ok=True)
    if domain_id is None:
        domain_id = random.SystemRandom().randint(1, 101)
    if not 0 <= int(domain_id) <= 232:
        raise ValueError(f"ROS_DOMAIN_ID must be in 0..232; got {domain_id}")
    env.pop("ROS_LOCALHOST_ONLY", None)  # deprecated in Jazzy; superseded by the discovery range
    env.pop("ROS_STATIC_PEERS", None)
    env.update(ROS_DOMAIN_ID=str(int(domain_id)), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               ROS_LOG_DIR=str(log_dir), PYTHONUNBUFFERED="1")
    return env


def write_params_file(path: str | os.PathLike, params: Mapping[str, Any], node: str = "/**") -> pathlib.Path:
    """Write a ROS 2 parameters YAML file for ``--params-file``.

    Parameters
    ----------
    params : mapping
        Parameter name (dots allowed, e.g. ``"camera.width"``) -> value (str, int, float, bool or
        a non-empty list of one of them).
    node : str
        Node name pattern; default all nodes.
    """
    import yaml

    for k, v in params.items():
        if isinstance(v, (list, tuple)) and not v:
            raise ValueError(f"parameter '{k}': an empty list has no type in a parameters file; "
                             f"leave it out to get the node's default")
    path = pathlib.Path(path)
    path.write_text(yaml.safe_dump({node: {"ros__parameters": {k: (list(v) if isinstance(v, tuple) else v)
                                                                  for k, v in params.items()}}}))
    return path


class NodeProcess:
    """A node running as a separate process in its own session (process group).

    Use :meth:`start_module` (or the constructor with a full command line) and always stop it,
    e.g. with ``with``. Output (stdout + stderr) goes to a log file, see :meth:`output`.

    Parameters
    ----------
    cmd : sequence of str
        Command line.
    env : mapping
        Environment, normally from :func:`isolated_ros_env`.
    log_path : path
        File receiving the process's stdout and stderr.
    """

    def __init__(self, cmd: Sequence[str], env: Mapping[str, str], log_path: str | os.PathLike):
        self.cmd = list(cmd)
        self.log_path = pathlib.Path(log_path)
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self._log = open(self.log_path, "wb")
        self.proc = subprocess.Popen(self.cmd, env=dict(env), stdout=self._log, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, start_new_session=True)

    @classmethod
    def start_module(cls, module: str, env: Mapping[str, str], *, params: Mapping[str, Any] | None = None,
                     params_files: Sequence[str | os.PathLike] = (), ros_args: Sequence[str] = (),
                     name: str | None = None, log_dir: str | os.PathLike | None = None) -> "NodeProcess":
        """Start ``python -m <module> --ros-args [--params-file <f>]... [--params-file <tmp>] <ros_args>``.

        Parameters
        ----------
        module : str
            Module with a ``main()`` run under ``if __name__ == "__main__"``, e.g.
            ``"deepprompt_ros.ros.sim_bridge"``.
        env : mapping
            From :func:`isolated_ros_env`.
        params : mapping, optional
            Parameters, written to a parameters file (see :func:`write_params_file`); they
            override those of ``params_files``.
        params_files : sequence of path
            Parameter files given first (e.g. the package's ``config/<node>.yaml``).
        ros_args : sequence of str
            Extra arguments after ``--ros-args`` (e.g. ``["-r", "__ns:=/arm"]``).
        name : str, optional
            Label for the log file; default the module's last component.
        log_dir : path, optional
            Where the log and parameter files go; default ``env["ROS_LOG_DIR"]``.
        """
        name = name or module.rsplit(".", 1)[-1]
        folder = pathlib.Path(log_dir or env.get("ROS_LOG_DIR") or tempfile.mkdtemp())
        folder.mkdir(parents=True, exist_ok=True)
        stamp = f"{name}.{time.time_ns()}"
        cmd = [sys.executable, "-m", module, "--ros-args"]
        for f in params_files:
            cmd += ["--params-file", str(f)]
        if params:
            cmd += ["--params-file", str(write_params_file(folder / f"{stamp}.params.yaml", params))]
        cmd += list(ros_args)
        return cls(cmd, env, folder / f"{stamp}.log")

    # -- state ----------------------------------------------------------------------------------
    @property
    def pid(self) -> int:
        return self.proc.pid

    @property
    def returncode(self) -> int | None:
        """Exit code (negative: killed by that signal), None while running."""
        return self.proc.poll()

    def running(self) -> bool:
        return self.proc.poll() is None

    def wait(self, timeout: float) -> int | None:
        """Wait up to ``timeout`` s for the process to end; its exit code or None."""
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None

    def output(self) -> str:
        """Everything the process has written so far (stdout and stderr)."""
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors="replace")

    def output_tail(self, n_chars: int = 3000) -> str:
        """The end of :meth:`output`, for assertion messages."""
        return f"--- {' '.join(self.cmd)} (rc={self.returncode}) ---\n" + self.output()[-n_chars:]

    # -- stopping -------------------------------------------------------------------------------
    def _signal_group(self, sig: int) -> None:
        try:
            os.killpg(self.proc.pid, sig)  # the session leader's pid is the group id
        except ProcessLookupError:
            pass

    def kill(self) -> int:
        """SIGKILL the whole process group now (a crash); returns the exit code."""
        self._signal_group(signal.SIGKILL)
        rc = self.proc.wait()
        self._signal_group(signal.SIGKILL)  # children that outlived the leader
        return rc

    def stop(self, sigint_timeout: float = 5.0) -> int:
        """SIGINT the process group; SIGKILL it if it has not ended after ``sigint_timeout`` s.

        Returns
        -------
        int
            The exit code (0 for a clean shutdown, negative signal number if killed).
        """
        try:
            if self.proc.poll() is None:
                self._signal_group(signal.SIGINT)
                try:
                    self.proc.wait(timeout=sigint_timeout)
                except subprocess.TimeoutExpired:
                    self._signal_group(signal.SIGKILL)
                    self.proc.wait()
            self._signal_group(signal.SIGKILL)  # whatever is left in the group
            return self.proc.returncode
        finally:
            self._log.close()

    @staticmethod
    def stop_all(procs) -> None:
        """SIGINT every running process of ``procs`` at once (they shut down side by side), then
        :meth:`stop` each (SIGKILL after 5 s)."""
        for p in procs:
            if p.running():
                p._signal_group(signal.SIGINT)
        for p in procs:
            p.stop()

    def __enter__(self) -> "NodeProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


class Received(NamedTuple):
    """A message received by :class:`RosTestClient`: ``time`` is ``time.perf_counter()`` at receipt."""

    time: float
    msg: Any


class MessageLog(list):
    """The messages of one subscription, in arrival order (a list of :class:`Received`)."""

    def __init__(self, topic: str):
        super().__init__()
        self.topic = topic
        self.subscription = None

    def messages(self) -> list:
        return [r.msg for r in self]

    def last(self):
        return self[-1].msg if self else None


class RosTestClient:
    """The test's own rclpy node on the network of ``env``, in a private ``Context``.

    It spins only inside :meth:`wait_for` / :meth:`spin_for` / :meth:`call`, so callbacks run in
    the test's thread. While it exists, the ROS variables of ``env`` are also set in this
    process's ``os.environ`` (the middleware reads some of them from there); they are restored
    by :meth:`close`.

    Parameters
    ----------
    env : mapping
        From :func:`isolated_ros_env`.
    name : str
        Node name.
    """

    def __init__(self, env: Mapping[str, str], name: str = "test_client"):
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self._saved = {k: os.environ.get(k) for k in ROS_ENV_KEYS}
        for k in ROS_ENV_KEYS:
            if k in env:
                os.environ[k] = env[k]
            else:
                os.environ.pop(k, None)
        self.context = Context()
        rclpy.init(context=self.context, domain_id=int(env["ROS_DOMAIN_ID"]))
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._publishers: dict[tuple[str, type], Any] = {}
        self._clients: dict[tuple[str, type], Any] = {}
        self._n_received = 0

    # -- spinning -------------------------------------------------------------------------------
    def spin_for(self, seconds: float) -> None:
        """Process callbacks for ``seconds``."""
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            self.executor.spin_once(timeout_sec=min(left, 0.05))

    def wait_for(self, predicate: Callable[[], bool], timeout: float) -> bool:
        """Process callbacks until ``predicate()`` is true or ``timeout`` s passed; its last value."""
        end = time.monotonic() + timeout
        while not predicate():
            left = end - time.monotonic()
            if left <= 0:
                return bool(predicate())
            self.executor.spin_once(timeout_sec=min(left, 0.05))
        return True

    def drain(self, timeout: float = 1.0) -> None:
        """Process the messages already waiting (a fast topic can queue up while the test does
        something else), until none is left or ``timeout`` s passed."""
        end = time.monotonic() + timeout
        idle = 0
        while idle < 2 and time.monotonic() < end:  # two empty rounds: a round may run a timer
            before = self._n_received
            self.executor.spin_once(timeout_sec=0.0)
            idle = idle + 1 if self._n_received == before else 0

    # -- topics ---------------------------------------------------------------------------------
    def subscribe(self, topic: str, msg_type, qos: Any = 100) -> MessageLog:
        """Subscribe and log every message (with its receive time) into the returned list.

        ``qos`` is a depth or a QoSProfile. For "the current state" of a fast topic subscribe
        with depth 1 (the middleware keeps only the newest message, nothing queues up even when
        this process is slow); for counting every message use a depth larger than what arrives
        while the test is not spinning, and :meth:`unsubscribe` when done (each message costs
        this process CPU time).
        """
        log = MessageLog(topic)

        def on_message(m):
            self._n_received += 1
            log.append(Received(time.perf_counter(), m))

        log.subscription = self.node.create_subscription(msg_type, topic, on_message, qos)
        return log

    def unsubscribe(self, log: MessageLog) -> None:
        """Stop filling ``log`` (the messages received so far stay in it)."""
        if log.subscription is not None:
            self.node.destroy_subscription(log.subscription)
            log.subscription = None

    def latest(self, log: MessageLog, timeout: float = 5.0):
        """The newest message of ``log``: process what is queued, then wait for one more message
        (so it was sent after this call started). Raises TimeoutError if none arrives."""
        self.drain()
        n = len(log)
        if not self.wait_for(lambda: len(log) > n, timeout):
            raise TimeoutError(f"no message on {log.topic} within {timeout} s")
        return log.last()

    def wait_for_messages(self, log: MessageLog, n: int, timeout: float) -> bool:
        """Wait until ``log`` holds at least ``n`` messages."""
        return self.wait_for(lambda: len(log) >= n, timeout)

    def publish(self, topic: str, msg, qos: Any = 10) -> None:
        """Publish ``msg`` on ``topic`` (the publisher is created on first use and kept)."""
        key = (topic, type(msg))
        if key not in self._publishers:
            self._publishers[key] = self.node.create_publisher(type(msg), topic, qos)
        self._publishers[key].publish(msg)

    def wait_for_subscriber(self, topic: str, timeout: float) -> bool:
        """Wait until some other node subscribes to ``topic`` (relative names resolve in '/')."""
        name = self.node.resolve_topic_name(topic)
        return self.wait_for(lambda: self.node.count_subscribers(name) > 0, timeout)

    def wait_for_publisher(self, topic: str, timeout: float) -> bool:
        """Wait until some node publishes ``topic``."""
        name = self.node.resolve_topic_name(topic)
        return self.wait_for(lambda: self.node.count_publishers(name) > 0, timeout)

    # -- services -------------------------------------------------------------------------------
    def _client(self, srv_type, name: str):
        key = (name, srv_type)
        if key not in self._clients:
            self._clients[key] = self.node.create_client(srv_type, name)
        return self._clients[key]

    def wait_for_service(self, srv_type, name: str, timeout: float, probe=None) -> bool:
        """Wait until service ``name`` is available; with ``probe`` (a request the server refuses
        or answers without side effects) also until the server has answered it.

        "Available" is this client's view of the discovery: it has matched the server's request
        reader and reply writer. The server matches this client's reply reader on its own
        schedule, and rmw_fastrtps drops a reply when that has not happened within the reply
        writer's ``max_blocking_time`` (100 ms by default; ros2/rmw_fastrtps#390, #704): the call
        then never returns. A probe that was answered proves the reply path, which stays matched
        for every later call through this client.
        """
        cli = self._client(srv_type, name)
        end = time.monotonic() + timeout
        if not self.wait_for(cli.service_is_ready, timeout):
            return False
        if probe is None:
            return True
        try:
            self.call(srv_type, name, probe, max(end - time.monotonic(), 0.0), resend_after=1.0)
        except TimeoutError:
            return False
        return True

    def call(self, srv_type, name: str, request=None, timeout: float = 10.0, resend_after: float | None = None):
        """Call a service and return its response.

        ``resend_after``: for a request that is safe to repeat, send it again whenever no reply
        came for that many seconds (a reply the server could not deliver is lost, see
        :meth:`wait_for_service`); the first reply is returned.

        Raises
        ------
        TimeoutError
            The service is not available or did not answer within ``timeout`` s (from the call).
        """
        cli = self._client(srv_type, name)
        end = time.monotonic() + timeout
        if not self.wait_for(cli.service_is_ready, timeout):
            raise TimeoutError(f"service '{name}' is not available after {timeout} s")
        request = srv_type.Request() if request is None else request
        sent = []
        while True:
            sent.append(cli.call_async(request))
            window = end - time.monotonic() if resend_after is None else min(resend_after, end - time.monotonic())
            if self.wait_for(lambda: any(f.done() for f in sent), max(window, 0.0)):
                fut = next(f for f in sent if f.done())
                for f in sent:
                    if f is not fut:
                        cli.remove_pending_request(f)
                return fut.result()
            if time.monotonic() >= end:
                for f in sent:
                    cli.remove_pending_request(f)
                raise TimeoutError(f"service '{name}' did not answer within {timeout} s"
                                   + (f" ({len(sent)} requests sent)" if len(sent) > 1 else ""))

    def wait_for_recorder(self, namespace: str = "", timeout: float = 30.0) -> bool:
        """Wait until the demo_recorder in ``namespace`` has answered on both of its services
        (:meth:`wait_for_service` with a probe each: start_recording of an invalid name, and
        stop_recording, which a recorder that is not recording refuses; neither has side effects
        then), so no later reply to this client is lost."""
        from deepprompt_msgs.srv import StartRecording, StopRecording

        prefix = namespace.rstrip("/") + "/" if namespace else ""
        return (self.wait_for_service(StartRecording, prefix + "start_recording", timeout,
                                      probe=StartRecording.Request(demo_name="-not-a-name"))
                and self.wait_for_service(StopRecording, prefix + "stop_recording", timeout,
                                          probe=StopRecording.Request()))

    # -- life cycle -----------------------------------------------------------------------------
    def close(self) -> None:
        """Destroy the node, shut the context down, restore ``os.environ`` (idempotent)."""
        import rclpy

        if self.node is None:
            return
        self.executor.shutdown()
        self.node.destroy_node()
        self.node = None
        rclpy.try_shutdown(context=self.context)
        for k, v in self._saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v

    def __enter__(self) -> "RosTestClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class JointStateTap:
    """Every message of a high-rate (500-1000 Hz) sensor_msgs/JointState topic, taken in batches
    from a subscription of the test client's node that no executor waits on
    (:class:`~deepprompt_ros.ros.fastpath.polled.NotExecuted`).

    Dispatching each message through an rclpy executor in the test process can fall behind a 1 kHz
    topic on a busy machine; taking the queued messages (serialized, deserialized in
    :meth:`arrays`) every few tens of ms keeps up. Call :meth:`take` often enough that fewer than
    ``depth`` messages queue up between calls.
    """

    def __init__(self, client: "RosTestClient", topic: str = "joint_states", depth: int = 10000):
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState

        from deepprompt_ros.ros.fastpath.polled import NotExecuted

        self.node = client.node
        self.sub = self.node.create_subscription(
            JointState, topic, lambda m: None, QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE),
            callback_group=NotExecuted(), raw=True)
        self.raw: list[bytes] = []

    def matched(self) -> bool:
        """The subscription has matched at least one publisher of the topic. A publisher known to the
        graph (``Node.count_publishers``) may not be matched yet; what it publishes before then is
        not received."""
        return self.sub.get_publisher_count() > 0

    def take(self) -> None:
        """Move the queued messages into :attr:`raw`."""
        from deepprompt_ros.ros.fastpath.polled import take_all

        self.raw.extend(msg for msg, _ in take_all(self.sub))

    def arrays(self, names: Sequence[str]):
        """Header stamps (N,) in ns, positions (N, d) and velocities (N, d; NaN where a message has
        none) in the order of ``names``."""
        import numpy as np
        from rclpy.serialization import deserialize_message
        from sensor_msgs.msg import JointState

        from deepprompt_ros.ros import conversions as conv

        msgs = [deserialize_message(b, JointState) for b in self.raw]
        d = len(names)
        stamps = np.array([conv.stamp_to_ns(m.header.stamp) for m in msgs], dtype=np.int64)
        q = np.array([conv.reorder_joints(m.name, m.position, names) for m in msgs]).reshape(-1, d)
        qd = np.array([conv.reorder_joints(m.name, m.velocity, names) if len(m.velocity) else np.full(d, np.nan)
                       for m in msgs]).reshape(-1, d)
        return stamps, q, qd

    def close(self) -> None:
        self.node.destroy_subscription(self.sub)
