"""The command stream across goals (deepprompt_ros.execution: controller, stream_loop), without ROS:
where a new stream starts (from the last command while the robot's controller still holds it, from
the measured state after an idle time longer than stale_timeout), against a robot that lags behind
its commands as a slow simulation does; and a tick that raises: every goal waiting in the stream
ends with a result code, and the loop serves on.

Plans are built directly from a grid (ExecutionReference) on a two-joint arm; Ruckig is the real one.
"""
from __future__ import annotations

import time
from dataclasses import replace as dataclass_replace

import numpy as np

from deepprompt_ros.common.results import Code
from deepprompt_ros.execution.controller import ExecutionController, ExecutionGoal, MeasuredState
from deepprompt_ros.execution.limits import JointLimits, check_limits
from deepprompt_ros.execution.plan import ExecutionPlan, ExecutionReference
from deepprompt_ros.execution.settings import LoopSettings
from deepprompt_ros.execution.stream_loop import StreamLoop

DT = 1e-3
LIMITS = JointLimits(lower=[-2.0, -2.0], upper=[2.0, 2.0], max_velocity=[1.0, 1.5], max_acceleration=[4.0, 5.0],
                     max_jerk=[50.0, 60.0], names=("a", "b"))
CFG = LoopSettings()  # shipped values: stale_timeout 0.2 s, lookahead 30 ticks


def plan(start, end, duration=1.0, name="move") -> ExecutionPlan:
    """A smooth (minimum-jerk shaped) motion from ``start`` to ``end``, shape (2,) each."""
    x = np.linspace(0.0, 1.0, 201)[:, None]
    s = 10 * x**3 - 15 * x**4 + 6 * x**5
    y = np.asarray(start) + s * (np.asarray(end) - np.asarray(start))
    return ExecutionPlan(name, name, ExecutionReference(y, periodic=False), duration, False, 1, False)


class LaggingRobot:
    """Drives an ExecutionController tick by tick; the robot moves towards the latest command at no
    more than ``speed`` x v_max (a simulation running slower than real time lags behind its commands
    and catches up once they stop). Every published command is kept with its tick number."""

    def __init__(self, q0, speed=0.4, config=CFG):
        self.ctl = ExecutionController(LIMITS, DT, config)
        self.k = 0
        self.t0 = 1000.0
        self.robot = np.array(q0, float)
        self.speed = speed
        self.command = self.robot.copy()
        self.ticks, self.q, self.qd = [], [], []

    @property
    def now(self) -> float:
        return self.t0 + self.k * DT

    @property
    def measured(self) -> MeasuredState:
        return MeasuredState(self.robot.copy(), None, self.now)

    def _robot_step(self):
        step = self.speed * LIMITS.max_velocity * DT
        self.robot += np.clip(self.command - self.robot, -step, step)

    def tick(self):
        s = self.ctl.pop_due(self.measured, self.now)
        if s is not None:
            self.command = s.q.copy()
            self.ticks.append(self.k), self.q.append(s.q), self.qd.append(s.qd)
        self.ctl.check_faults(self.measured, self.now)
        self.ctl.compute_next()
        self._robot_step()
        self.k += 1

    def idle(self, seconds):
        """No ticks (the loop sleeps while idle); the robot keeps moving towards the last command."""
        for _ in range(int(round(seconds / DT))):
            self._robot_step()
            self.k += 1

    def run(self, goal, max_ticks=20000):
        self.ctl.start_goal(goal, self.measured, self.now)
        for _ in range(max_ticks):
            self.tick()
            if goal.done.is_set() and self.ctl.idle:
                return goal.outcome
        raise AssertionError("the goal did not end")

    def report(self):
        """check_limits over every published command, the tick numbers as times (a gap of k ticks
        allows k periods of motion)."""
        t = np.array(self.ticks, float) * DT
        return check_limits(np.array(self.q), np.array(self.qd), None, DT, LIMITS, t=t)


def test_a_goal_right_after_another_starts_from_the_last_command_not_from_the_lagging_robot():
    a, b = plan([0.0, 0.0], [0.8, -0.9]), plan([0.8, -0.9], [0.1, 0.3])
    run = LaggingRobot([0.0, 0.0])
    assert run.run(ExecutionGoal(a)).code == Code.SUCCESS
    last = run.q[-1].copy()
    lag = np.abs(run.robot - last).max()
    assert lag > 0.05, f"the robot should lag behind the end of the first goal; lag {lag}"
    n = len(run.q)
    run.idle(0.05)  # the next goal comes 50 ms later (< stale_timeout): the robot has not caught up
    assert np.abs(run.robot - last).max() > 0.02
    assert run.run(ExecutionGoal(b)).code == Code.SUCCESS
    # the new stream starts exactly where the last one ended, and every command is within the limits
    np.testing.assert_array_equal(run.q[n], last)
    rep = run.report()
    assert rep.ok(), rep
    assert rep.fd_velocity_ratio <= 1 + 1e-9
    np.testing.assert_allclose(run.q[-1], [0.1, 0.3], atol=1e-6)


def test_after_an_idle_time_longer_than_stale_timeout_a_goal_starts_from_the_measured_state():
    a = plan([0.0, 0.0], [0.8, -0.9])
    run = LaggingRobot([0.0, 0.0], speed=0.4)
    assert run.run(ExecutionGoal(a)).code == Code.SUCCESS
    n = len(run.q)
    run.robot = np.array([0.75, -0.85])  # moved while the server was idle (another controller, a hand)
    run.command = run.robot.copy()
    run.idle(CFG.stale_timeout + 0.05)
    b = plan([0.75, -0.85], [0.2, 0.2])
    assert run.run(ExecutionGoal(b)).code == Code.SUCCESS
    np.testing.assert_allclose(run.q[n], [0.75, -0.85], atol=1e-12)  # where the robot is, not the old command


def test_the_first_goal_starts_from_the_measured_state():
    run = LaggingRobot([0.3, -0.2])
    assert run.run(ExecutionGoal(plan([0.3, -0.2], [0.5, 0.0], 0.5))).code == Code.SUCCESS
    np.testing.assert_allclose(run.q[0], [0.3, -0.2], atol=1e-12)
    assert run.report().ok()


# ------------------------------------------------------------------------------------------------
# a tick that raises: every goal still waiting ends with a result
# ------------------------------------------------------------------------------------------------
def nan_plan() -> ExecutionPlan:
    """A plan whose grid is NaN: the streamer refuses its reference (ValueError) in the tick that
    first tracks it (the server refuses such a handle before the loop; here it stands for any
    failure inside a tick)."""
    return ExecutionPlan("bad", "bad", ExecutionReference(np.full((11, 2), np.nan), periodic=False), 1.0, False, 1,
                         False)


class PerfectRobot:
    """A StreamLoop whose robot reports every command it is given; ticks are driven by hand
    (:meth:`StreamLoop.timer_tick`, the 'timer' mode) or by the loop's own thread."""

    def __init__(self, q0):
        self.errors = []
        self.ctl = ExecutionController(LIMITS, DT, CFG)
        self.loop = StreamLoop(self.ctl, CFG, publish_command=self._publish, on_error=self.errors.append)
        self.loop.update_measured(np.array(q0, float))
        self.q = []

    def _publish(self, q, qd, qdd, due):
        self.q.append(q)
        self.loop.update_measured(q.copy())

    def until(self, pred, max_ticks=20000):
        for _ in range(max_ticks):
            self.loop.timer_tick()
            if pred():
                return
        raise AssertionError("condition not reached")


def test_a_tick_that_raises_after_a_preempt_ends_the_preempted_goal_and_the_failed_one():
    run = PerfectRobot([0.0, 0.0])
    a = ExecutionGoal(plan([0.0, 0.0], [0.6, -0.6], 1.0))
    run.loop.execute(a)
    run.until(lambda: a.progress.phase > 0.3)
    b = run.loop.execute(ExecutionGoal(nan_plan()))
    run.loop.timer_tick()  # b splices on (a is preempted), then its first sample raises
    assert a.done.is_set() and b.done.is_set(), "a goal was left without a result"
    assert a.outcome.code == Code.PREEMPTED, a.outcome
    assert "its last commands were not published" in a.outcome.message and "ValueError" in a.outcome.message
    assert b.outcome.code == Code.INTERNAL_ERROR and "control loop failure" in b.outcome.message, b.outcome
    assert any("control loop tick failed" in e for e in run.errors), run.errors
    assert run.ctl.idle  # nothing of the cut stream is published later
    # the loop serves on: a new goal starts from the measured state and runs to its end
    n = len(run.q)
    c = run.loop.execute(ExecutionGoal(plan(run.q[-1], [0.0, 0.0], 1.0)))
    run.until(lambda: c.done.is_set())
    assert c.outcome.code == Code.SUCCESS, c.outcome
    np.testing.assert_array_equal(run.q[n], run.q[n - 1])


def test_a_tick_that_raises_while_taking_over_ends_both_goals():
    run = PerfectRobot([0.0, 0.0])
    a = run.loop.execute(ExecutionGoal(plan([0.0, 0.0], [0.6, -0.6], 1.0)))
    run.until(lambda: a.progress.phase > 0.3)
    bad = ExecutionGoal(dataclass_replace(plan([0.0, 0.0], [0.1, 0.1]), duration=0.0))  # its clock raises
    run.loop.execute(bad)
    run.loop.timer_tick()
    assert a.outcome.code == Code.PREEMPTED, a.outcome
    assert bad.outcome.code == Code.INTERNAL_ERROR and "duration/period T" in bad.outcome.message, bad.outcome


def test_a_success_not_yet_published_when_a_tick_raises_ends_internal_error():
    run = PerfectRobot([0.0, 0.0])
    a = run.loop.execute(ExecutionGoal(plan([0.0, 0.0], [0.3, 0.2], 0.5)))
    run.until(lambda: run.ctl.active is None)  # the last sample computed, the look-ahead not yet published
    assert not a.done.is_set()
    b = run.loop.execute(ExecutionGoal(nan_plan()))
    run.loop.timer_tick()
    assert a.outcome.code == Code.INTERNAL_ERROR and "end of the motion was not published" in a.outcome.message
    assert b.outcome.code == Code.INTERNAL_ERROR


def test_the_control_thread_survives_a_tick_that_raises_and_every_goal_gets_a_result():
    run = PerfectRobot([0.0, 0.0])
    run.loop.start(threaded=True)
    try:
        a = run.loop.execute(ExecutionGoal(plan([0.0, 0.0], [0.6, -0.6], 1.0)))
        deadline = time.monotonic() + 10
        while a.progress.phase < 0.3 and time.monotonic() < deadline:
            time.sleep(0.005)
        b = run.loop.execute(ExecutionGoal(nan_plan()))
        assert a.done.wait(5) and b.done.wait(5), "a goal was left without a result"
        assert (a.outcome.code, b.outcome.code) == (Code.PREEMPTED, Code.INTERNAL_ERROR), (a.outcome, b.outcome)
        c = run.loop.execute(ExecutionGoal(plan(run.q[-1], [0.0, 0.0], 0.8)))
        assert c.done.wait(10) and c.outcome.code == Code.SUCCESS, c.outcome
    finally:
        run.loop.shutdown()


def test_the_shortest_duration_is_where_the_fastest_joint_reaches_its_velocity_limit():
    # y_0 = sin(πx) has |y'| <= π at x = 0, 1 (0 at x = 0.5); y_1 = 2x has |y'| = 2 everywhere
    x = np.linspace(0.0, 1.0, 2001)
    ref = ExecutionReference(np.stack([np.sin(np.pi * x), 2.0 * x], axis=1), periodic=False, h=0.001)
    v_max = np.array([1.0, 0.5])  # joint 1 needs 2 / 0.5 = 4 s, joint 0 at most π s
    ratios = ref.velocity_limit_ratios(v_max)
    assert ratios.shape == (2001,)
    np.testing.assert_allclose(ratios, np.maximum(np.abs(np.pi * np.cos(np.pi * x)), 4.0), rtol=1e-5, atol=1e-5)
    assert abs(ref.shortest_duration(v_max) - 4.0) < 1e-9
    assert abs(ref.shortest_duration([0.5, 4.0]) - 2.0 * np.pi) < 1e-4  # now joint 0's peak decides
