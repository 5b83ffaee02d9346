"""Robot descriptions: packaged URDFs, specs, Pinocchio kinematics/dynamics (no mocks)."""
import math
import re

import numpy as np
import pinocchio as pin
import pybullet as pb
import pytest

from deepprompt_ros.robots.geometry import log3, quat_xyzw, rodrigues, rot_y, rot_z, rotation_from_quat_xyzw, skew
from deepprompt_ros.robots.ik import solve_ik
from deepprompt_ros.robots.kinematics import RobotKinematics
from deepprompt_ros.robots.spec import (
    DEFAULT_ACCELERATION_PER_VELOCITY,
    DEFAULT_JERK_PER_ACCELERATION,
    GRAVITY,
    available_robots,
    load_robot,
    urdf_path,
)

# Published numbers the packaged URDFs must reproduce (sources cited in the URDF files).
GEN3_LITE = dict(
    joints=[f"joint_{i}" for i in range(1, 7)],
    upper=[2.69, 2.69, 2.69, 2.59, 2.57, 2.59],           # Kinova kortex_description
    effort=[10, 14, 10, 7, 7, 7],                         # Kinova kortex_description
    velocity=[0.5] * 6,                                   # Kinova ros2 joint_limits.yaml
    acceleration=[1.0, 0.5, 0.4, 1.0, 10.0, 10.0],        # Kinova ros2 joint_limits.yaml
)
WAM = dict(
    joints=[f"wam_j{i}" for i in range(1, 8)],
    lower=[-2.6, -2.0, -2.8, -0.9, -4.76, -1.6, -3.0],    # Barrett WAM manual, Table 6
    upper=[2.6, 2.0, 2.8, 3.1, 1.24, 1.6, 3.0],
    velocity=[1.5708, 1.0472, 2.0944, 2.0944, 4.1888, 4.1888, 1.0472],
    effort=[77.3, 160.6, 95.6, 29.4, 11.6, 11.6, 2.7],
)
# Barrett WAM manual Table 5 (a, alpha, d), standard DH T = Rz(θ) Tz(d) Tx(a) Rx(α).
WAM_DH = [(0, -math.pi / 2, 0), (0, math.pi / 2, 0), (0.045, -math.pi / 2, 0.55),
          (-0.045, math.pi / 2, 0), (0, -math.pi / 2, 0.3), (0, math.pi / 2, 0), (0, 0, 0.06)]
# Kinova kortex_description joint origins (xyz, rpy) and the gripper's tool_frame.
GEN3_LITE_ORIGINS = [((0, 0, 0.12825), (0, 0, 0)), ((0, -0.03, 0.115), (math.pi / 2, 0, 0)),
                     ((0, 0.28, 0), (-math.pi, 0, 0)), ((0, -0.14, 0.02), (math.pi / 2, 0, 0)),
                     ((0.0285, 0, 0.105), (0, math.pi / 2, 0)), ((-0.105, 0, 0.0285), (0, -math.pi / 2, 0))]
GEN3_LITE_TOOL = ((0, 0, 0.130), (0, 0, math.pi / 2))


def _dh(a, alpha, d, theta):
    ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
    return np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st],
                     [0, sa, ca, d], [0, 0, 0, 1.0]])


def _origin(xyz, rpy):
    T = np.eye(4)
    T[:3, :3] = pin.rpy.rpyToMatrix(*rpy)
    T[:3, 3] = xyz
    return T


def _rz(theta):
    T = np.eye(4)
    T[:2, :2] = [[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]]
    return T


@pytest.mark.parametrize("name,ref", [("gen3_lite", GEN3_LITE), ("wam", WAM)])
def test_packaged_urdf_loads_in_pinocchio_with_published_limits(name, ref):
    model = pin.buildModelFromUrdf(str(urdf_path(name)))
    n = len(ref["joints"])
    assert model.nq == model.nv == n
    assert [model.names[i] for i in range(1, model.njoints)] == ref["joints"]
    lower = ref.get("lower", [-u for u in ref["upper"]])
    np.testing.assert_array_equal(model.lowerPositionLimit, lower)
    np.testing.assert_array_equal(model.upperPositionLimit, ref["upper"])
    np.testing.assert_array_equal(model.velocityLimit, ref["velocity"])
    np.testing.assert_array_equal(model.effortLimit, ref["effort"])
    spec = load_robot(name)
    assert list(spec.joint_names) == ref["joints"]
    np.testing.assert_array_equal(spec.lower, lower)
    np.testing.assert_array_equal(spec.velocity, ref["velocity"])
    np.testing.assert_array_equal(spec.effort, ref["effort"])
    assert model.existFrame(spec.ee_frame)


@pytest.mark.parametrize("name,ref", [("gen3_lite", GEN3_LITE), ("wam", WAM)])
def test_packaged_urdf_loads_in_pybullet_with_same_joints_and_limits(name, ref):
    spec = load_robot(name)
    client = pb.connect(pb.DIRECT)
    try:
        body = pb.loadURDF(str(urdf_path(name)), useFixedBase=True, physicsClientId=client)
        infos = [pb.getJointInfo(body, j, physicsClientId=client)
                 for j in range(pb.getNumJoints(body, physicsClientId=client))]
        revolute = [i for i in infos if i[2] == pb.JOINT_REVOLUTE]
        assert [i[1].decode() for i in revolute] == ref["joints"]
        np.testing.assert_allclose([i[8] for i in revolute], spec.lower)
        np.testing.assert_allclose([i[9] for i in revolute], spec.upper)
        np.testing.assert_allclose([i[10] for i in revolute], spec.effort)
        np.testing.assert_allclose([i[11] for i in revolute], spec.velocity)
        assert spec.ee_frame in [i[12].decode() for i in infos]
        # every link has its URDF mass (no link silently given PyBullet's default 1 kg)
        model = pin.buildModelFromUrdf(str(urdf_path(name)))
        total_pin = sum(model.inertias[i].mass for i in range(1, model.njoints))
        total_pb = sum(pb.getDynamicsInfo(body, j, physicsClientId=client)[0] for j in range(len(infos)))
        assert total_pb == pytest.approx(total_pin, rel=1e-9)
    finally:
        pb.disconnect(physicsClientId=client)


def test_gen3_lite_spec_has_kinova_acceleration_limits_and_control_rate():
    spec = load_robot("gen3_lite")
    np.testing.assert_array_equal(spec.acceleration, GEN3_LITE["acceleration"])
    np.testing.assert_allclose(spec.jerk, DEFAULT_JERK_PER_ACCELERATION * spec.acceleration)
    assert spec.control_rate_hz == 1000.0
    assert spec.ee_frame == "tool_frame"
    assert np.all(spec.home > spec.lower + 1.0) and np.all(spec.home < spec.upper - 1.0)


def test_wam_forward_kinematics_equals_barrett_dh_table():
    kin = RobotKinematics(load_robot("wam"))
    rng = np.random.default_rng(0)
    for _ in range(25):
        q = rng.uniform(kin.spec.lower, kin.spec.upper)
        T = _origin((0, 0, 0.346), (0, 0, 0))  # J1/J2 intersection above the mount
        for (a, alpha, d), theta in zip(WAM_DH, q):
            T = T @ _dh(a, alpha, d, theta)
        pose = kin.forward_kinematics(q)
        np.testing.assert_allclose(pose.position, T[:3, 3], atol=1e-9)
        np.testing.assert_allclose(pose.rotation, T[:3, :3], atol=1e-9)
    # all zero: arm straight up, tool plate at 0.346 + 0.55 + 0.3 + 0.06 m
    np.testing.assert_allclose(kin.forward_kinematics(np.zeros(7)).position, [0, 0, 1.256], atol=1e-12)


def test_gen3_lite_forward_kinematics_equals_kortex_joint_origins():
    kin = RobotKinematics(load_robot("gen3_lite"))
    rng = np.random.default_rng(1)
    for _ in range(25):
        q = rng.uniform(kin.spec.lower, kin.spec.upper)
        T = np.eye(4)
        for (xyz, rpy), theta in zip(GEN3_LITE_ORIGINS, q):
            T = T @ _origin(xyz, rpy) @ _rz(theta)
        T = T @ _origin(*GEN3_LITE_TOOL)
        pose = kin.forward_kinematics(q)
        np.testing.assert_allclose(pose.position, T[:3, 3], atol=1e-9)
        np.testing.assert_allclose(pose.rotation, T[:3, :3], atol=1e-9)


@pytest.mark.parametrize("name", ["gen3_lite", "wam"])
def test_gravity_torques_are_the_gradient_of_potential_energy(name):
    kin = RobotKinematics(load_robot(name))
    rng = np.random.default_rng(2)
    q = rng.uniform(kin.spec.lower, kin.spec.upper)
    g = kin.gravity_torques(q)

    def potential(qq):
        return pin.computePotentialEnergy(kin.model, kin.data, kin.configuration(qq))

    eps = 1e-6
    grad = [(potential(q + eps * e) - potential(q - eps * e)) / (2 * eps) for e in np.eye(len(q))]
    np.testing.assert_allclose(g, grad, atol=1e-6)
    assert abs(g[0]) < 1e-9  # joint 1 axis is vertical: gravity never loads it
    assert np.max(np.abs(g)) > 1.0  # and the arm is heavy enough for the check to mean something
    assert kin.model.gravity.linear[2] == -GRAVITY


def test_jacobian_matches_finite_differences_of_forward_kinematics():
    kin = RobotKinematics(load_robot("wam"))
    q = np.random.default_rng(3).uniform(kin.spec.lower, kin.spec.upper)
    J = kin.jacobian(q)
    assert J.shape == (6, 7)
    eps = 1e-7
    for j in range(7):
        dq = np.zeros(7)
        dq[j] = eps
        dp = (kin.forward_kinematics(q + dq).position - kin.forward_kinematics(q - dq).position) / (2 * eps)
        np.testing.assert_allclose(J[:3, j], dp, atol=1e-6)


def test_panda_from_example_robot_data_uses_urdf_limits_and_locks_the_fingers():
    spec = load_robot("panda")
    assert spec.joints_text() == "panda_joint1..panda_joint7"
    assert [j for j, _ in spec.locked_joints] == ["panda_finger_joint1", "panda_finger_joint2"]
    model = pin.buildModelFromUrdf(str(spec.urdf_path))
    np.testing.assert_array_equal(spec.velocity, model.velocityLimit[:7])
    np.testing.assert_array_equal(spec.lower, model.lowerPositionLimit[:7])
    np.testing.assert_array_equal(spec.acceleration, [15, 7.5, 10, 12.5, 15, 20, 20])  # libfranka
    kin = RobotKinematics(spec)
    assert kin.model.nq == kin.model.nv == 7
    pose = kin.forward_kinematics(spec.home)
    assert spec.ee_frame == "panda_hand_tcp" and 0.2 < pose.position[2] < 1.0


def test_example_robot_data_arm_without_published_dynamics_gets_documented_defaults():
    spec = load_robot("ur5")
    np.testing.assert_allclose(spec.acceleration, DEFAULT_ACCELERATION_PER_VELOCITY * spec.velocity)
    np.testing.assert_allclose(spec.jerk, DEFAULT_JERK_PER_ACCELERATION * spec.acceleration)
    assert spec.ee_frame == "tool0" and spec.n_joints == 6


def test_continuous_joints_take_plain_angles():
    spec = load_robot("kinova")  # Kinova JACO2 j2s6s200: joints 1, 4, 6 are continuous
    np.testing.assert_array_equal(spec.continuous, [True, False, False, True, False, True])
    assert np.all(np.isinf(spec.lower[spec.continuous]))
    kin = RobotKinematics(spec)
    assert kin.model.nq == 9 and kin.model.nv == 6
    q = spec.home.copy()
    p0 = kin.forward_kinematics(q).position
    q[0] += 2 * math.pi
    np.testing.assert_allclose(kin.forward_kinematics(q).position, p0, atol=1e-12)
    q[0] += 0.3
    assert np.linalg.norm(kin.forward_kinematics(q).position - p0) > 1e-3
    np.testing.assert_allclose(kin.joint_values(kin.configuration(spec.home)), spec.home, atol=1e-12)
    spec.validate_positions(q + 100.0 * spec.continuous)  # no limit on continuous joints


def test_unknown_robot_error_lists_available_names():
    with pytest.raises(ValueError) as err:
        load_robot("gen4_heavy")
    msg = str(err.value)
    assert "gen4_heavy" in msg and "gen3_lite" in msg and "wam" in msg and "panda" in msg
    with pytest.raises(ValueError, match="gen3_lite"):
        urdf_path("nope")
    with pytest.raises(ValueError, match="floating base"):
        load_robot("anymal")
    assert available_robots()[:2] == ("gen3_lite", "wam") and "ur5" in available_robots()


def test_limit_checks_name_the_joint_and_the_expectation():
    spec = load_robot("gen3_lite")
    with pytest.raises(ValueError, match=r"has 5 joint values .*'gen3_lite' has 6 joints: joint_1..joint_6"):
        spec.validate_positions(np.zeros(5), label="via-point 3")
    with pytest.raises(ValueError, match=r"joint 'joint_3' = 2\.8000 is outside \[-2\.6900, 2\.6900\]"):
        spec.validate_positions([0, 0, 2.8, 0, 0, 0])
    with pytest.raises(ValueError, match="NaN or inf for joint.*joint_2"):
        spec.validate_positions([0, np.nan, 0, 0, 0, 0])
    with pytest.raises(ValueError, match=r"joint 'joint_4' = -0\.6000 exceeds ±0\.5000"):
        spec.validate_velocities([0, 0, 0, -0.6, 0, 0])
    # a whole trajectory, shape (T, n), is checked at once and the bad sample is located
    traj = np.zeros((4, 6))
    traj[2, 5] = -3.0
    with pytest.raises(ValueError, match=r"\[2\] joint 'joint_6'"):
        spec.validate_positions(traj)
    kin = RobotKinematics(spec)
    assert kin.within_limits(spec.home) and not kin.within_limits([0, 0, 2.8, 0, 0, 0])
    with pytest.raises(ValueError, match="joint_5"):
        kin.check_joint_limits(spec.home, qd=[0, 0, 0, 0, 0.7, 0])


def test_spec_is_immutable_and_serialisable():
    spec = load_robot("wam")
    with pytest.raises(ValueError):
        spec.lower[0] = 0.0  # read-only array
    with pytest.raises(AttributeError):
        spec.name = "other"
    d = spec.to_dict()
    assert d["joint_names"] == WAM["joints"] and d["velocity"] == WAM["velocity"]
    assert d["urdf_path"].endswith("wam.urdf")


@pytest.mark.parametrize("name,tag", [("gen3_lite", "[K1]"), ("wam", "[B1]")])
def test_every_joint_and_inertial_in_packaged_urdfs_cites_a_source(name, tag):
    text = urdf_path(name).read_text()
    assert tag in text
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if re.search(r"<joint name=|<inertial>", line):
            before = "\n".join(lines[max(0, i - 4):i])
            assert re.search(r"\[[KB]\d\]|Explicit negligible inertia", before), (name, i + 1, line)


def test_geometry_conversions_agree_with_pinocchio_and_pybullet():
    rng = np.random.default_rng(4)
    for _ in range(200):
        q = rng.standard_normal(4)
        # quaternion -> matrix: PyBullet's own conversion, to the last bit (any norm)
        R = rotation_from_quat_xyzw(q)
        assert R.tobytes() == np.array(pb.getMatrixFromQuaternion(q), dtype=np.float64).reshape(3, 3).tobytes()
        # matrix -> quaternion: the same rotation as Pinocchio's, up to the sign of q
        quat = quat_xyzw(R)
        ref = np.array(pin.Quaternion(R).coeffs())
        assert np.isclose(np.linalg.norm(quat), 1.0)
        assert min(np.abs(quat - ref).max(), np.abs(quat + ref).max()) < 1e-12
        # log3 / rodrigues: inverse of each other
        w = log3(R)
        angle = np.linalg.norm(w)
        assert np.allclose(rodrigues(w, angle), R, atol=1e-12)
        assert np.allclose(pin.log3(R), w, atol=1e-9)
    assert np.allclose(rot_z(0.3), pin.rpy.rpyToMatrix(0.0, 0.0, 0.3))
    assert np.allclose(rot_y(-0.7), pin.rpy.rpyToMatrix(0.0, -0.7, 0.0))
    v, u = rng.standard_normal(3), rng.standard_normal(3)
    assert np.allclose(skew(v) @ u, np.cross(v, u))
    # FramePose.quaternion_xyzw is the same conversion
    pose = RobotKinematics(load_robot("wam")).forward_kinematics(load_robot("wam").home)
    assert np.array_equal(pose.quaternion_xyzw, quat_xyzw(pose.rotation))


@pytest.mark.parametrize("robot", ["wam", "gen3_lite"])
def test_solve_ik_reaches_poses_inside_the_shrunk_limits(robot):
    spec = load_robot(robot)
    kin = RobotKinematics(spec)
    rng = np.random.default_rng(1)
    for _ in range(5):
        q_goal = spec.clip_positions(spec.home + rng.uniform(-0.3, 0.3, spec.n_joints))
        pose = kin.forward_kinematics(q_goal)
        res = solve_ik(kin, pose.position, spec.home, rotation=pose.rotation)
        assert res.position_error < 1e-4 and res.angle_error < 1e-3
        assert np.all(res.q >= spec.lower + 0.05 - 1e-12) and np.all(res.q <= spec.upper - 0.05 + 1e-12)
        reached = kin.forward_kinematics(res.q)
        assert np.linalg.norm(reached.position - pose.position) == pytest.approx(res.position_error)
        # position only, without null-space term or step cap: the error reported is the one of the
        # configuration before the last step when the iterations run out
        few = solve_ik(kin, pose.position, spec.home, iterations=1, rest_gain=0.0, max_step=None,
                       measure_after_last_step=False)
        start = kin.forward_kinematics(np.clip(spec.home, spec.lower + 0.05, spec.upper - 0.05)).position
        assert few.position_error == pytest.approx(np.linalg.norm(pose.position - start))
