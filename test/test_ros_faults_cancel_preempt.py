"""Cancel and preempt at the edges of a goal, with real processes over real DDS (LOCALHOST discovery,
random domain): sim_bridge and primitive_server (shipped ``config/primitive_server.yaml``,
stale_timeout raised to 1 s), Execute goals from this test.

* at the first tick: a cancel sent as soon as the goal is accepted; a second goal sent as soon as the
  first is accepted (the goal accepted last wins, whichever plan the server finishes first);
* at the last tick: a cancel and a new goal when the feedback phase has reached the end;
* during braking: a second cancel, and a new goal while a canceled goal brakes (the canceled goal
  ends CANCELED, the new one splices onto the braking stream).

Each time the goals end with the code of what happened to them, with the matching action status,
and the command stream, taken from ``joint_command``, is finite, inside the position limits, with
every consecutive pair of commands within the velocity, acceleration and jerk limits (splices
included: no jump), and ends at rest.
"""
from __future__ import annotations

import numpy as np
import pytest
from action_msgs.msg import GoalStatus
from deepprompt_msgs.action import Execute
from deepprompt_msgs.msg import ResultCode
from deepprompt_msgs.srv import Condition
from rclpy.action import ActionClient

from deepprompt_ros.execution.limits import check_limits
from deepprompt_ros.robots.spec import load_robot
from deepprompt_ros.ros.testing import JointStateTap, NodeProcess, RosTestClient
from deepprompt_ros.server.config import ServerConfig, robot_limits
from served_reach import reach_timing

SPEC = load_robot("gen3_lite")
LIMITS = robot_limits(SPEC, ServerConfig())
DT = 1e-3
SRV = "/primitive_server"


@pytest.fixture(scope="module")
def client(ros_env, repo_root):
    procs = {}
    try:
        procs["sim"] = NodeProcess.start_module("deepprompt_ros.ros.sim_bridge", ros_env, params={
            "camera.enabled": False, "publish_clock": False, "rate_hz": 250.0})
        # stale_timeout 1 s: the simulation can pause past the shipped 0.2 s on a busy machine, and staleness
        # is not what this file tests (test_ros_faults_robot.py runs the shipped value)
        procs["server"] = NodeProcess.start_module("deepprompt_ros.ros.primitive_server", ros_env,
                                                   params_files=[repo_root / "config" / "primitive_server.yaml"],
                                                   params={"stale_timeout": 1.0})
        with RosTestClient(ros_env) as c:
            c.server = procs["server"]
            c.ac = ActionClient(c.node, Execute, f"{SRV}/execute")
            c.tap = JointStateTap(c, "joint_command")
            assert c.wait_for(c.ac.server_is_ready, 60), c.server.output_tail()
            assert c.wait_for(lambda: "receiving joint_states" in c.server.output(), 60), (
                c.server.output_tail() + procs["sim"].output_tail())
            # the commands come from the server's control process: a goal's first commands are only received
            # once this subscription has matched its publisher
            assert c.wait_for(c.tap.matched, 60), c.server.output_tail()
            c.handle = handle(c)
            # every goal runs near the shortest duration the velocity limits allow for that handle (the prior
            # mean, timed as the server times it): c.timing.fast; a goal canceled while braking is canceled
            # at the phase of the reach's top speed (.fastest_phase()), braking from there takes about a second
            c.timing = reach_timing(c)
            yield c
            c.ac.destroy()
    finally:
        for p in procs.values():
            p.stop()


def handle(client) -> str:
    r = client.call(Condition, f"{SRV}/condition", Condition.Request(primitive="reach"), timeout=20)
    assert r.success, r.message
    return r.handle


def until(client, predicate, timeout):
    """Spin (taking the commands into the tap) until ``predicate()``."""
    return client.wait_for(lambda: client.tap.take() or predicate(), timeout)


class Goal:
    """One Execute goal of the test: its handle, feedback and result."""

    def __init__(self, client, duration, wait_accepted=True):
        self.client = client
        self.feedback = []
        self.sent = client.ac.send_goal_async(Execute.Goal(handle=client.handle, duration=duration),
                                              feedback_callback=lambda m: self.feedback.append(m.feedback))
        if wait_accepted:
            self.accepted()

    def accepted(self):
        assert until(self.client, self.sent.done, 10)
        self.gh = self.sent.result()
        assert self.gh.accepted
        self.res = self.gh.get_result_async()
        return self

    @property
    def phase(self) -> float:
        return self.feedback[-1].phase if self.feedback else 0.0

    def wait_phase(self, phase, timeout=20.0):
        assert until(self.client, lambda: self.phase >= phase or self.res.done(), timeout)
        assert not self.res.done(), self.res.result().result.message

    def cancel(self):
        fut = self.gh.cancel_goal_async()
        assert until(self.client, fut.done, 5)
        return fut.result()

    def result(self, timeout=30.0):
        """(result, action status)."""
        assert until(self.client, self.res.done, timeout), "no Execute result"
        r = self.res.result()
        return r.result, r.status


def fresh(client):
    assert until(client, lambda: True, 1)
    client.tap.raw.clear()


def assert_stream_ok(client):
    """The commands since :func:`fresh`, once none came for 0.2 s: finite, inside the limits, every
    consecutive pair within the limits (no jump, splices included), ending at rest."""
    while True:
        n = len(client.tap.raw)
        client.spin_for(0.2)
        client.tap.take()
        if len(client.tap.raw) == n:
            break
    stamps, q, qd = client.tap.arrays(SPEC.joint_names)
    assert q.shape[0] > 10 and np.all(np.isfinite(q)) and np.all(np.isfinite(qd))
    assert np.all(np.diff(stamps) > 0)
    rep = check_limits(q, qd, None, DT, LIMITS)  # accelerations: from the velocities
    assert rep.ok(rtol=1e-6), rep
    assert np.all(qd[-1] == 0.0), "the stream ends moving"
    return stamps, q, qd


def assert_canceled(result, status):
    assert result.code.value == ResultCode.CANCELED and not result.success, result.message
    assert status == GoalStatus.STATUS_CANCELED, status


def assert_succeeded(result, status):
    assert result.success and result.code.value == ResultCode.SUCCESS, result.message
    assert status == GoalStatus.STATUS_SUCCEEDED and result.final_phase == 1.0, (status, result)


# ------------------------------------------------------------------------------------------------
def test_cancel_at_the_first_tick(client):
    fresh(client)
    g = Goal(client, client.timing.fast)
    reply = g.cancel()
    assert len(reply.goals_canceling) == 1
    result, status = g.result()
    assert_canceled(result, status)
    assert result.final_phase < 0.1, result  # stopped at once
    assert_stream_ok(client)


def test_a_goal_sent_at_the_first_tick_of_another_preempts_it(client):
    fresh(client)
    a = Goal(client, client.timing.fast)
    b = Goal(client, client.timing.fast)  # accepted after a, while a's plan is being made or at a's first tick
    ra, sa = a.result()
    rb, sb = b.result()
    assert ra.code.value == ResultCode.PREEMPTED and sa == GoalStatus.STATUS_ABORTED, ra.message
    assert ra.message.startswith("preempted by a newer Execute goal") and ra.final_phase < 0.1, ra
    assert_succeeded(rb, sb)
    assert_stream_ok(client)


def test_cancel_at_the_last_tick(client):
    fresh(client)
    g = Goal(client, client.timing.fast)
    g.wait_phase(0.99)  # the clock's end: the goal settles onto the end state
    reply = g.cancel()
    result, status = g.result()
    if result.code.value == ResultCode.SUCCESS:  # it finished before the cancel reached it
        assert_succeeded(result, status)
        assert len(reply.goals_canceling) in (0, 1)
    else:
        assert_canceled(result, status)
        assert result.final_phase >= 0.99, result
    print(f"cancel at the last tick: {result.message}")
    assert_stream_ok(client)


def test_a_goal_sent_at_the_last_tick_of_another_preempts_it_or_follows_it(client):
    fresh(client)
    a = Goal(client, client.timing.fast)
    a.wait_phase(0.99)
    b = Goal(client, client.timing.fast)
    ra, sa = a.result()
    rb, sb = b.result()
    if ra.code.value == ResultCode.SUCCESS:
        assert_succeeded(ra, sa)
    else:
        assert ra.code.value == ResultCode.PREEMPTED and sa == GoalStatus.STATUS_ABORTED, ra.message
        assert ra.final_phase >= 0.99, ra
    print(f"goal at the last tick: first {ra.message}")
    assert_succeeded(rb, sb)
    assert_stream_ok(client)


def test_a_second_cancel_while_braking_changes_nothing(client):
    fresh(client)
    g = Goal(client, client.timing.fast)
    cancel_at = client.timing.fastest_phase()
    g.wait_phase(cancel_at)
    assert len(g.cancel().goals_canceling) == 1
    until(client, lambda: False, 0.15)  # applied within a feedback period (50 ms) + the look-ahead
    assert not g.res.done(), g.res.result().result.message
    g.cancel()
    result, status = g.result()
    assert_canceled(result, status)
    assert cancel_at <= result.final_phase < 1.0, result
    assert_stream_ok(client)


def test_a_goal_sent_while_a_canceled_goal_brakes_takes_over_and_the_canceled_one_ends_canceled(client):
    fresh(client)
    a = Goal(client, client.timing.fast)
    a.wait_phase(client.timing.fastest_phase())
    assert len(a.cancel().goals_canceling) == 1
    until(client, lambda: False, 0.15)  # braking
    assert not a.res.done(), a.res.result().result.message
    b = Goal(client, client.timing.fast)
    ra, sa = a.result()
    rb, sb = b.result()
    assert_canceled(ra, sa)
    assert "canceled" in ra.message and "took over" in ra.message, ra.message
    assert_succeeded(rb, sb)
    stamps, q, qd = assert_stream_ok(client)
    # one motion: at rest only while held at the start (the look-ahead's first samples) and at the end
    rest = np.flatnonzero(np.all(qd == 0.0, axis=1))
    lookahead = ServerConfig().lookahead_ticks
    assert not np.any((rest >= lookahead) & (rest < len(qd) - 1)), "the new goal must splice onto the braking stream"
