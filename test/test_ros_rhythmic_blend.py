"""primitive_server over real DDS (LOCALHOST discovery, random domain), every node a real process:

1. the rhythmic WAM primitive (models/wam_shake.safetensors) on the simulated 7-joint WAM, run
   for 3 cycles: the command stream has no jump at the seams between cycles and stays within the
   WAM's position / velocity / acceleration limits;
2. a blend of two conditioned Gen3 lite reach primitives (weight of a: 1 at phase 0 -> 0 at
   phase 1), executed while the phase rate is halved and restored: the command stream stays
   within the limits and has no jump at the rate changes.
"""
import pathlib
import time

import numpy as np
import pytest
import yaml
from deepprompt_msgs.action import Execute
from deepprompt_msgs.msg import Context, ResultCode
from deepprompt_msgs.srv import Blend, Condition, SetPhaseRate
from rclpy.action import ActionClient

from deepprompt_ros.server.config import ServerConfig, robot_limits
from deepprompt_ros.robots.spec import load_robot
from deepprompt_ros.execution.limits import check_limits
from deepprompt_ros.ros import conversions as conv
from deepprompt_ros.ros.testing import JointStateTap, NodeProcess, RosTestClient, isolated_ros_env

SRV = "/primitive_server"


def model_path(name: str) -> str:
    p = pathlib.Path(__file__).resolve().parents[1] / "models" / name
    assert p.is_file(), p
    return str(p)


def limit_report(stamps, q, qd, limits, dt):
    """check_limits over the whole stream. Consecutive commands are consecutive samples of the
    stream, dt apart in its own time: the server's loop publishes one buffered sample per tick and
    stamps it with the tick's deadline, and a late tick moves the deadlines on (a stamp gap that is
    no lost sample). Returns the worst ratios and the number of such stamp gaps."""
    assert np.all(np.diff(stamps) > 0), "command stamps must increase"
    late = int(np.sum(np.round(np.diff(stamps) / (dt * 1e9)) != 1))
    acc = np.vstack([np.zeros((1, q.shape[1])), np.diff(qd, axis=0) / dt])
    rep = check_limits(q, qd, acc, dt, limits)
    worst = dict(velocity=rep.velocity_ratio, fd_velocity=rep.fd_velocity_ratio,
                 fd_acceleration=rep.fd_acceleration_ratio, position_excess=rep.position_excess)
    return worst, late


def assert_within_limits(worst, q, limits):
    assert np.all(q >= limits.lower) and np.all(q <= limits.upper)
    assert worst["position_excess"] == 0.0, worst
    assert worst["velocity"] <= 1 + 1e-6 and worst["fd_velocity"] <= 1 + 1e-6, worst
    assert worst["fd_acceleration"] <= 1 + 1e-6, worst  # no velocity jump anywhere


class Rig:
    """sim_bridge + primitive_server + this test's client and command / state taps."""

    def __init__(self, tmp, robot: str, primitives: list[dict]):
        self.tmp = tmp
        self.env = isolated_ros_env(tmp / "log")
        prims = tmp / "primitives.yaml"
        prims.write_text(yaml.safe_dump({"primitives": primitives}))
        self.procs = {}
        self.procs["sim"] = NodeProcess.start_module("deepprompt_ros.ros.sim_bridge", self.env, params={
            "robot": robot, "real_time_factor": 1.0, "camera.enabled": False, "publish_clock": False})
        self.procs["server"] = NodeProcess.start_module("deepprompt_ros.ros.primitive_server", self.env, params={
            "robot": robot, "primitives_file": str(prims),
            "stale_timeout": 1.0})  # above the default 0.2 s: pauses of the Python sim are not under test
        self.client = RosTestClient(self.env)
        self.ac = ActionClient(self.client.node, Execute, f"{SRV}/execute")
        self.cmd = JointStateTap(self.client, "joint_command")
        self.states = JointStateTap(self.client, "joint_states")

    def wait_ready(self):
        server = self.procs["server"]
        assert self.client.wait_for(self.ac.server_is_ready, 60.0), server.output_tail()
        assert self.client.wait_for(lambda: "receiving joint_states" in server.output(), 60.0), (
            server.output_tail() + self.procs["sim"].output_tail())
        # the commands come from the server's control process (another DDS participant): its
        # publisher is discovered on its own, possibly after the action server; its first commands are
        # received once this subscription has matched it
        assert self.client.wait_for(self.cmd.matched, 60.0), server.output_tail()

    def call(self, srv, name, req, timeout=20.0):
        return self.client.call(srv, f"{SRV}/{name}", req, timeout=timeout)

    def take(self):
        self.cmd.take()
        self.states.take()

    def spin_taking(self, predicate, timeout):
        return self.client.wait_for(lambda: self.take() or predicate(), timeout)

    def close(self):
        try:
            self.cmd.close()
            self.states.close()
            self.ac.destroy()
            self.client.close()
        finally:
            for p in self.procs.values():
                p.stop()


@pytest.fixture
def rig_factory(tmp_path):
    rigs = []

    def make(robot, primitives):
        rig = Rig(tmp_path / robot, robot, primitives)
        rigs.append(rig)
        return rig

    yield make
    for r in rigs:
        r.close()


def execute(rig, goal, during=None, timeout=60.0):
    """Send ``goal``; ``during(feedback, result_future)`` runs after acceptance. Returns the result,
    the feedback list and the wall time."""
    fb = []
    rig.take()
    rig.cmd.raw.clear()
    rig.states.raw.clear()
    t0 = time.perf_counter()
    fut = rig.ac.send_goal_async(goal, feedback_callback=lambda m: fb.append(m.feedback))
    assert rig.spin_taking(fut.done, 10.0) and fut.result().accepted
    res_fut = fut.result().get_result_async()
    if during is not None:
        during(fb, res_fut)
    assert rig.spin_taking(res_fut.done, timeout), rig.procs["server"].output_tail()
    wall = time.perf_counter() - t0
    rig.spin_taking(lambda: False, 0.3)  # the braking tail / last commands
    rig.take()
    return res_fut.result().result, fb, wall


# ------------------------------------------------------------------------------------------------
WAM_PERIOD = 3.0  # s per cycle
WAM_CYCLES = 3


def test_wam_rhythmic_cycles_have_no_seam_and_keep_the_limits(rig_factory):
    spec = load_robot("wam")
    limits = robot_limits(spec, ServerConfig())
    dt = 1.0 / spec.control_rate_hz
    rig = rig_factory("wam", [{"name": "shake", "model": model_path("wam_shake.safetensors")}])
    rig.wait_ready()
    n = 1001
    r = rig.call(Condition, "condition", Condition.Request(primitive="shake", preview_points=n))
    assert r.success, r.message
    mean = conv.preview_from_msg(r.preview).mean  # (n, 7); row n-1 is the point of x = 1 (= x = 0)
    res, fb, wall = execute(rig, Execute.Goal(handle=r.handle, duration=WAM_PERIOD, cycles=WAM_CYCLES))
    server = rig.procs["server"]
    assert res.success and res.code.value == ResultCode.SUCCESS, res.message + server.output_tail()
    assert res.cycles_completed == WAM_CYCLES
    seen = {f.cycle for f in fb}  # the last feedback may already count the finished cycle
    assert set(range(WAM_CYCLES)) <= seen <= set(range(WAM_CYCLES + 1)), seen

    stamps, q, qd = rig.cmd.arrays(spec.joint_names)
    assert q.shape[0] > WAM_CYCLES * WAM_PERIOD / dt, q.shape
    worst, late = limit_report(stamps, q, qd, limits, dt)

    # The phase clock runs N ticks per cycle, so the seams are exactly N ticks apart: find the offset
    # k0 (start of cycle 0) whose seams k0 + N, k0 + 2N best match the primitive's start state
    # (position mean[0], velocity mean'(0) / period).
    N = int(round(WAM_PERIOD / dt))
    h = 1.0 / (n - 1)
    v0 = (mean[1] - mean[-2]) / (2 * h) / WAM_PERIOD  # periodic central difference at x = 0
    score = np.abs(q - mean[0]).max(axis=1) + 0.1 * np.abs(qd - v0).max(axis=1)
    k0s = np.arange(0, q.shape[0] - WAM_CYCLES * N)
    total = sum(score[k0s + k * N] for k in range(1, WAM_CYCLES))
    k0 = int(k0s[np.argmin(total)])
    seams = [k0 + k * N for k in range(1, WAM_CYCLES)]
    # the stream does pass the start state there (Ruckig tracks with a lag of ~10 ms)
    assert max(np.abs(q[s] - mean[0]).max() for s in seams) < 0.05, [np.abs(q[s] - mean[0]).max() for s in seams]

    dq = np.abs(np.diff(q, axis=0)).max(axis=1)  # (T-1,) largest joint step of each tick
    dqd = np.abs(np.diff(qd, axis=0)).max(axis=1)
    w = 10  # ticks either side of a seam
    inside = np.ones(dq.shape[0], bool)
    inside[:k0] = False
    inside[k0 + WAM_CYCLES * N - 1:] = False
    for s in seams:
        inside[s - w:s + w] = False
    seam_dq = [dq[s - w:s + w].max() for s in seams]
    seam_dqd = [dqd[s - w:s + w].max() for s in seams]
    in_dq, in_dqd = dq[inside].max(), dqd[inside].max()
    stat_n = len(rig.states.raw)
    print(f"WAM shake, {WAM_CYCLES} cycles of {WAM_PERIOD} s: {wall:.1f} s wall, {q.shape[0]} commands "
          f"({late} late ticks), {stat_n} joint_states; seams at ticks {seams} (cycle 0 at {k0}); "
          f"position step at seams {np.round(seam_dq, 6)} rad vs largest inside {in_dq:.6f}; velocity step "
          f"{np.round(seam_dqd, 6)} rad/s vs {in_dqd:.6f}; limit ratios {({k: round(v, 6) for k, v in worst.items()})}; "
          f"max tracking error {res.max_tracking_error * 1e3:.1f} mrad")
    tol_q, tol_qd = 1e-6, 1e-6
    assert all(s <= in_dq + tol_q for s in seam_dq), (seam_dq, in_dq)
    assert all(s <= in_dqd + tol_qd for s in seam_dqd), (seam_dqd, in_dqd)
    assert in_dq > 1e-4  # the arm did move during the cycles (the comparison is not 0 <= 0)
    assert_within_limits(worst, q, limits)
    assert np.all(qd[-1] == 0.0)  # the finished motion ends at rest
    # the simulated arm followed the stream
    s_stamps, s_q, _ = rig.states.arrays(spec.joint_names)
    assert s_q.shape[0] > 100 and res.max_tracking_error < 0.3


# ------------------------------------------------------------------------------------------------
#: the reach's default_duration (config/primitives.yaml): well above the shortest the velocity limits allow
#: for these two contexts' reaches, which move at their demonstrations' speed
BLEND_DURATION = 6.0


def test_gen3_lite_blend_with_live_phase_rate_changes_keeps_the_limits(rig_factory):
    spec = load_robot("gen3_lite")
    limits = robot_limits(spec, ServerConfig())
    dt = 1.0 / spec.control_rate_hz
    rig = rig_factory("gen3_lite", [{"name": "reach", "model": model_path("gen3_lite_reach.safetensors")}])
    rig.wait_ready()
    handles, means = [], []
    for obj in ([0.35, -0.15, 0.05], [0.35, 0.15, 0.10]):
        r = rig.call(Condition, "condition", Condition.Request(
            primitive="reach", contexts=[Context(modality="object", values=obj)], preview_points=101))
        assert r.success, r.message
        handles.append(r.handle)
        means.append(conv.preview_from_msg(r.preview).mean)
    b = rig.call(Blend, "blend", Blend.Request(handle_a=handles[0], handle_b=handles[1], schedule_phases=[0.0, 1.0],
                                               schedule_weights=[1.0, 0.0], preview_points=101))
    assert b.success, b.message
    blended = conv.preview_from_msg(b.preview).mean
    # a real blend: starts at a's mean, ends at b's (the contexts give different motions)
    gap = np.abs(means[0][-1] - means[1][-1]).max()
    assert gap > 0.02, gap
    assert np.abs(blended[0] - means[0][0]).max() < 0.1 * gap + 1e-3
    assert np.abs(blended[-1] - means[1][-1]).max() < 0.1 * gap + 1e-3

    rate = 1.0 / BLEND_DURATION
    changes = []

    def during(fb, res_fut):
        for phase, new_rate in ((0.25, 0.5 * rate), (0.5, rate)):
            assert rig.spin_taking(lambda: (fb and fb[-1].phase > phase) or res_fut.done(), 30.0)
            assert not res_fut.done(), res_fut.result().result.message
            r = rig.call(SetPhaseRate, "set_phase_rate", SetPhaseRate.Request(phase_rate=new_rate))
            assert r.success, r.message
            changes.append((fb[-1].phase, new_rate))

    res, fb, wall = execute(rig, Execute.Goal(handle=b.handle, duration=BLEND_DURATION), during)
    server = rig.procs["server"]
    assert res.success and res.code.value == ResultCode.SUCCESS, res.message + server.output_tail()
    assert res.final_phase == 1.0
    rates = [f.phase_rate for f in fb if 0.02 < f.phase < 0.98]
    assert min(rates) == pytest.approx(0.5 * rate, abs=1e-9) and max(rates) == pytest.approx(rate, abs=1e-9)
    slow = [f.phase for f in fb if abs(f.phase_rate - 0.5 * rate) < 1e-12]
    assert slow and min(slow) > 0.2 and max(slow) < 0.6, (min(slow), max(slow))

    stamps, q, qd = rig.cmd.arrays(spec.joint_names)
    # slowed for a quarter of the stroke: ~ BLEND_DURATION * 1.25 s of commands
    assert q.shape[0] > 0.9 * BLEND_DURATION * 1.25 / dt, q.shape
    worst, late = limit_report(stamps, q, qd, limits, dt)
    dq = np.abs(np.diff(q, axis=0)) / dt / limits.max_velocity
    dqd = np.abs(np.diff(qd, axis=0)) / dt / limits.max_acceleration
    print(f"Gen3 lite blend, duration {BLEND_DURATION} s, rate x0.5 at phase {changes[0][0]:.3f} and x1 at "
          f"{changes[1][0]:.3f}: {wall:.1f} s wall, {q.shape[0]} commands ({late} late ticks); "
          f"limit ratios {({k: round(v, 6) for k, v in worst.items()})}; largest step {dq.max():.4f} v_max dt, "
          f"largest velocity step {dqd.max():.4f} a_max dt; max tracking error {res.max_tracking_error * 1e3:.1f} mrad")
    assert_within_limits(worst, q, limits)
    assert np.all(qd[-1] == 0.0)
    # the stream followed the blended mean to its end
    assert np.abs(q[-1] - blended[-1]).max() < 0.01
