"""The 1 kHz control loop of primitive_server in a process of its own (``loop_process: true``).

Why: in one interpreter the control thread and the service handlers share one interpreter lock.
With both in the node's process, a Condition request takes several times longer inside the
handler than alone and the loop misses periods while a request is handled
(``bench/bench_ros.py --param loop_process:=false`` shows both). Here the child process owns
everything that runs per tick: the :class:`~deepprompt_ros.execution.stream_loop.StreamLoop` with
its controller, the ``joint_command`` and JointTrajectory publishers and the joint_states reader
(:class:`~deepprompt_ros.ros.loop_io.LoopIO`), on its own rclpy context and its one node
(``<server>_control``, same namespace, topic names resolved by the server so remappings apply).
The server keeps the services and the Execute action. With ``fast_path: false`` the child also
spins its node with an executor (the joint_states subscription is then an ordinary callback).

Link: one Unix socket pair (``multiprocessing.connection.Connection``) carrying the typed messages
of :mod:`deepprompt_ros.execution.commands`: server -> child a ``LoopSetup`` once, then
``StartGoal`` (the per-Execute decoded dense trajectory), ``CancelGoal``, ``SetGoalRate``,
``StopLoop``; child -> server ``LoopReady`` (with the refused priority or CPU), a ``LoopStatus``
every ``STATUS_PERIOD`` s and a ``GoalDone`` when a goal's last sample has been published.

Lifetime: the child asks the kernel to kill it when the server dies (``PR_SET_PDEATHSIG``),
exits when the link closes, and ignores SIGINT (it shares the server's process group; the
server stops it with ``StopLoop`` on its way down). If the child exits unexpectedly, every
pending goal ends with INTERNAL_ERROR (the action never hangs), the error is logged, and a new
child is started (at most ``MAX_RESTARTS`` times); a goal sent while it starts waits for its first
robot state (at most ``RESTART_GRACE`` s) and is executed by it.

One module of about 400 lines on purpose: the two ends of the link, the server's proxy
(:class:`ControlProcess`) and the child's main loop, speak the same messages and change together.
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import itertools  # noqa: E402
import math  # noqa: E402
import signal  # noqa: E402
import socket  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from multiprocessing.connection import Connection  # noqa: E402

from deepprompt_ros.common.results import Code, RequestError  # noqa: E402
from deepprompt_ros.execution.commands import (CancelGoal, GoalDone, LoopReady, LoopSetup, LoopStatus,  # noqa: E402
                                               SetGoalRate, StartGoal, StopLoop)
from deepprompt_ros.execution.controller import ExecutionGoal, Outcome, Stage  # noqa: E402
from deepprompt_ros.ros.fastpath import realtime  # noqa: E402

__all__ = ["ControlProcess", "main"]

STATUS_PERIOD = 0.01  #: s between two status messages of the child


class ControlProcess:
    """Server-side proxy of the control loop in a child process; the same interface as the
    in-process :class:`~deepprompt_ros.execution.stream_loop.StreamLoop` offers the node
    (``execute``, ``cancel``, ``set_rate``, ``active_goal``, ``measured_age``, ``summary``,
    ``shutdown``).

    Parameters
    ----------
    setup : LoopSetup
        What every child (the first and each restarted one) is built from.
    logger : rclpy logger of the server (child exits and restarts are reported there).
    """

    MAX_RESTARTS = 5
    #: s after a restart during which a goal waits for the new process's first robot state (starting
    #: the interpreter, rclpy and the node, and discovering joint_states take a second or two)
    RESTART_GRACE = 5.0

    def __init__(self, setup: LoopSetup, logger):
        self._setup = setup
        self._log = logger
        self._lock = threading.Lock()
        self._goals: dict[int, ExecutionGoal] = {}
        self._keys = itertools.count(1)
        self._latest: ExecutionGoal | None = None
        self._stamp: float | None = None
        self._refused = ""  # why the child refused the joint_states since the newest accepted one
        self._summary = "no goal finished yet"
        self._stopping = False
        self._dead = ""          # why no child runs ('' = one runs)
        self.restarts = 0
        self.warnings = ""  #: the child's start-up warnings (refused priority or CPU), "" = none
        self.pid = 0
        self._ready = threading.Event()
        self._state_seen = threading.Event()  # the current child has reported a robot state
        self._grace_until = 0.0  # time.monotonic() until which a goal waits for a restarted child's state
        self._spawn()

    # ------------------------------------------------------------------ child lifecycle
    def _spawn(self) -> None:
        ours, theirs = socket.socketpair()
        fd = theirs.fileno()
        self.proc = subprocess.Popen([sys.executable, "-m", "deepprompt_ros.ros.control_process", str(fd),
                                      str(os.getpid())], pass_fds=(fd,), stdin=subprocess.DEVNULL)
        theirs.close()
        self.pid = self.proc.pid
        self._conn = Connection(ours.detach())
        self._stamp, self._refused = None, ""
        self._conn.send(self._setup)
        self._reader = threading.Thread(target=self._read, args=(self._conn, self.proc), name="control_link",
                                        daemon=True)
        self._reader.start()

    def _read(self, conn: Connection, proc: subprocess.Popen) -> None:
        realtime.name_os_thread("control_link")
        try:
            while True:
                self._handle(conn.recv())
        except (EOFError, OSError):
            pass
        except Exception as exc:  # a message we cannot read: treat the link as broken
            self._log.error(f"control process link failed: {exc!r}")
        try:
            code = proc.wait(2.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            code = proc.wait()
        with self._lock:  # (every send holds the lock: none is mid-write when the link closes, and a later one
            conn.close()  # gets the closed link's OSError, not a TypeError from a handle closed under it)
        if self._stopping:
            return
        why = f"the control process (pid {proc.pid}) exited unexpectedly with code {code}"
        with self._lock:
            self._dead = why
            pending, self._goals = list(self._goals.values()), {}
            self._stamp = None
            self._state_seen.clear()
            self._grace_until = time.monotonic() + self.RESTART_GRACE
        for goal in pending:
            goal._finish(Outcome(Code.INTERNAL_ERROR, f"{why}; the command stream stopped", goal.max_tracking_error,
                                 goal.progress.phase, goal.progress.cycle))
        self._log.error(why + (f"; {len(pending)} goal(s) aborted" if pending else ""))
        with self._lock:
            if self._stopping:
                return
            if self.restarts >= self.MAX_RESTARTS:
                self._dead = why + f" (not restarted: {self.restarts} restarts already)"
                self._grace_until = 0.0
                self._state_seen.set()  # nothing to wait for
                return
            self.restarts += 1
            self._spawn()
            self._dead = ""
        self._log.warn(f"control process restarted (pid {self.pid}, restart {self.restarts})")

    def _handle(self, msg) -> None:
        if isinstance(msg, LoopStatus):
            self._stamp, self._refused = msg.joint_states_stamp, msg.refused
            if msg.joint_states_stamp is not None:
                self._state_seen.set()
            goal = self._goals.get(msg.key)
            if goal is not None and msg.progress is not None and not goal.done.is_set():
                goal._progress, goal._tracking_error = msg.progress, msg.progress.tracking_error
                goal.stage = msg.stage
        elif isinstance(msg, GoalDone):
            self._summary = msg.loop_summary
            with self._lock:
                goal = self._goals.pop(msg.key, None)
            if goal is not None:
                goal.max_tracking_error = max(goal.max_tracking_error, msg.outcome.max_tracking_error)
                goal._finish(msg.outcome)
        elif isinstance(msg, LoopReady):
            self.warnings = msg.warnings
            self._ready.set()
            self._log.info(f"control loop running in its own process (pid {msg.pid})")
            if self.warnings:
                self._log.warn(self.warnings)
        else:
            raise TypeError(f"unexpected message from the control process: {msg!r}")

    def _send(self, msg) -> None:
        try:
            self._conn.send(msg)
        except OSError:  # the child is gone: the link thread reports it and fails the goals
            pass

    def wait_ready(self, timeout: float) -> bool:
        """Wait until the (first) child runs: its node, publishers and control thread exist."""
        return self._ready.wait(timeout)

    # ------------------------------------------------------------------ the loop's interface
    def execute(self, goal: ExecutionGoal) -> ExecutionGoal:
        with self._lock:
            if self._dead:
                goal._finish(Outcome(Code.INTERNAL_ERROR, f"no control loop: {self._dead}", 0.0,
                                     goal.plan.start_phase, 0))
                return goal
            goal._link_key = key = next(self._keys)
            self._goals[key] = goal
            latest = self._latest
            if latest is None or latest.done.is_set() or goal.order is None or latest.order is None \
                    or goal.order > latest.order:  # an older goal does not take the newer one's place
                self._latest = goal
            self._send(StartGoal(key, goal.plan, goal.order))
        return goal

    def cancel(self, goal: ExecutionGoal) -> None:
        key = getattr(goal, "_link_key", None)
        if key is not None and not goal.done.is_set():
            with self._lock:
                self._send(CancelGoal(key))

    @property
    def active_goal(self) -> ExecutionGoal | None:
        g = self._latest
        return g if g is not None and not g.done.is_set() else None

    def set_rate(self, rate: float) -> ExecutionGoal:
        goal = self.active_goal
        if goal is None or goal.stage in (Stage.STOPPING, Stage.DONE):
            raise RequestError(Code.NO_ACTIVE_EXECUTION, "no Execute goal is running; SetPhaseRate changes the "
                               "rate of a running goal")
        with self._lock:
            self._send(SetGoalRate(goal._link_key, float(rate)))
        return goal

    def measured_age(self) -> float:
        """Seconds since the robot state the control process received last (inf: none yet). Within
        ``RESTART_GRACE`` s of a restart, first waits for the new process's first state, so that a
        goal sent while it starts is executed by it rather than refused."""
        s = self._stamp
        if s is None and (wait := self._grace_until - time.monotonic()) > 0:
            self._state_seen.wait(wait)
            s = self._stamp
        return math.inf if s is None else time.monotonic() - s

    def state_refusal(self) -> str:
        """Why the control process refused the joint_states received since the newest accepted one
        ('' = none was)."""
        return self._refused

    def summary(self) -> str:
        """The child's loop summary sent with the latest outcome."""
        return f"control process {self.pid}: {self._summary}"

    def shutdown(self, timeout: float = 3.0) -> None:
        with self._lock:
            self._stopping = True
            self._send(StopLoop())
        try:
            self.proc.wait(timeout)
        except (subprocess.TimeoutExpired, KeyboardInterrupt):  # (a second SIGINT while waiting)
            self.proc.kill()
            self.proc.wait()
        self._reader.join(timeout)


# ======================================================================================== child
class _LinkedGoal(ExecutionGoal):
    """A goal in the child: wakes the reporter when it finishes."""

    def __init__(self, plan, key: int, wake: threading.Event, order: int | None = None):
        super().__init__(plan, str(key), order)
        self.key = key
        self._wake = wake

    def _finish(self, outcome) -> None:
        super()._finish(outcome)
        self._wake.set()


def _die_with_parent(parent_pid: int) -> bool:
    """PR_SET_PDEATHSIG = SIGKILL; False if the parent is already gone."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    return os.getppid() == parent_pid


def _child(fd: int, parent_pid: int) -> int:
    if not _die_with_parent(parent_pid):
        return 1
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the server stops this process through the link
    conn = Connection(fd)
    setup = conn.recv()
    if not isinstance(setup, LoopSetup):
        raise TypeError(f"the control process expects a LoopSetup first; got {setup!r}")
    cfg = setup.config
    warnings = []
    if cfg.control_cpu >= 0:  # before any thread exists: all inherit it
        warnings.append(realtime.set_cpu_affinity(cfg.control_cpu, "the control process"))
    if cfg.realtime_priority > 0:
        # Every thread of this process at SCHED_FIFO, set here before rclpy (its import starts two
        # threads), DDS and the loop create theirs (they inherit it): a normal-priority thread
        # holding the interpreter lock could otherwise be preempted by any other process while the
        # real-time control thread waits for that lock (priority inversion). The other threads sleep
        # almost always (status every STATUS_PERIOD, the link, the JointTrajectory snapshots); the
        # control thread sets its own priority again.
        realtime.set_fifo_priority(cfg.realtime_priority)  # refused: the control thread reports it

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from deepprompt_ros.ros.loop_io import LoopIO
    from deepprompt_ros.execution.controller import ExecutionController
    from deepprompt_ros.execution.stream_loop import StreamLoop

    realtime.set_switch_interval(cfg.gil_switch_interval)
    rclpy.init(args=[], signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(setup.node_name, namespace=setup.namespace, start_parameter_services=False)
    log = node.get_logger()
    io = LoopIO(node, setup.joint_names, setup.limits, cfg, setup.command_topic, setup.trajectory_topic,
                setup.joint_states_topic)
    loop = StreamLoop(ExecutionController(setup.limits, setup.dt, cfg), cfg, io.publish_command,
                      io.publish_trajectory, on_error=lambda m: log.error(m, throttle_duration_sec=1.0),
                      poll_measured=io.poll_joint_state, thread_setup=realtime.prepare_thread)
    io.on_measured, io.on_refused = loop.update_measured, loop.refuse_measured
    goals: dict[int, _LinkedGoal] = {}
    wake, stop, failed = threading.Event(), threading.Event(), threading.Event()
    send_lock = threading.Lock()

    def send(msg) -> None:
        with send_lock:
            conn.send(msg)

    def receive() -> None:
        realtime.name_os_thread("link_reader")
        try:
            while True:
                msg = conn.recv()
                if isinstance(msg, StartGoal):
                    goal = goals[msg.key] = _LinkedGoal(msg.plan, msg.key, wake, msg.order)
                    loop.execute(goal)
                elif isinstance(msg, CancelGoal):
                    if (goal := goals.get(msg.key)) is not None:
                        loop.cancel(goal)
                elif isinstance(msg, SetGoalRate):
                    if (goal := goals.get(msg.key)) is not None:
                        loop.set_goal_rate(goal, msg.phase_rate)
                elif isinstance(msg, StopLoop):
                    break
                else:
                    log.error(f"control process: unexpected message {msg!r} ignored")
        except (EOFError, OSError):
            pass
        stop.set()
        wake.set()

    executor = None
    if io.poll_joint_state is None:  # plain rclpy: joint_states arrive through an executor callback
        executor = SingleThreadedExecutor(context=node.context)
        executor.add_node(node)

        def spin() -> None:
            realtime.name_os_thread("executor")
            try:
                executor.spin()
            except Exception as exc:  # shut down; else the states stop coming: end, the server restarts us
                if not stop.is_set():
                    log.error(f"control process: its executor stopped ({exc!r}); no joint_states can arrive, "
                              "the process ends and the server starts a new one")
                    failed.set()
                    stop.set()
                    wake.set()

        threading.Thread(target=spin, name="executor", daemon=True).start()
    loop.start(threaded=True)
    loop.started.wait(5.0)
    threading.Thread(target=receive, name="link_reader", daemon=True).start()
    realtime.freeze_startup_objects()
    try:
        send(LoopReady(os.getpid(), "; ".join(w for w in (*warnings, loop.priority_error) if w)))
        while not stop.is_set():
            wake.wait(STATUS_PERIOD)
            wake.clear()
            for key, goal in list(goals.items()):
                if goal.done.is_set():
                    del goals[key]
                    send(GoalDone(key, goal.outcome, loop.summary()))
            a = loop.active_goal
            m = loop.measured
            send(LoopStatus(None if m is None else m.stamp, None if a is None else a.key,
                            None if a is None else a.stage, None if a is None else a.progress,
                            loop.state_refusal()))
    except (OSError, EOFError):
        pass
    finally:
        stop.set()
        loop.shutdown()
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        io.destroy()
        node.destroy_node()
        rclpy.try_shutdown()
        conn.close()
    return 1 if failed.is_set() else 0


def _exit_now(code: int) -> None:
    """Exit without interpreter finalization (nothing is left to clean up: the node is destroyed,
    the link closed); tearing down the extension objects took long and printed nanobind's leak
    report."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def main(argv=None) -> int:
    """``python -m deepprompt_ros.ros.control_process <fd> <parent pid>`` (started by ControlProcess)."""
    argv = sys.argv[1:] if argv is None else argv
    return _child(int(argv[0]), int(argv[1]))


if __name__ == "__main__":
    _exit_now(main())
