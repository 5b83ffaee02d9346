"""PyBullet simulation: real PyBullet + real Pinocchio, no mocks."""
import time

import numpy as np
import pybullet as pb
import pytest

from deepprompt_ros.robots.kinematics import RobotKinematics
from deepprompt_ros.robots.spec import load_robot
from deepprompt_ros.sim.camera import CameraPose
from deepprompt_ros.sim.simulation import Simulation


@pytest.fixture
def gen3():
    sim = Simulation("gen3_lite")
    yield sim
    sim.close()


@pytest.mark.parametrize("name", ["gen3_lite", "wam"])
def test_pinocchio_fk_equals_pybullet_link_pose(name):
    with Simulation(name) as sim:
        kin = RobotKinematics(sim.spec)
        rng = np.random.default_rng(10)
        for _ in range(30):
            q = rng.uniform(sim.spec.lower, sim.spec.upper)
            sim.reset(q)
            pb_pose = sim.link_pose("ee")
            pin_pose = kin.forward_kinematics(q)
            np.testing.assert_allclose(pb_pose.position, pin_pose.position, atol=1e-6)
            np.testing.assert_allclose(pb_pose.rotation, pin_pose.rotation, atol=1e-5)


@pytest.mark.parametrize("name,duration", [("gen3_lite", 3.5), ("wam", 2.5)])
def test_position_control_reaches_target_without_exceeding_velocity_limits(name, duration):
    with Simulation(name) as sim:
        spec = sim.spec
        signs = np.where(np.arange(spec.n_joints) % 2 == 0, 1.0, -1.0)
        target = spec.clip_positions(spec.home + 0.7 * signs)
        sim.set_position_targets(target)
        qd_max = np.zeros(spec.n_joints)
        for _ in range(int(duration / sim.timestep)):
            sim.step()
            qd_max = np.maximum(qd_max, np.abs(sim.joint_state().velocity))
        q = sim.joint_state().position
        np.testing.assert_allclose(q, target, atol=1e-4)
        assert np.all(qd_max <= spec.velocity), (qd_max, spec.velocity)
        # the limit was reached, so the run really tested it
        assert np.any(qd_max >= 0.99 * spec.velocity)


def test_position_control_tracks_a_streamed_trajectory_with_feed_forward(gen3):
    q0 = gen3.spec.home.copy()
    # joint_1 follows q0 + A (1 - cos ωt): starts at rest, peak 0.24 rad/s and 0.37 rad/s²
    # (limits 0.5 and 1.0); one target per 1 kHz step, as a trajectory streamer sends them.
    amp, w = 0.15, 2 * np.pi * 0.25

    def reference(t):
        q, qd = q0.copy(), np.zeros(6)
        q[0] += amp * (1 - np.cos(w * t))
        qd[0] = amp * w * np.sin(w * t)
        return q, qd

    errors = []
    for k in range(2000):
        gen3.set_position_targets(*reference(k * gen3.timestep))
        gen3.step()
        if k >= 200:
            q_ref, _ = reference((k + 1) * gen3.timestep)
            errors.append(np.max(np.abs(gen3.joint_state().position - q_ref)))
    assert max(errors) < 1e-3
    assert abs(gen3.joint_state().position[0] - q0[0]) > 0.25  # it did move


def test_position_targets_are_validated(gen3):
    with pytest.raises(ValueError, match="joint 'joint_2' = 3.0000 is outside"):
        gen3.set_position_targets([0, 3.0, 0, 0, 0, 0])
    with pytest.raises(ValueError, match="6 joints: joint_1..joint_6"):
        gen3.set_position_targets([0, 0, 0])
    with pytest.raises(ValueError, match="velocity target .* joint 'joint_1' = 0.9000 exceeds"):
        gen3.set_position_targets(gen3.spec.home, [0.9, 0, 0, 0, 0, 0])
    gen3.set_kinesthetic(True)
    with pytest.raises(RuntimeError, match="kinesthetic"):
        gen3.set_position_targets(gen3.spec.home)


@pytest.mark.parametrize("name", ["gen3_lite", "wam"])
def test_kinesthetic_gravity_compensation_holds_the_arm_still(name):
    with Simulation(name, kinesthetic=True, kinesthetic_damping=0.0) as sim:
        q0 = sim.joint_state().position
        sim.step(1000)  # 1 s
        state = sim.joint_state()
        assert np.max(np.abs(state.position - q0)) < 2e-3
        # the actuators produce exactly Pinocchio's gravity torques, which are not small
        g = RobotKinematics(sim.spec).gravity_torques(state.position)
        np.testing.assert_allclose(state.effort, g, atol=1e-6)
        assert np.max(np.abs(g)) > 1.0
        # without the compensating torques (motors still off) the same arm falls
        sim.reset(q0)
        for _ in range(1000):
            pb.stepSimulation(physicsClientId=sim.client_id)
        assert np.max(np.abs(sim.joint_state().position - q0)) > 0.1


def test_kinesthetic_guiding_spring_moves_the_end_effector_to_the_target(gen3):
    gen3.set_kinesthetic(True)
    p0 = gen3.ee_position()
    target = p0 + np.array([0.0, 0.10, 0.10])
    gen3.guide_towards(target, stiffness=100.0)
    gen3.step(500)
    d_half = np.linalg.norm(target - gen3.ee_position())
    gen3.step(1000)
    d_end = np.linalg.norm(target - gen3.ee_position())
    assert np.linalg.norm(target - p0) == pytest.approx(0.1414, abs=1e-3)
    assert d_half < 0.07 and d_end < 0.01
    # released: the arm stays where it was guided to (gravity compensated, damped)
    gen3.release()
    p1 = gen3.ee_position()
    gen3.step(500)
    assert np.linalg.norm(gen3.ee_position() - p1) < 0.01
    # back to position control: it holds that pose
    gen3.set_kinesthetic(False)
    q1 = gen3.joint_state().position
    gen3.step(500)
    assert np.max(np.abs(gen3.joint_state().position - q1)) < 5e-3


def test_constant_guiding_force_pushes_the_end_effector_along_the_force(gen3):
    gen3.set_kinesthetic(True)
    p0 = gen3.ee_position()
    gen3.apply_guiding_force("ee", [0.0, 0.0, 5.0])
    gen3.step(300)
    dp = gen3.ee_position() - p0
    # a free arm moves along M⁻¹JᵀF, not exactly along F, but the force does positive work
    assert dp[2] > 0.05 and dp[2] > 0.5 * np.linalg.norm(dp)
    with pytest.raises(ValueError, match="no link 'gripper'"):
        gen3.apply_guiding_force("gripper", [0, 0, 1])


def test_camera_image_shape_and_objects_change_it(gen3):
    empty = gen3.camera_image(96, 64)
    assert empty.shape == (64, 96, 3) and empty.dtype == np.uint8
    ee = gen3.ee_position()
    gen3.spawn_object("cube", "box", (0.06, 0.06, 0.06), position=(ee[0], ee[1], 0.03),
                      rgba=(1.0, 0.0, 0.0, 1.0), mass=0.0)
    with_cube = gen3.camera_image(96, 64)
    changed = np.any(with_cube != empty, axis=2)
    assert changed.sum() > 30
    red = with_cube[changed].astype(int)
    assert np.mean(red[:, 0] > red[:, 1] + 50) > 0.8  # the new pixels are the red cube
    gen3.remove_object("cube")
    np.testing.assert_array_equal(gen3.camera_image(96, 64), empty)
    # another camera pose gives another image
    other = gen3.camera_image(96, 64, CameraPose(eye=(0.0, 1.2, 0.6), target=(0.2, 0.0, 0.2)))
    assert np.mean(other != empty) > 0.1


def test_objects_fall_on_the_ground_and_report_their_pose(gen3):
    gen3.spawn_object("ball", "sphere", (0.03,), position=(0.5, -0.3, 0.3), mass=0.05)
    gen3.spawn_object("can", "cylinder", (0.03, 0.1), position=(0.5, 0.3, 0.2), mass=0.2)
    gen3.step(800)
    ball = gen3.object_pose("ball")
    can = gen3.object_pose("can")
    assert ball.position[2] == pytest.approx(0.03, abs=2e-3)
    assert can.position[2] == pytest.approx(0.05, abs=2e-3)
    assert np.linalg.norm(can.orientation_xyzw) == pytest.approx(1.0)
    assert gen3.objects == ("ball", "can")
    gen3.set_object_pose("can", (0.0, 0.6, 0.05))
    np.testing.assert_allclose(gen3.object_pose("can").position, (0.0, 0.6, 0.05))
    with pytest.raises(ValueError, match="exists already"):
        gen3.spawn_object("ball", "sphere", (0.02,))
    with pytest.raises(ValueError, match="size of a box must be 3 positive numbers"):
        gen3.spawn_object("bad", "box", (0.1, 0.1))
    with pytest.raises(ValueError, match="unknown shape 'cone'"):
        gen3.spawn_object("bad", "cone", (0.1,))
    gen3.remove_object("ball")
    with pytest.raises(ValueError, match="no object named 'ball'; objects: \\['can'\\]"):
        gen3.object_pose("ball")


def test_two_simulations_in_one_process_are_independent():
    with Simulation("gen3_lite") as a, Simulation("gen3_lite") as b:
        assert a.client_id != b.client_id
        home = b.joint_state().position
        image_b = b.camera_image(64, 64)
        target = a.spec.clip_positions(a.spec.home + 0.3)
        a.set_position_targets(target)
        a.spawn_object("cube", "box", (0.1, 0.1, 0.1), position=(0.35, 0.0, 0.05))
        a.step(1500)
        assert np.max(np.abs(a.joint_state().position - home)) > 0.25
        np.testing.assert_array_equal(b.joint_state().position, home)
        assert b.objects == () and b.time == 0.0
        np.testing.assert_array_equal(b.camera_image(64, 64), image_b)
        b.step(10)
        assert b.time == pytest.approx(0.01) and a.time == pytest.approx(1.5)


def test_example_robot_data_panda_simulates_with_locked_fingers():
    with Simulation("panda", kinesthetic=True, kinesthetic_damping=0.0) as sim:
        assert sim.spec.n_joints == 7
        q0 = sim.joint_state().position
        sim.step(500)
        assert np.max(np.abs(sim.joint_state().position - q0)) < 2e-3
        kin = RobotKinematics(sim.spec)
        np.testing.assert_allclose(sim.link_pose("ee").position,
                                   kin.forward_kinematics(sim.joint_state().position).position, atol=1e-6)


def test_reset_places_the_arm_at_rest():
    with Simulation("wam") as sim:
        sim.set_position_targets(sim.spec.clip_positions(sim.spec.home + 0.5))
        sim.step(200)
        q = sim.spec.clip_positions(sim.spec.home - 0.2)
        sim.reset(q)
        state = sim.joint_state()
        np.testing.assert_allclose(state.position, q, atol=1e-12)
        np.testing.assert_array_equal(state.velocity, np.zeros(7))
        np.testing.assert_array_equal(sim.position_targets, q)
        with pytest.raises(ValueError, match="reset configuration"):
            sim.reset(np.full(7, 5.0))


def test_real_time_factor_paces_simulated_time():
    with Simulation("gen3_lite", real_time_factor=1.0) as sim:
        sim.step(1)  # first step sets the wall-clock reference
        t0 = time.perf_counter()
        sim.step(100)
        assert time.perf_counter() - t0 >= 0.095  # 0.1 s of simulated time at real time
        sim.real_time_factor = 4.0
        sim.step(1)
        t0 = time.perf_counter()
        sim.step(100)
        assert time.perf_counter() - t0 >= 0.0235
        with pytest.raises(ValueError, match="real_time_factor must be >= 0"):
            sim.real_time_factor = -1.0
    with pytest.raises(RuntimeError, match="closed"):
        sim.step()


def test_unknown_robot_in_simulation_gives_the_list():
    with pytest.raises(ValueError, match="unknown robot 'kuka'.*gen3_lite, wam"):
        Simulation("kuka")
    with pytest.raises(ValueError, match="timestep"):
        Simulation(load_robot("gen3_lite"), timestep=0.0)
