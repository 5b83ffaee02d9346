"""Faults of the robot side, with real processes over real DDS (LOCALHOST discovery, random domain):
primitive_server started with ``config/primitive_server.yaml`` as shipped (the safety defaults
unchanged: ``stale_timeout`` 0.2 s, the shipped primitives) next to sim_bridge.

* sim_bridge killed mid-execution: the stream stops within the shipped stale_timeout (braking starts
  at most stale_timeout + one state poll + the look-ahead after the kill, and the stream ends at rest
  no later than the time-optimal stop from there), the goal ends ROBOT_STATE_STALE, no command
  follows its result; a new sim_bridge is served again by the same server and control process.
* joint_states published by the test instead of sim_bridge, first good then bad (NaN / inf positions,
  NaN velocities, unknown or missing joints, wrong array sizes): each bad kind is refused with a log
  line of the control process naming what was wrong, the running goal brakes to rest with
  ROBOT_STATE_STALE (its message names the refusal), no command carries a NaN, a new goal is refused
  with ROBOT_STATE_STALE naming the refusal, and a later good execution succeeds.
* a robot that lags behind its commands (sim_bridge at a quarter of real time): a goal sent as soon as
  the previous one ended starts from the last command, not from the measured state behind it (no
  setpoint jump at the restart).

Every command stream is checked with :func:`~deepprompt_ros.execution.limits.check_limits` over all
consecutive commands (a late tick adds one period of motion, so a skipped tick is no excuse for a jump).
"""
from __future__ import annotations

import re
import threading
import time

import numpy as np
import pytest
from deepprompt_msgs.action import Execute
from deepprompt_msgs.msg import ResultCode
from deepprompt_msgs.srv import Condition
from rclpy.action import ActionClient
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState

from deepprompt_ros.execution.limits import check_limits
from deepprompt_ros.robots.spec import load_robot
from deepprompt_ros.ros import conversions as conv
from deepprompt_ros.ros.fastpath import realtime
from deepprompt_ros.ros.fastpath.polled import NotExecuted, take_newest
from deepprompt_ros.ros.testing import JointStateTap, NodeProcess, RosTestClient
from deepprompt_ros.server.config import ServerConfig, robot_limits
from served_reach import reach_timing

SPEC = load_robot("gen3_lite")
NAMES = SPEC.joint_names
SHIPPED = ServerConfig()  # config/primitive_server.yaml holds exactly these defaults (test_server_logic)
LIMITS = robot_limits(SPEC, SHIPPED)
DT = 1e-3  # the Gen3 lite's control rate, the shipped control_rate_hz 0
SRV = "/primitive_server"
CHILD = re.compile(r"control loop running in its own process \(pid (\d+)\)")
#: joint_states per second of the test's own publisher, and physics steps (and joint_states) per
#: second of sim_bridge (less than the arm's 1 kHz: a lighter process on a busy machine)
FAKE_RATE_HZ = SIM_RATE_HZ = 250.0


# ------------------------------------------------------------------------------------------------
# processes
# ------------------------------------------------------------------------------------------------
class Sim:
    """The sim_bridge process of this module; :meth:`ensure` starts one when none runs."""

    def __init__(self, env):
        self.env = env
        self.proc: NodeProcess | None = None

    def ensure(self) -> NodeProcess:
        if self.proc is None or not self.proc.running():
            self.stop()
            self.proc = NodeProcess.start_module("deepprompt_ros.ros.sim_bridge", self.env, params={
                "camera.enabled": False, "publish_clock": False, "rate_hz": SIM_RATE_HZ})
        return self.proc

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.stop()
            self.proc = None


@pytest.fixture(scope="module")
def sim(ros_env):
    holder = Sim(ros_env)
    holder.ensure()
    try:
        yield holder
    finally:
        holder.stop()


@pytest.fixture(scope="module")
def server(ros_env, repo_root, sim):
    """primitive_server with the shipped parameters file, nothing overridden."""
    with NodeProcess.start_module("deepprompt_ros.ros.primitive_server", ros_env,
                                  params_files=[repo_root / "config" / "primitive_server.yaml"]) as proc:
        yield proc


class FakeRobot:
    """joint_states published by the test at FAKE_RATE_HZ from a thread of its own (a timer of the
    client's node would slow the client's executor down): the robot's joints at the newest
    joint_command position (a robot that follows every command exactly), or, with :attr:`bad` set,
    the message that function makes of it. Silent while :attr:`on` is False (sim_bridge publishes)."""

    def __init__(self, client: RosTestClient):
        node = client.node
        self.pub = node.create_publisher(JointState, "joint_states", 10)
        self.cmd = node.create_subscription(JointState, "joint_command", lambda m: None,
                                            QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE),
                                            callback_group=NotExecuted())
        self.q = np.array(SPEC.home, dtype=float)
        self.on = False
        self.bad = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        realtime.prepare_thread("fake_robot", 10)  # as a robot driver; refused: normal scheduling
        while not self._stop.wait(1.0 / FAKE_RATE_HZ):
            if not self.on:
                continue
            m = take_newest(self.cmd)
            if m is not None:
                self.q = conv.reorder_joints(m.name, m.position, NAMES)
            msg = conv.arrays_to_joint_state(NAMES, self.q, np.zeros(len(NAMES)), stamp_ns=time.time_ns())
            bad = self.bad
            self.pub.publish(msg if bad is None else bad(msg))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)


@pytest.fixture(scope="module")
def client(ros_env, server, sim):
    with RosTestClient(ros_env) as c:
        c.ac = ActionClient(c.node, Execute, f"{SRV}/execute")
        c.tap = JointStateTap(c, "joint_command")
        c.fake = FakeRobot(c)
        assert c.wait_for(c.ac.server_is_ready, 60), server.output_tail()
        assert c.wait_for(lambda: "receiving joint_states" in server.output(), 60), (
            server.output_tail() + sim.ensure().output_tail())
        assert c.wait_for(c.tap.matched, 30), server.output_tail()  # the control process's command publisher
        # durations of the executions (s): .ordinary, executable within the velocity limits; .fast, near the
        # shortest they allow (the lagging robot falls far behind its commands)
        c.timing = reach_timing(c)
        yield c
        c.fake.close()
        c.ac.destroy()


# ------------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------------
def condition(client) -> str:
    r = client.call(Condition, f"{SRV}/condition", Condition.Request(primitive="reach"), timeout=20)
    assert r.success, r.message
    return r.handle


def send(client, handle, feedback=None, duration=None):
    """Send a goal of ``duration`` s (default ``client.timing.ordinary``); its result future once accepted."""
    duration = client.timing.ordinary if duration is None else duration
    fut = client.ac.send_goal_async(Execute.Goal(handle=handle, duration=duration),
                                    feedback_callback=None if feedback is None else
                                    (lambda m: feedback.append(m.feedback)))
    assert client.wait_for(lambda: tap_and(client, fut.done), 10)
    gh = fut.result()
    assert gh.accepted
    return gh.get_result_async()


def tap_and(client, predicate):
    """``predicate()``, after moving the queued commands into the tap (called while waiting)."""
    client.tap.take()
    return predicate()


def wait_result(client, res, timeout=20.0):
    assert client.wait_for(lambda: tap_and(client, res.done), timeout), "no Execute result"
    return res.result().result


def fresh_commands(client):
    """Forget the commands taken so far (the next window starts empty)."""
    client.tap.take()
    client.tap.raw.clear()


def commands(client, quiet=0.2):
    """(stamps ns, q, qd) of the commands since :func:`fresh_commands`, once none came for ``quiet`` s."""
    while True:
        n = len(client.tap.raw)
        client.spin_for(quiet)
        client.tap.take()
        if len(client.tap.raw) == n:
            return client.tap.arrays(NAMES)


def assert_stream_ok(stamps, q, qd):
    """Finite, inside the position limits, stamps increasing, and every consecutive pair of commands
    within the velocity, acceleration and jerk limits (no jump anywhere, skipped ticks included:
    a late tick still moves by one period)."""
    assert q.shape[0] > 10, q.shape
    assert np.all(np.isfinite(q)) and np.all(np.isfinite(qd)), "a command carries NaN or inf"
    assert np.all(np.diff(stamps) > 0), "command stamps must increase"
    rep = check_limits(q, qd, None, DT, LIMITS)  # accelerations: from the velocities
    assert rep.ok(rtol=1e-6), rep
    assert np.all(qd[-1] == 0.0), "the stream must end at rest"


def stop_time_bound(qd, acc) -> float:
    """Upper bound (s) of the time-optimal stop of every joint from velocity ``qd`` and acceleration
    ``acc`` (d,) within the acceleration and jerk limits: bring the acceleration to the braking limit,
    brake at it, release it."""
    a_max, j_max = LIMITS.max_acceleration, LIMITS.max_jerk
    v_extra = acc ** 2 / (2 * j_max)  # velocity gained while the acceleration is reduced
    return float(np.max((np.abs(acc) + a_max) / j_max + (np.abs(qd) + v_extra) / a_max + a_max / j_max))


def start_when_served(client, feedback, duration=None, timeout=30.0):
    """Condition and send a goal, again while it is refused with ROBOT_STATE_STALE (the control process
    reports the state it receives every 10 ms; a new robot takes a moment to be discovered); the
    running goal's result future."""
    end = time.monotonic() + timeout
    while True:
        handle = condition(client)
        fresh_commands(client)
        fut = send(client, handle, feedback, duration)
        client.wait_for(lambda: tap_and(client, lambda: fut.done() or bool(feedback)), 10)
        if not fut.done():
            return fut
        res = fut.result().result
        assert res.code.value == ResultCode.ROBOT_STATE_STALE and time.monotonic() < end, res.message
        client.spin_for(0.2)


def start_and_reach(client, phase, duration=None, attempts=3):
    """A goal started and seen past ``phase`` (feedback), its result future and feedback list. A goal
    that ends before (the robot paused past stale_timeout on a busy machine: ROBOT_STATE_STALE) is
    sent again: the faults are injected into a running goal."""
    for _ in range(attempts):
        fb = []
        fut = start_when_served(client, fb, duration)
        assert client.wait_for(lambda: tap_and(client, lambda: (fb and fb[-1].phase > phase) or fut.done()), 20)
        if not fut.done():
            return fut, fb
        res = fut.result().result
        assert res.code.value == ResultCode.ROBOT_STATE_STALE, res.message
        print(f"goal ended before the fault, sent again: {res.message}")
    pytest.fail(f"{attempts} goals ended before reaching phase {phase}")


def run_to_success(client, duration=None, attempts=3):
    """A goal that succeeds once the server sees the robot; its commands are checked. A goal that the
    robot's pause past the shipped stale_timeout stopped (a Python simulation on a busy machine:
    ROBOT_STATE_STALE, the robot stopped reporting) is sent again: braking was the right answer."""
    for _ in range(attempts):
        fut = start_when_served(client, [], duration)
        res = wait_result(client, fut)
        stamps, q, qd = commands(client)
        assert_stream_ok(stamps, q, qd)
        if res.code.value != ResultCode.ROBOT_STATE_STALE or "the robot stopped reporting" not in res.message:
            break
        print(f"the robot paused, sent again: {res.message}")
    assert res.success and res.code.value == ResultCode.SUCCESS, res.message
    return res


# ------------------------------------------------------------------------------------------------
# sim_bridge killed and restarted
# ------------------------------------------------------------------------------------------------
def test_sim_bridge_killed_mid_execution_stops_the_stream_within_the_shipped_stale_timeout(client, sim, server):
    client.fake.on = False
    sim.ensure()
    fut, fb = start_and_reach(client, 0.2)
    t_kill = time.time_ns()
    sim.proc.kill()
    res = wait_result(client, fut, 10.0)
    t_result = time.time_ns()
    assert res.code.value == ResultCode.ROBOT_STATE_STALE and not res.success, res.message
    age = float(re.search(r"no joint_states for ([0-9.]+) s \(stale_timeout 0.2 s\)", res.message).group(1))
    assert SHIPPED.stale_timeout <= age <= SHIPPED.stale_timeout + 0.01, res.message  # checked every tick
    assert 0.2 < res.final_phase < 0.9, res
    stamps, q, qd = commands(client)
    assert_stream_ok(stamps, q, qd)
    assert stamps[-1] <= t_result, "a command after the result"
    # braking starts at the latest one state poll (10 ms) + stale_timeout + the look-ahead after the
    # kill (+ 20 ms of scheduling); from the commanded state there, the stop takes at most its time bound
    t_brake = t_kill + int((0.01 + SHIPPED.stale_timeout + SHIPPED.lookahead_ticks * DT + 0.02) * 1e9)
    k = int(np.searchsorted(stamps, t_brake))
    assert 0 < k < len(stamps), "the stream ended before braking could have started"
    bound = stop_time_bound(qd[k], (qd[k] - qd[k - 1]) / DT)
    assert stamps[-1] <= t_brake + int((bound + 0.005) * 1e9), (
        f"the stream ended {(stamps[-1] - t_kill) * 1e-9:.3f} s after the kill; the stop from "
        f"{(t_brake - t_kill) * 1e-9:.3f} s takes at most {bound:.3f} s")
    print(f"stale stop: stream ended {(stamps[-1] - t_kill) * 1e-6:.0f} ms after the kill (bound "
          f"{(t_brake - t_kill) * 1e-6 + bound * 1e3:.0f} ms), result after {(t_result - t_kill) * 1e-6:.0f} ms")
    n = len(client.tap.raw)
    client.spin_for(0.5)
    client.tap.take()
    assert len(client.tap.raw) == n, "commands after the goal ended"

    # a new sim_bridge: the same server (and control process) serves it
    pids = CHILD.findall(server.output())
    sim.ensure()
    run_to_success(client)
    assert server.running() and CHILD.findall(server.output()) == pids, "the server or its control process restarted"


# ------------------------------------------------------------------------------------------------
# bad joint_states published by the test
# ------------------------------------------------------------------------------------------------
def _with(**fields):
    def make(msg):
        for k, v in fields.items():
            setattr(msg, k, v(msg) if callable(v) else v)
        return msg
    return make


def _set(field, j, value):
    def make(msg):
        values = list(getattr(msg, field))
        values[j] = value
        setattr(msg, field, values)
        return msg
    return make


BAD = {  # kind: (message maker, what the log line says)
    "nan_position": (_set("position", 2, float("nan")), "position of joint_3 is nan"),
    "inf_position": (_set("position", 0, float("inf")), "position of joint_1 is inf"),
    "nan_velocity": (_set("velocity", 1, float("nan")), "velocity of joint_2 is nan"),
    "unknown_joints": (_with(name=[f"arm_{n}" for n in NAMES]), "is missing joint(s)"),
    "missing_joint": (_with(name=lambda m: list(m.name)[:3] + list(m.name)[4:],
                            position=lambda m: list(m.position)[:3] + list(m.position)[4:],
                            velocity=lambda m: list(m.velocity)[:3] + list(m.velocity)[4:]),
                      "is missing joint(s) ['joint_4']"),
    "short_position": (_with(position=lambda m: list(m.position)[:5]), "has 5 position values for 6 joint names"),
    "long_position": (_with(position=lambda m: list(m.position) + [0.0]), "has 7 position values for 6 joint names"),
    "short_velocity": (_with(velocity=lambda m: list(m.velocity)[:3]), "has 3 velocity values for 6 joint names"),
    "no_position": (_with(position=[]), "has no positions"),
}


def test_bad_joint_states_are_refused_the_goal_brakes_and_the_node_serves_on(client, sim, server):
    """For each bad kind in turn: a goal runs on good states, then only bad ones come; the goal brakes
    with ROBOT_STATE_STALE naming the refusal, the control process logs it, every command is finite
    and within the limits. The next kind's goal (and a last full execution) shows that the reader
    took good states again."""
    sim.stop()
    client.fake.bad, client.fake.on = None, True
    try:
        for kind, (make, logged) in BAD.items():
            log_before = len(server.output())
            fut, fb = start_and_reach(client, 0.02)  # good states from the test
            client.fake.bad = make
            res = wait_result(client, fut, 10.0)
            assert res.code.value == ResultCode.ROBOT_STATE_STALE and not res.success, (kind, res.message)
            assert "no valid joint_states for" in res.message and logged in res.message, (kind, res.message)
            assert res.final_phase < 0.95, (kind, res)
            stamps, q, qd = commands(client)
            assert_stream_ok(stamps, q, qd)
            log = server.output()[log_before:]
            assert "joint_states ignored: " in log and logged in log, (kind, server.output_tail())
            # while only bad states come, a new goal is refused at once, saying why
            res = wait_result(client, send(client, condition(client)), 10.0)
            assert res.code.value == ResultCode.ROBOT_STATE_STALE, (kind, res.message)
            assert "no valid joint_states on" in res.message and logged in res.message, (kind, res.message)
            client.fake.bad = None
        run_to_success(client)
        assert server.running() and "Traceback" not in server.output(), server.output_tail()
    finally:
        client.fake.bad, client.fake.on = None, False


# ------------------------------------------------------------------------------------------------
# a robot that lags behind its commands
# ------------------------------------------------------------------------------------------------
#: simulated seconds per wall-clock second of the lagging sim_bridge: its joints move at no more than a
#: quarter of the velocity limits in wall time, so they fall behind the commands of a fast motion (as a
#: simulation that cannot keep up does) and catch up only seconds after the commands stop
SLOW_FACTOR = 0.25


def test_a_goal_right_after_another_continues_from_the_last_command_while_the_robot_lags(client, sim, server):
    """A goal sent as soon as the previous one's result came (within the shipped stale_timeout of its last
    command) starts from that command, not from the measured state the lagging robot is at: the commands
    of both goals, the restart included, keep the limits pair by pair (no setpoint jump back to the
    robot). A restart later than stale_timeout (a busy machine delayed this client) starts from the
    measured state by design; it is sent again, at most three times."""
    client.fake.on = False
    sim.stop()
    sim.proc = NodeProcess.start_module("deepprompt_ros.ros.sim_bridge", sim.env, params={
        "camera.enabled": False, "publish_clock": False, "rate_hz": SIM_RATE_HZ, "real_time_factor": SLOW_FACTOR})
    js = JointStateTap(client, "joint_states")
    try:
        assert client.wait_for(lambda: js.take() or js.raw, 30), sim.proc.output_tail()
        for attempt in range(3):
            back = condition(client)  # the reach run backward: it starts where the first goal ends
            fut = start_when_served(client, [], duration=client.timing.fast)
            res = wait_result(client, fut)
            js.take()
            fut_b = client.ac.send_goal_async(Execute.Goal(handle=back, duration=client.timing.fast, reverse=True))
            if res.code.value != ResultCode.SUCCESS:  # the slow simulation paused past stale_timeout
                print(f"first goal ended {res.message}, sent again")
                wait_result(client, send_accepted(client, fut_b), 20.0)
                continue
            m = deserialize_message(js.raw[-1], JointState)  # the robot's state when the result came
            robot = conv.reorder_joints(m.name, m.position, NAMES)
            del js.raw[:-1]
            res_b = wait_result(client, send_accepted(client, fut_b), 20.0)
            stamps, q, qd = commands(client)
            k = int(np.argmax(np.diff(stamps)))  # the restart: the longest pause between two commands
            gap = (stamps[k + 1] - stamps[k]) * 1e-9
            if res_b.code.value == ResultCode.SUCCESS and gap < SHIPPED.stale_timeout - 0.02:
                break
            print(f"second goal {res_b.message} {gap:.3f} s after the first goal's last command, sent again")
        else:
            pytest.fail("no pair of goals ran back to back within stale_timeout in 3 attempts")
        assert_stream_ok(stamps, q, qd)  # both goals, every consecutive pair, the restart included
        lag = float(np.abs(robot - q[k]).max())
        # far more than one period at the velocity limit: a start from the measured state would jump
        assert lag > 10 * LIMITS.max_velocity.max() * DT, f"the robot lagged by {lag:.4f} rad only"
        # the new stream starts at the last command (within 1e-6 rad: the last ticks of the first goal's landing
        # move by up to ~4e-7 rad, and a command of them may be missing from this client's record), at rest, not
        # at the robot, which lags by more than 10 periods at the velocity limit
        assert np.all(np.abs(q[k + 1] - q[k]) < 1e-6), q[k + 1] - q[k]
        assert np.all(np.abs(qd[k]) < 1e-3) and np.all(qd[k + 1] == 0.0), (qd[k], qd[k + 1])
        print(f"restart {gap * 1e3:.0f} ms after the last command, the robot {lag:.3f} rad behind it")
    finally:
        js.close()
        sim.stop()


def send_accepted(client, fut):
    """The result future of a goal whose acceptance ``fut`` is pending."""
    assert client.wait_for(lambda: tap_and(client, fut.done), 10)
    gh = fut.result()
    assert gh.accepted
    return gh.get_result_async()

