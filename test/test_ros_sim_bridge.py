"""sim_bridge as a real process over DDS (localhost discovery, random domain): joint states,
commands, objects, camera, kinesthetic guiding, robustness to bad input and bad parameters. The
tests on the running node run once with its fast path and once with plain rclpy (``fast_path``)."""
import pathlib
import re
import time

import numpy as np
import pytest
from deepprompt_msgs.msg import ResultCode
from deepprompt_msgs.srv import SpawnObject
from geometry_msgs.msg import PointStamped, PoseStamped
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Image, JointState
from std_msgs.msg import String
from std_srvs.srv import SetBool, Trigger

from deepprompt_ros.robots.kinematics import RobotKinematics
from deepprompt_ros.robots.spec import load_robot
from deepprompt_ros.ros import conversions as conv
from deepprompt_ros.common.params import specs_of
from deepprompt_ros.ros.fastpath.wire import ClockSerializer, CommandReader, JointStateSerializer
from deepprompt_ros.ros.testing import NodeProcess, RosTestClient, isolated_ros_env
from deepprompt_ros.sim.bridge_config import ObjectConfig, SimBridgeConfig

CONFIG = pathlib.Path(__file__).resolve().parents[1] / "config" / "sim_bridge.yaml"
SPEC = load_robot("gen3_lite")
KIN = RobotKinematics(SPEC)
RATE = 1000.0
CAMERA = dict(width=48, height=32, rate=10.0)
SIM_PARAMS = {
    "robot": "gen3_lite", "rate_hz": RATE, "real_time_factor": 1.0,
    "camera.enabled": True, "camera.width": CAMERA["width"], "camera.height": CAMERA["height"],
    "camera.rate_hz": CAMERA["rate"],
    "object_names": ["box1"], "objects.box1.shape": "box", "objects.box1.size": [0.04, 0.04, 0.04],
    "objects.box1.position": [0.35, 0.15, 0.02],
}


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    return isolated_ros_env(tmp_path_factory.mktemp("ros_sim_bridge"))


@pytest.fixture(scope="module", params=[True, False], ids=["fast_path", "plain_rclpy"])
def sim(env, request):
    """The node under test, in one mode after the other (the first is stopped before the second starts)."""
    with NodeProcess.start_module("deepprompt_ros.ros.sim_bridge", env,
                                  params={**SIM_PARAMS, "fast_path": request.param},
                                  name="sim_bridge_" + ("fast" if request.param else "plain")) as proc:
        yield proc


@pytest.fixture(scope="module")
def client(env, sim):
    with RosTestClient(env) as c:
        c.joint_states = c.subscribe("joint_states", JointState, 1)  # the current state only
        assert c.wait_for_messages(c.joint_states, 1, timeout=30.0), sim.output_tail()
        yield c


def _q(msg) -> np.ndarray:
    return conv.reorder_joints(msg.name, msg.position, SPEC.joint_names)


def _latest_q(client) -> np.ndarray:
    return _q(client.latest(client.joint_states))


def _wait_at_rest(client, timeout: float = 5.0, tol: float = 1e-3) -> np.ndarray:
    """Wait until all joint speeds are below ``tol`` rad/s; return the positions then."""
    def at_rest():
        client.drain()
        return np.max(np.abs(client.joint_states.last().velocity)) < tol

    assert client.wait_for(at_rest, timeout), f"arm still moving: {client.joint_states.last().velocity}"
    return _latest_q(client)


def _command(q, names=SPEC.joint_names, velocity=None) -> JointState:
    return conv.arrays_to_joint_state(names, q, velocity)


def test_robot_description_reaches_a_late_subscriber(sim, client):
    """Published once at start, transient local: a subscriber created long after gets the URDF."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    log = client.subscribe("robot_description", String, qos)
    assert client.wait_for_messages(log, 1, 10.0), sim.output_tail()
    assert log.last().data == SPEC.urdf_path.read_text()
    assert '<robot name="' in log.last().data and all(f'name="{j}"' in log.last().data for j in SPEC.joint_names)
    info, = client.node.get_publishers_info_by_topic("/robot_description")  # (depth is not discovered)
    assert (info.qos_profile.durability, info.qos_profile.reliability) == (DurabilityPolicy.TRANSIENT_LOCAL,
                                                                          ReliabilityPolicy.RELIABLE)
    client.unsubscribe(log)


def test_joint_states_rate_names_and_stamps(sim, client):
    log = client.subscribe("joint_states", JointState, 3000)  # every message
    assert client.wait_for_messages(log, 1, 5.0)
    n0 = len(log)
    client.spin_for(1.5)
    client.unsubscribe(log)
    got = log[n0:]
    assert len(got) > 300, sim.output_tail()
    msgs = [r.msg for r in got]
    assert all(tuple(m.name) == SPEC.joint_names for m in msgs)
    assert all(len(m.position) == len(m.velocity) == len(m.effort) == 6 for m in msgs)
    np.testing.assert_allclose(_q(msgs[0]), SPEC.home, atol=1e-2)  # starts at home and holds it
    # One message per physics step of 1/RATE s of simulated time, none lost on the way.
    stamps = np.array([conv.stamp_to_ns(m.header.stamp) for m in msgs])
    np.testing.assert_allclose(np.diff(stamps), 1e9 / RATE, atol=2)
    # Paced to real time: wall-clock rate close to RATE (the machine may be shared: lenient below).
    recv = np.array([r.time for r in got])
    wall_rate = (len(got) - 1) / (recv[-1] - recv[0])
    sim_per_wall = (stamps[-1] - stamps[0]) * 1e-9 / (recv[-1] - recv[0])
    gaps = np.diff(recv) * 1e3
    print(f"joint_states: {wall_rate:.0f} msg/s (configured {RATE:.0f}), simulated s per wall s "
          f"{sim_per_wall:.3f}, inter-arrival p50 {np.percentile(gaps, 50):.3f} ms, "
          f"p99 {np.percentile(gaps, 99):.3f} ms, max {gaps.max():.2f} ms")
    # Pacing: never faster than real time; the lower bounds (a quarter of real time) only catch a
    # stalled simulation, not one slowed down by other work on the machine.
    assert 0.25 * RATE < wall_rate < 1.1 * RATE
    assert 0.25 < sim_per_wall < 1.1
    # /clock carries the same simulation time.
    clock = client.subscribe("/clock", Clock, 100)
    assert client.wait_for_messages(clock, 5, 5.0)
    # /clock carries the same simulation time: every clock value lies on the joint_states step grid
    # (same epoch, whole physics steps later) — independent of how late either message arrives.
    for m in clock.messages()[:5]:
        steps = (conv.stamp_to_ns(m.clock) - stamps[0]) / (1e9 / RATE)
        assert steps >= 0 and abs(steps - round(steps)) < 1e-3, steps


def test_joint_states_rate_hz_publishes_every_nth_step(env, tmp_path):
    params = {"rate_hz": RATE, "joint_states_rate_hz": 250.0, "camera.enabled": False, "publish_clock": False}
    with NodeProcess.start_module("deepprompt_ros.ros.sim_bridge", env, params=params, log_dir=tmp_path,
                                  name="js250", ros_args=["-r", "__ns:=/js250"]) as proc, \
            RosTestClient(env, "js250_client") as c:  # own namespace: no second /joint_states or /reset
        log = c.subscribe("/js250/joint_states", JointState, 1000)
        assert c.wait_for_messages(log, 1, 30.0), proc.output_tail()
        n0 = len(log)
        c.spin_for(1.0)
        got = log[n0:]
    stamps = np.array([conv.stamp_to_ns(r.msg.header.stamp) for r in got])
    np.testing.assert_allclose(np.diff(stamps), 4e9 / RATE, atol=2)  # every 4th step of 1 ms
    recv = np.array([r.time for r in got])
    assert 0.25 * 250 < (len(got) - 1) / (recv[-1] - recv[0]) < 1.1 * 250
    assert "every 4 steps (250 Hz)" in proc.output()


def test_serialized_joint_states_clock_and_commands_match_the_messages():
    """The byte templates of sim_bridge agree with rclpy's serialization, field by field."""
    from builtin_interfaces.msg import Time
    from rclpy.serialization import deserialize_message, serialize_message

    rng = np.random.default_rng(3)
    ser = JointStateSerializer(SPEC.joint_names, effort=True)
    for stamp in (0, 1_795_000_000_123_456_789, 2**31 * 10**9 - 1):
        q, qd, eff = rng.normal(size=(3, 6))
        m = deserialize_message(ser(q, qd, stamp, eff), JointState)
        assert conv.stamp_to_ns(m.header.stamp) == stamp and tuple(m.name) == SPEC.joint_names
        np.testing.assert_array_equal(m.position, q)
        np.testing.assert_array_equal(m.velocity, qd)
        np.testing.assert_array_equal(m.effort, eff)
    assert conv.stamp_to_ns(deserialize_message(ClockSerializer()(123_000_000_456), Clock).clock) == 123_000_000_456

    read = CommandReader(SPEC.joint_names, SPEC.joints_text())
    names = SPEC.joint_names
    order = [3, 0, 5, 1, 4, 2]
    for k in range(6):  # layouts: robot order, shuffled, shuffled with a frame id, without velocities
        perm = list(range(6)) if k < 2 else order
        q, qd = rng.uniform(-1, 1, (2, 6))
        msg = conv.arrays_to_joint_state([names[i] for i in perm], q[perm], None if k == 5 else qd[perm],
                                         effort=np.ones(6), stamp_ns=k)
        if k >= 4:
            msg.header.frame_id = "base_link_frame"
        for _ in range(2):  # first the full validation, then the in-place read of the same layout
            got_q, got_qd = read(serialize_message(msg))
            np.testing.assert_array_equal(got_q, q)
            assert got_qd is None if k == 5 else np.array_equal(got_qd, qd)
    bad = [(JointState(name=list(names), position=[0.0] * 6, velocity=[0.0] * 2), "2 velocity values"),
           (JointState(name=list(names[:5]) + ["wrist"], position=[0.0] * 6), "expected exactly the 6 joints"),
           (JointState(name=list(names), position=[0.0] * 5), "5 position values"),
           (JointState(name=list(names)), "no positions")]
    for m, text in bad:  # the same names as the cached layout, other counts: refused too
        with pytest.raises(ValueError, match=text):
            read(serialize_message(m))
    with pytest.raises(ValueError, match="not a sensor_msgs/JointState"):
        read(serialize_message(Time(sec=1)))
    np.testing.assert_array_equal(read(serialize_message(conv.arrays_to_joint_state(names, np.ones(6))))[0],
                                  np.ones(6))


def test_command_moves_arm_within_velocity_limit(sim, client):
    target = SPEC.home + np.array([0.12, -0.1, 0.1, -0.12, 0.1, 0.12])
    SPEC.validate_positions(target)
    names = tuple(reversed(SPEC.joint_names))  # any joint order is accepted
    n0 = len(client.joint_states)
    t0 = time.perf_counter()
    reached = None
    while time.perf_counter() - t0 < 8.0:
        client.publish("joint_command", _command(target[::-1], names))
        client.spin_for(0.02)
        client.drain()
        if np.max(np.abs(_q(client.joint_states.last()) - target)) < 2e-3:
            reached = time.perf_counter() - t0
            break
    q_end = _q(client.joint_states.last())
    assert reached is not None, f"arm at {q_end}, target {target}\n{sim.output_tail()}"
    vel = np.array([conv.reorder_joints(r.msg.name, r.msg.velocity, SPEC.joint_names)
                    for r in client.joint_states[n0:]])
    print(f"command reached within 2 mrad after {reached:.2f} s; peak |qd| {np.abs(vel).max(axis=0).round(3)}")
    assert np.all(np.abs(vel).max(axis=0) <= SPEC.velocity * 1.002)
    assert np.abs(vel).max() > 0.2  # it really moved at speed (the limit is 0.5 rad/s)


def test_malformed_commands_do_not_kill_it(sim, client):
    q0 = _wait_at_rest(client)
    bad = [
        _command(q0, names=("joint_1", "joint_2", "joint_3", "joint_4", "joint_5", "wrist")),
        _command(q0[:5], names=SPEC.joint_names[:5]),
        _command(np.where(np.arange(6) == 2, np.nan, q0)),
        _command(q0 + np.array([0, 5.0, 0, 0, 0, 0])),  # joint_2 outside its limits
        _command(q0, velocity=np.full(6, 10.0)),  # above the velocity limits
        JointState(name=list(SPEC.joint_names), position=list(q0), velocity=[0.0, 0.0]),
        JointState(name=["joint_1"] * 6, position=list(q0)),
    ]
    for _ in range(20):
        for msg in bad:
            client.publish("joint_command", msg)
        client.spin_for(0.02)
    client.spin_for(0.3)
    assert sim.running(), sim.output_tail()
    q1 = _latest_q(client)
    assert np.max(np.abs(q1 - q0)) < 1e-3  # none of them was executed
    out = sim.output()
    warnings = re.findall(r"joint command rejected: .*", out)
    assert warnings, sim.output_tail()
    assert len(warnings) <= 4  # 140 bad messages in ~1 s, throttled to about one line per second


def test_spawn_object_and_pose_topics(sim, client):
    box = client.subscribe("objects/box1/pose", PoseStamped, 10)
    assert client.wait_for_messages(box, 1, 5.0), sim.output_tail()
    p, _ = conv.pose_to_arrays(box.last().pose)
    assert box.last().header.frame_id == "world"
    np.testing.assert_allclose(p, [0.35, 0.15, 0.02], atol=5e-3)  # object from the parameters

    req = SpawnObject.Request(name="ball", shape="sphere", size=[0.03], mass=0.1)
    req.pose = conv.arrays_to_pose([0.3, -0.2, 0.03])
    res = client.call(SpawnObject, "spawn_object", req)
    assert res.success and res.code.value == ResultCode.SUCCESS, res.message
    ball = client.subscribe("objects/ball/pose", PoseStamped, 10)
    assert client.wait_for_messages(ball, 3, 5.0)
    np.testing.assert_allclose(conv.pose_to_arrays(ball.last().pose)[0], [0.3, -0.2, 0.03], atol=5e-3)

    req.pose = conv.arrays_to_pose([0.25, 0.25, 0.03])  # same name: replaced
    assert client.call(SpawnObject, "spawn_object", req).success
    assert client.wait_for(lambda: abs(ball.last().pose.position.y - 0.25) < 5e-3, 3.0)

    for bad, match in [(SpawnObject.Request(name="cone", shape="cone", size=[0.1]), "unknown shape 'cone'"),
                       (SpawnObject.Request(name="9 bad/name", shape="box", size=[0.1, 0.1, 0.1]), "not valid"),
                       (SpawnObject.Request(name="flat", shape="box", size=[0.1]), "3 positive numbers")]:
        res = client.call(SpawnObject, "spawn_object", bad)
        assert not res.success and res.code.value == ResultCode.INVALID_REQUEST
        assert match in res.message, res.message
    assert sim.running()


def test_camera_image(sim, client):
    images = client.subscribe("camera/image_raw", Image, 10)
    assert client.wait_for_messages(images, 3, 5.0), sim.output_tail()
    msg = images.last()
    assert (msg.width, msg.height, msg.encoding, msg.step) == (48, 32, "rgb8", 48 * 3)
    assert msg.header.frame_id == "camera"
    img = conv.image_to_array(msg)
    assert img.shape == (32, 48, 3) and img.std() > 10  # a rendered scene, not a blank frame
    dt = np.diff([conv.stamp_to_ns(r.msg.header.stamp) for r in images]) * 1e-9
    np.testing.assert_allclose(dt, 1.0 / CAMERA["rate"], atol=2e-3)  # camera.rate_hz in simulated time


def test_kinesthetic_guiding_moves_the_arm_and_reset(sim, client):
    res = client.call(SetBool, "set_kinesthetic", SetBool.Request(data=True))
    assert res.success, res.message
    q0 = _latest_q(client)
    ee0 = KIN.forward_kinematics(q0).position
    target = ee0 + np.array([0.0, 0.12, 0.0])
    guide = PointStamped()
    guide.header.frame_id = "world"
    guide.point.x, guide.point.y, guide.point.z = target.tolist()
    client.publish("guide_target", guide)
    client.publish("joint_command", _command(SPEC.home))  # ignored while kinesthetic
    t0 = time.perf_counter()

    def ee():
        client.drain()
        return KIN.forward_kinematics(_q(client.joint_states.last())).position

    arrived = client.wait_for(lambda: np.linalg.norm(target - ee()) < 0.02, 10.0)
    ee1 = ee()
    print(f"guided end effector moved {np.linalg.norm(ee1 - ee0) * 100:.1f} cm towards a target 12 cm away "
          f"in {time.perf_counter() - t0:.2f} s; remaining {np.linalg.norm(target - ee1) * 100:.1f} cm")
    assert arrived, sim.output_tail()
    assert "kinesthetic mode is on" in sim.output()

    guide.point.x = float("nan")  # clear the guide, leave kinesthetic mode: the arm holds still
    client.publish("guide_target", guide)
    client.spin_for(0.1)
    assert client.call(SetBool, "set_kinesthetic", SetBool.Request(data=False)).success
    q_hold = _wait_at_rest(client)
    client.spin_for(0.5)
    assert np.max(np.abs(_latest_q(client) - q_hold)) < 1e-3

    assert client.call(Trigger, "reset").success
    client.spin_for(0.1)
    np.testing.assert_allclose(_latest_q(client), SPEC.home, atol=1e-3)


def _flatten(d, prefix=""):
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[prefix + k] = v
    return out


def test_config_file_documents_the_declared_parameters():
    import yaml

    values = _flatten(yaml.safe_load(CONFIG.read_text())["sim_bridge"]["ros__parameters"])
    declared = {p.name: list(p.default) if isinstance(p.default, tuple) else p.default
                for p in specs_of(SimBridgeConfig)}
    objects = values.pop("object_names")
    assert objects == ["cube"]
    obj = {k: v for k, v in values.items() if k.startswith("objects.")}
    assert {k for k in obj} == {f"objects.cube.{f.name}" for f in specs_of(ObjectConfig)}
    ObjectConfig(**{k.rsplit(".", 1)[1]: tuple(v) if isinstance(v, list) else v for k, v in obj.items()})
    plain = {k: v for k, v in values.items() if k not in obj}
    assert set(plain) == set(declared) - {"object_names"}
    assert {k: v for k, v in plain.items() if v != declared[k]} == {}  # the file shows the defaults


def test_invalid_parameters_exit_with_clear_message(env, tmp_path):
    shipped = NodeProcess.start_module("deepprompt_ros.ros.sim_bridge", env, params_files=[CONFIG],
                                       log_dir=tmp_path, name="shipped_config")
    cases = [({"robot": "no_such_robot"}, "unknown robot 'no_such_robot'; available: gen3_lite, wam"),
             ({"rate_hz": -5.0}, "rate_hz"),
             ({"camera.width": "wide"}, "camera.width"),
             ({"initial_positions": [0.0, 0.0]}, "has 2 joint values"),
             ({"joint_states_rate_hz": 2000.0}, "joint_states_rate_hz")]
    procs = [NodeProcess.start_module("deepprompt_ros.ros.sim_bridge", env, params=p, log_dir=tmp_path,
                                      name=f"bad{i}") for i, (p, _) in enumerate(cases)]
    try:
        for proc, (_, text) in zip(procs, cases):
            rc = proc.wait(60.0)
            out = proc.output()
            assert rc == 2, proc.output_tail()
            assert "invalid configuration" in out and text in out, out
            assert "Traceback" not in out, out
        # The shipped configuration starts (with its example cube) and stops cleanly on SIGINT.
        deadline = time.monotonic() + 60.0
        while "objects ['cube']" not in shipped.output() and shipped.running() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert "robot gen3_lite (joint_1..joint_6), 1000 Hz" in shipped.output(), shipped.output_tail()
        assert shipped.stop() == 0, shipped.output_tail()
    finally:
        for proc in procs + [shipped]:
            proc.stop()
