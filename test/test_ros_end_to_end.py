"""End to end over real DDS (LOCALHOST discovery, random domain), every node a real process:

sim_bridge (PyBullet Gen3 lite) + demo_recorder: demonstrations guided kinesthetically (a spring
pulls the end effector through waypoints to varied targets), recorded to .npz -> a DeepProMP
trained here from those files with the package's default model selection -> primitive_server
serving it: conditioned on one via-point (with refinement), executed on the simulated arm, and the
arm's measured joint_states pass through the via-point; the server runs once with its fast path
and once with plain rclpy (``fast_path: false``).
"""
import time

import numpy as np
import pytest
import yaml
from deepprompt_msgs.action import Execute
from deepprompt_msgs.msg import ResultCode
from deepprompt_msgs.srv import Condition, StartRecording, StopRecording
from geometry_msgs.msg import PointStamped
from rclpy.action import ActionClient
from sensor_msgs.msg import JointState
from std_srvs.srv import SetBool, Trigger

from deepprompt_ros.data.demo_dataset import load_dataset
from deepprompt_ros.robots.kinematics import RobotKinematics
from deepprompt_ros.robots.spec import load_robot
from deepprompt_ros.training.config import TrainConfig
from deepprompt_ros.training.loop import train
from deepprompt_ros.ros import conversions as conv
from deepprompt_ros.ros.testing import JointStateTap, NodeProcess, RosTestClient, isolated_ros_env

SPEC = load_robot("gen3_lite")
KIN = RobotKinematics(SPEC)
SRV = "/primitive_server"

#: Simulated seconds per wall second. The demonstrations are stamped in simulated time, so a faster
#: simulation would only shorten the test, but it multiplies the joint_states per wall second (1000
#: per simulated second) that the recorder, a Python process, has to keep up with: behind, it loses
#: messages and answers stop_recording late. 0 (as fast as possible) takes a whole core.
REAL_TIME_FACTOR = 1.0
N_DEMOS = 6
#: Simulated times (s after start_recording) at which the guide moves to the waypoint, then to the
#: target, and at which the recording is stopped.
T_WAYPOINT, T_TARGET, T_END = 0.1, 0.8, 2.0
#: Offset (rad) added to the primitive's mean at the via phase on two joints.
VIA_PHASE, VIA_OFFSET = 0.5, 0.03
#: Seconds for phase 0 -> 1. The guided demonstrations last T_END simulated s and move joint_5 by up
#: to ~4.5 rad per unit of phase; at its 0.5 rad/s limit a primitive that reproduces them needs ~9 s.
EXEC_DURATION = 10.0
#: How close (max over joints, rad) the measured arm must pass to the via-point. The server streams
#: the refined mean (which meets the via-point within 1e-6 rad) through Ruckig at 1 kHz, which tracks
#: it within a few 1e-4 rad when the mean keeps the limits; PyBullet's position loop (gain 20/s plus
#: velocity feed-forward) follows the stream with a lag along the path (the server logs it as
#: commanded-minus-measured; this is why the closest approach is measured, not the sample at the via
#: time) and little across it; joint_states every 1 ms of simulated time add < 0.5 mrad at 0.5 rad/s.
VIA_TOLERANCE = 0.01


@pytest.fixture(scope="module")
def tmp(tmp_path_factory):
    return tmp_path_factory.mktemp("end_to_end")


@pytest.fixture(scope="module")
def env(tmp):
    return isolated_ros_env(tmp / "log")


@pytest.fixture(scope="module")
def sim(env):
    with NodeProcess.start_module("deepprompt_ros.ros.sim_bridge", env, params={
            "robot": "gen3_lite", "real_time_factor": REAL_TIME_FACTOR, "camera.enabled": False,
            "publish_clock": False}) as proc:
        yield proc


@pytest.fixture(scope="module")
def client(env, sim):
    with RosTestClient(env) as c:
        c.joint_states = c.subscribe("joint_states", JointState, 1)  # the current state only
        assert c.wait_for_messages(c.joint_states, 1, timeout=30.0), sim.output_tail()
        yield c



def _sim_time(client) -> float:
    return conv.stamp_to_ns(client.latest(client.joint_states).header.stamp) * 1e-9


def _wait_sim_until(client, t: float, timeout: float = 20.0) -> None:
    assert client.wait_for(lambda: client.drain() or
                           conv.stamp_to_ns(client.joint_states.last().header.stamp) * 1e-9 >= t, timeout)


def _guide(client, xyz) -> None:
    msg = PointStamped()
    msg.header.frame_id = "world"
    msg.point.x, msg.point.y, msg.point.z = (float(v) for v in xyz)
    client.publish("guide_target", msg)


@pytest.fixture(scope="module")
def demos_dir(env, tmp, sim, client):
    """Record N_DEMOS kinesthetic demonstrations with demo_recorder; returns their folder and the
    guide targets (N_DEMOS, 3)."""
    out = tmp / "demos"
    with NodeProcess.start_module("deepprompt_ros.ros.demo_recorder", env, params={
            "output_directory": str(out), "record_bag": False}, name="demo_recorder") as rec:
        assert client.wait_for_recorder("", 60.0), rec.output_tail()
        assert client.call(SetBool, "set_kinesthetic", SetBool.Request(data=True)).success
        ee_home = KIN.forward_kinematics(SPEC.home).position
        rng = np.random.default_rng(0)
        targets = []
        t_wall = time.perf_counter()
        for i in range(N_DEMOS):
            assert client.call(Trigger, "reset").success  # home, at rest, guide cleared
            target = ee_home + np.array([rng.uniform(-0.08, 0.08), rng.uniform(-0.15, 0.15),
                                         rng.uniform(-0.12, -0.04)])
            targets.append(target)
            waypoint = 0.5 * (ee_home + target) + np.array([0.0, 0.0, rng.uniform(0.03, 0.06)])
            deadline = time.monotonic() + 30.0  # the recorder needs a recent joint state to start
            while not (res := client.call(StartRecording, "start_recording",
                                          StartRecording.Request(demo_name=f"guided_{i}"))).success:
                assert time.monotonic() < deadline, res.message + rec.output_tail()
                client.spin_for(0.2)
            t0 = _sim_time(client)
            _wait_sim_until(client, t0 + T_WAYPOINT)
            _guide(client, waypoint)
            _wait_sim_until(client, t0 + T_TARGET)
            _guide(client, target)
            _wait_sim_until(client, t0 + T_END)
            res = client.call(StopRecording, "stop_recording", StopRecording.Request())
            assert res.success, res.message + rec.output_tail()
            _guide(client, [float("nan")] * 3)
        print(f"recorded {N_DEMOS} demonstrations of {T_END} simulated s in "
              f"{time.perf_counter() - t_wall:.1f} s wall")
    assert client.call(SetBool, "set_kinesthetic", SetBool.Request(data=False)).success  # position control
    assert client.call(Trigger, "reset").success
    return out, np.array(targets)


@pytest.fixture(scope="module")
def dataset(demos_dir):
    return load_dataset(demos_dir[0])


@pytest.fixture(scope="module")
def model(dataset, tmp):
    """A DeepProMP trained in this process from the recorded files, with the package's default model
    selection (what ``train --data DIR`` does) and few updates."""
    path = tmp / "model.safetensors"
    t0 = time.perf_counter()
    train(dataset, TrainConfig(steps=300, batch_size=16, n_points=50, max_via_points=5, val_every=300, threads=1,
                               seed=0),
          out_path=path, log=lambda m: None)
    print(f"trained on {len(dataset)} demonstrations in {time.perf_counter() - t0:.1f} s")
    assert path.is_file()
    return path


def test_recorded_demonstrations_are_valid_and_moved(demos_dir, dataset):
    assert len(dataset) == N_DEMOS
    assert [d.name for d in dataset.demos] == [f"guided_{i}" for i in range(N_DEMOS)]
    ends, lost = [], 0
    for d in dataset.demos:
        assert d.joint_names == SPEC.joint_names and d.q.shape == (len(d.t), 6)
        dt = np.diff(d.t)
        assert d.t[0] == 0.0 and np.all(dt > 0)
        assert np.median(dt) == pytest.approx(1e-3, abs=1e-6)  # the sim's 1 kHz stamps
        lost += int(np.round(dt / 1e-3).sum()) - len(dt)
        assert T_END - 0.01 < d.t[-1] < T_END + 1.0, d.t[-1]  # stopped after T_END simulated s
        np.testing.assert_allclose(d.q[0], SPEC.home, atol=2e-3)  # started at home (reset)
        joint_range = np.ptp(d.q, axis=0)
        assert joint_range.max() > 0.15, f"{d.name}: joints moved only {joint_range.round(3)} rad"
        ends.append(KIN.forward_kinematics(d.q[-1]).position)
    ends = np.array(ends)
    miss = np.linalg.norm(ends - demos_dir[1], axis=1)
    spread = np.linalg.norm(ends - ends.mean(0), axis=1).mean()
    n = sum(len(d.t) for d in dataset.demos)
    print(f"demonstrations: durations {[float(round(d.t[-1], 3)) for d in dataset.demos]} s, {n} samples, "
          f"{lost} lost; end effector ends {miss.max() * 1e3:.2f} mm or less from its guide target; "
          f"end points {spread * 100:.1f} cm from their centre on average")
    assert lost <= 0.01 * n
    assert np.all(miss < 0.01)  # the guiding spring took the arm to each target
    assert spread > 0.04  # varied targets: a distribution to learn, not one motion


def _condition(client, **kw):
    r = client.call(Condition, f"{SRV}/condition", Condition.Request(primitive="guided", **kw), timeout=20.0)
    assert r.success, r.message
    return r


@pytest.mark.parametrize("fast_path", [True, False], ids=["fast_path", "plain_rclpy"])
def test_learned_primitive_passes_through_a_via_point_on_the_arm(env, tmp, sim, client, model, fast_path):
    """The same condition -> execute with the server's fast path and with plain rclpy (``fast_path``)."""
    prims = tmp / "primitives.yaml"
    prims.write_text(yaml.safe_dump({"primitives": [{"name": "guided", "model": str(model)}]}))
    assert client.call(Trigger, "reset").success  # every run starts from home, at rest
    t_start = time.perf_counter()
    with NodeProcess.start_module("deepprompt_ros.ros.primitive_server", env, params={
            "robot": "gen3_lite", "primitives_file": str(prims), "fast_path": fast_path,
            "stale_timeout": 1.0}) as server:  # above the default 0.2 s: pauses of the Python sim are not under test
        ac = ActionClient(client.node, Execute, f"{SRV}/execute")
        tap = JointStateTap(client)
        try:
            assert client.wait_for(ac.server_is_ready, 60.0), server.output_tail()
            assert client.wait_for(lambda: "receiving joint_states" in server.output(), 30.0), server.output_tail()
            t_ready = time.perf_counter() - t_start

            n = 1001
            prior = conv.preview_from_msg(_condition(client, preview_points=n).preview)
            k = int(round(VIA_PHASE * (n - 1)))
            assert prior.phases[k] == pytest.approx(VIA_PHASE)
            # The two joints the demonstrations varied most at the via phase: an offset there is within
            # the learned distribution (a joint the demonstrations never moved, like joint_6 under the
            # guiding spring, cannot be moved by conditioning).
            joints = np.sort(np.argsort(prior.std[k])[-2:])
            via = prior.mean[k].copy()
            via[joints] += np.array([VIA_OFFSET, -VIA_OFFSET])
            SPEC.validate_positions(via)
            prior_gap = np.abs(prior.mean - via).max(axis=1).min()  # closest approach of the prior mean

            # The server's default conditioning of the selected model (exact Gaussian conditioning of
            # its linear block) meets the via-point already; the refinement then has nothing to do.
            r = _condition(client, via_points=conv.via_points_to_msgs([VIA_PHASE], [via]), refine=True,
                           preview_points=n)
            assert r.reachable and r.refine_max_error <= 1e-6, (r.reachable, r.refine_max_error, r.message)
            mean = conv.preview_from_msg(r.preview).mean
            assert np.abs(mean[k] - via).max() <= 1e-6
            refine_iterations = r.refine_iterations

            client.unsubscribe(client.joint_states)  # the tap records them; less work for this process
            tap.take()
            tap.raw.clear()
            feedback = []
            t0 = time.perf_counter()
            fut = ac.send_goal_async(Execute.Goal(handle=r.handle, duration=EXEC_DURATION),
                                     feedback_callback=lambda m: feedback.append(m.feedback))
            assert client.wait_for(lambda: tap.take() or fut.done(), 10.0) and fut.result().accepted
            res_fut = fut.result().get_result_async()
            assert client.wait_for(lambda: tap.take() or res_fut.done(), 60.0), server.output_tail()
            t_exec = time.perf_counter() - t0
            client.wait_for(lambda: tap.take() or False, 0.3)  # the arm settles on the last command
            tap.take()
            res = res_fut.result().result
            assert res.success and res.code.value == ResultCode.SUCCESS, res.message + server.output_tail()
            stats = [line for line in server.output().splitlines() if "control loop so far" in line]
        finally:
            tap.close()
            ac.destroy()

    stamps, q, _ = tap.arrays(SPEC.joint_names)
    steps = np.diff(stamps) / 1e6  # ms of simulated time between consecutive messages (1 = none lost)
    phases = [f.phase for f in feedback]
    assert len(phases) > 20 and np.all(np.diff(phases) >= -1e-12) and phases[-1] > 0.9, phases
    assert q.shape[0] > 2000 and np.all(steps > 0), (q.shape, steps.min())
    # Each measured configuration's nearest point on the refined mean path gives its phase; the
    # closest approach to the via-point is taken among those around the via phase.
    near = np.abs(q[:, None, :] - mean[None, ::10, :]).max(axis=2).argmin(axis=1) * 10 / (n - 1)
    window = (near >= VIA_PHASE - 0.25) & (near <= VIA_PHASE + 0.25)
    err = np.where(window, np.abs(q - via).max(axis=1), np.inf)
    i = int(np.argmin(err))
    sim_s = (stamps[-1] - stamps[0]) * 1e-9
    print(f"via-point (phase {VIA_PHASE}, mean + [{VIA_OFFSET}, -{VIA_OFFSET}] rad on "
          f"{[SPEC.joint_names[j] for j in joints]}): closest approach of the measured arm {err[i] * 1e3:.2f} mrad "
          f"(max over joints; tolerance {VIA_TOLERANCE * 1e3:.0f} mrad) at mean-path phase {near[i]:.2f}; "
          f"the prior mean passes {prior_gap * 1e3:.1f} mrad away; refinement {refine_iterations} iterations")
    print(f"server ready after {t_ready:.1f} s; execution {t_exec:.1f} s wall for duration {EXEC_DURATION} s; "
          f"{len(q)} joint states over {sim_s:.2f} simulated s ({int(np.sum(steps - 1))} lost); "
          f"reported max tracking error {res.max_tracking_error * 1e3:.1f} mrad")
    print(stats[-1] if stats else "no loop statistics in the server log")
    assert prior_gap > 2 * VIA_TOLERANCE  # the via-point is off the unconditioned motion
    assert err[i] <= VIA_TOLERANCE
    assert np.abs(q[-1] - mean[-1]).max() < VIA_TOLERANCE  # and the arm ends where the refined mean ends
