"""Demo recording: the ROS-free core (deepprompt_ros.recording) in-process, then the
demo_recorder node as a real process next to a real sim_bridge process (localhost DDS, random
domain): a kinesthetic demonstration guided in the simulation (recorded with the recorder's fast
path and with plain rclpy, ``fast_path``), bad requests, crash safety."""
import pathlib
import time

import numpy as np
import pytest
import yaml
from deepprompt_msgs.msg import ResultCode
from deepprompt_msgs.srv import StartRecording, StopRecording
from geometry_msgs.msg import PointStamped
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState
from std_srvs.srv import SetBool, Trigger

from deepprompt_ros.common.params import specs_of
from deepprompt_ros.recording.bag_writer import BagWriter, message_definition, qos_profile_yaml
from deepprompt_ros.recording.checks import (
    RecordingError,
    check_writable_directory,
    default_demo_name,
    parse_context_spec,
    validate_demo_name,
)
from deepprompt_ros.recording.demo_buffer import DemoBuffer
from deepprompt_ros.recording.images import ImageKeeper, resize_image
from deepprompt_ros.recording.config import RecorderConfig
from deepprompt_ros.data.demo_dataset import load_dataset
from deepprompt_ros.data.io import load_demo
from deepprompt_ros.robots.kinematics import RobotKinematics
from deepprompt_ros.robots.spec import load_robot
from deepprompt_ros.ros import conversions as conv
from deepprompt_ros.ros.testing import NodeProcess, RosTestClient, isolated_ros_env

CONFIG = pathlib.Path(__file__).resolve().parents[1] / "config" / "demo_recorder.yaml"
SPEC = load_robot("gen3_lite")
CUBE = [0.35, -0.1, 0.02]


def _read_mcap(path):
    """(summary, [(topic, schema name, decoded message)]) of an MCAP file."""
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        msgs = [(ch.topic, sch.name, dec) for sch, ch, _, dec in reader.iter_decoded_messages()]
    return summary, msgs


# ==============================================================================================
# core, in-process
# ==============================================================================================
def test_message_definition_has_each_dependency_once():
    text = message_definition("geometry_msgs/msg/PoseStamped")
    headers = [line for line in text.splitlines() if line.startswith("MSG: ")]
    assert headers == ["MSG: std_msgs/Header", "MSG: builtin_interfaces/Time", "MSG: geometry_msgs/Pose",
                       "MSG: geometry_msgs/Point", "MSG: geometry_msgs/Quaternion"]
    assert text.count("=" * 80 + "\n") == 5
    with pytest.raises(RecordingError, match="share/nope_msgs/msg/Foo.msg"):
        message_definition("nope_msgs/msg/Foo")


def test_bag_writer_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    bag = BagWriter(tmp_path, "b1")
    bag.add_topic("/joint_states", "sensor_msgs/msg/JointState", offered_qos_profiles=qos_profile_yaml())
    bag.add_topic("/objects/cube/pose", "geometry_msgs/msg/PoseStamped")
    sent = []
    for i in range(50):
        q = rng.normal(size=6)
        sent.append(q)
        bag.write("/joint_states", serialize_message(conv.arrays_to_joint_state(SPEC.joint_names, q)),
                  1_000_000_000 + i * 1_000_000)
    for i in range(5):
        bag.write("/objects/cube/pose", serialize_message(conv.pose_stamped([i, 0, 0])), 1_000_000_000 + i)
    with pytest.raises(RecordingError, match="not added"):
        bag.write("/other", b"", 0)
    assert not (tmp_path / "b1").exists()  # only the hidden temporary folder while writing
    path = bag.close()
    assert path == tmp_path / "b1" / "b1_0.mcap"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b1"]
    summary, msgs = _read_mcap(path)
    assert summary.statistics.message_count == 55
    assert {s.name: s.encoding for s in summary.schemas.values()} == {
        "sensor_msgs/msg/JointState": "ros2msg", "geometry_msgs/msg/PoseStamped": "ros2msg"}
    js = [m for t, _, m in msgs if t == "/joint_states"]
    np.testing.assert_array_equal([list(m.position) for m in js], sent)
    assert list(js[0].name) == list(SPEC.joint_names)
    meta = yaml.safe_load((path.parent / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 9 and meta["storage_identifier"] == "mcap" and meta["message_count"] == 55
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]}
    assert counts == {"/joint_states": 50, "/objects/cube/pose": 5}
    assert meta["relative_file_paths"] == ["b1_0.mcap"]
    assert meta["duration"]["nanoseconds"] == 49_000_000
    qos = yaml.safe_load(meta["topics_with_message_count"][0]["topic_metadata"]["offered_qos_profiles"])
    assert qos[0]["reliability"] == "reliable" and qos[0]["history"] == "keep_last"
    with pytest.raises(RecordingError, match="exists already"):
        BagWriter(tmp_path, "b1")


def test_bag_writer_abort_leaves_nothing(tmp_path):
    bag = BagWriter(tmp_path, "gone")
    bag.add_topic("/joint_states", "sensor_msgs/msg/JointState")
    bag.write("/joint_states", serialize_message(JointState()), 1)
    bag.abort()
    assert list(tmp_path.iterdir()) == []


def test_resize_image_area_average():
    rng = np.random.default_rng(1)
    blocks = rng.integers(0, 256, size=(3, 4, 3)).astype(np.uint8)
    img = np.repeat(np.repeat(blocks, 5, axis=0), 5, axis=1)  # 15 x 20, constant 5x5 blocks
    np.testing.assert_array_equal(resize_image(img, 3, 4), blocks)
    small = resize_image(rng.integers(0, 256, size=(48, 64, 3), dtype=np.uint8), 10, 7)
    assert small.shape == (10, 7, 3) and small.dtype == np.uint8
    flat = np.full((31, 17, 3), 123, dtype=np.uint8)
    np.testing.assert_array_equal(resize_image(flat, 8, 40), 123)  # any ratio, also enlarging
    two = np.zeros((2, 2, 3), dtype=np.uint8)
    two[:, 1] = 200
    np.testing.assert_array_equal(resize_image(two, 1, 1), 100)
    with pytest.raises(RecordingError, match=r"uint8 with shape \(H, W, 3\)"):
        resize_image(np.zeros((4, 4)), 2, 2)


def test_image_keeper_is_bounded_and_spread_over_the_recording():
    keeper = ImageKeeper(max_images=4, height=2, width=2)
    for i in range(1000):
        keeper.add(np.full((6, 6, 3), i % 256, dtype=np.uint8) if i < 256 else np.full((6, 6, 3), 255, np.uint8))
        assert len(keeper) < keeper.capacity
    sel = keeper.selected()
    assert sel.shape == (4, 2, 2, 3)
    assert sel[0, 0, 0, 0] == 0 and sel[-1, 0, 0, 0] == 255  # first and last part of the recording
    few = ImageKeeper(max_images=4, height=2, width=2)
    few.add(np.zeros((3, 3, 3), np.uint8))
    assert few.selected().shape == (1, 2, 2, 3)
    assert ImageKeeper(2, 2, 2).selected() is None


def test_demo_buffer():
    buf = DemoBuffer("d1", ["b", "a"], max_images=2, image_height=4, image_width=4)
    assert buf.add_joint_state(1_000_000_000, ["a", "b", "c"], [1.0, 2.0, 3.0])
    assert not buf.add_joint_state(1_000_000_000, ["a", "b"], [0.0, 0.0])  # same stamp
    assert not buf.add_joint_state(1_001_000_000, ["a"], [0.0])  # joint b missing
    assert not buf.add_joint_state(1_001_000_000, ["a", "b"], [np.nan, 0.0])
    assert buf.add_joint_state(1_002_000_000, ["b", "a"], [5.0, 4.0])
    assert buf.add_context("object", [0.3, 0.1, 0.0]) and not buf.add_context("object", [9.0, 9.0, 9.0])
    buf.add_image(np.zeros((8, 8, 3), np.uint8))
    s = buf.stats()
    assert (s.n_samples, s.missing_joints, s.not_increasing, s.non_finite) == (2, 1, 1, 1)
    demo = buf.to_demonstration()
    np.testing.assert_allclose(demo.t, [0.0, 0.002])
    np.testing.assert_array_equal(demo.q, [[2.0, 1.0], [5.0, 4.0]])
    assert demo.joint_names == ("b", "a")
    np.testing.assert_array_equal(demo.contexts["object"], [[0.3, 0.1, 0.0]])
    assert demo.images.shape == (1, 4, 4, 3)
    empty = DemoBuffer("d2", ["a"])
    empty.add_joint_state(1, ["x"], [0.0])
    with pytest.raises(RecordingError, match=r"0 joint sample\(s\); at least 2.*1 message\(s\) lacked"):
        empty.to_demonstration()


def test_recording_helpers(tmp_path):
    assert parse_context_spec("object=objects/cube/pose") == ("object", "objects/cube/pose")
    assert parse_context_spec("/camera/image_raw") == ("camera_image_raw", "/camera/image_raw")
    with pytest.raises(RecordingError, match="context name"):
        parse_context_spec("1x=topic")
    for bad in ["", "../x", "a/b", "-x", "x" * 101]:
        with pytest.raises(RecordingError, match="not valid"):
            validate_demo_name(bad)
    assert validate_demo_name(default_demo_name())
    a_file = tmp_path / "file"
    a_file.write_text("")
    with pytest.raises(RecordingError, match="not a writable folder"):
        check_writable_directory(a_file / "sub")
    assert check_writable_directory(tmp_path / "new" / "dir").is_dir()


def test_config_file_documents_the_declared_parameters():
    values = yaml.safe_load(CONFIG.read_text())["demo_recorder"]["ros__parameters"]
    declared = {p.name: list(p.default) if isinstance(p.default, tuple) else p.default
                for p in specs_of(RecorderConfig)}
    assert set(values) == set(declared)
    assert values.pop("context_topics") == ["object=objects/cube/pose", "camera/image_raw"]
    assert {k: v for k, v in values.items() if v != declared[k]} == {}  # the file shows the defaults


# ==============================================================================================
# nodes as processes
# ==============================================================================================
@pytest.fixture(scope="module")
def env(tmp_path_factory):
    return isolated_ros_env(tmp_path_factory.mktemp("ros_recorder"))


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return tmp_path_factory.mktemp("recordings")


def _recorder_params(out: pathlib.Path, **kw):
    return {"output_directory": str(out), "context_topics": ["object=objects/cube/pose", "camera/image_raw"],
            "max_images": 3, "image_width": 24, "image_height": 16, **kw}


@pytest.fixture(scope="module")
def nodes(env, work):
    """sim_bridge + recorder A (main) + P (A's settings with plain rclpy, in /p) + B (crashed later) +
    C (misconfigured) + D (invalid parameters)."""
    not_a_dir = work / "not_a_dir"
    not_a_dir.write_text("")
    procs = {
        "sim": NodeProcess.start_module("deepprompt_ros.ros.sim_bridge", env, params={
            "rate_hz": 1000.0, "camera.width": 48, "camera.height": 32, "camera.rate_hz": 10.0,
            "object_names": ["cube"], "objects.cube.position": CUBE}),
        "A": NodeProcess.start_module("deepprompt_ros.ros.demo_recorder", env, name="recorder_A",
                                      params_files=[CONFIG], params=_recorder_params(work / "A")),
        "P": NodeProcess.start_module("deepprompt_ros.ros.demo_recorder", env, name="recorder_P",
                                      params_files=[CONFIG], ros_args=["-r", "__ns:=/p"],
                                      params=_recorder_params(work / "P", fast_path=False,
                                                              joint_states_topic="/joint_states",
                                                              context_topics=["object=/objects/cube/pose",
                                                                              "/camera/image_raw"])),
        "B": NodeProcess.start_module("deepprompt_ros.ros.demo_recorder", env, name="recorder_B",
                                      ros_args=["-r", "__ns:=/b"],
                                      params=_recorder_params(work / "B", joint_states_topic="/joint_states",
                                                              context_topics=["object=/objects/cube/pose"])),
        "C": NodeProcess.start_module("deepprompt_ros.ros.demo_recorder", env, name="recorder_C",
                                      ros_args=["-r", "__ns:=/c"],
                                      params=_recorder_params(not_a_dir / "demos", joint_states_topic="nothing_here",
                                                              context_topics=["object=/objects/cube/pose"])),
        "D": NodeProcess.start_module("deepprompt_ros.ros.demo_recorder", env, name="recorder_D",
                                      params={"max_images": 0, "phase_type": "circular",
                                              "context_topics": ["9=bad"]}),
    }
    try:
        yield procs
    finally:
        for p in procs.values():
            p.stop()


@pytest.fixture(scope="module")
def client(env, nodes):
    with RosTestClient(env) as c:
        c.joint_states = c.subscribe("joint_states", JointState, 1)
        for ns in ("", "/p", "/b", "/c"):
            assert c.wait_for_recorder(ns, 30.0), "\n".join(p.output_tail() for p in nodes.values())
        assert c.wait_for_messages(c.joint_states, 1, 10.0), nodes["sim"].output_tail()
        for prefix, name in (("", "A"), ("/p/", "P"), ("/b/", "B")):  # until each recorder discovered the sim
            deadline = time.monotonic() + 30.0
            while not (res := _start(c, "probe", prefix)).success and time.monotonic() < deadline:
                c.spin_for(0.2)
            assert res.success, res.message + nodes[name].output_tail()
            assert _stop(c, prefix, discard=True).success
        yield c


def _start(client, name, prefix=""):
    return client.call(StartRecording, prefix + "start_recording", StartRecording.Request(demo_name=name))


def _stop(client, prefix="", discard=False):
    return client.call(StopRecording, prefix + "stop_recording", StopRecording.Request(discard=discard))


@pytest.mark.parametrize("recorder,prefix", [("A", ""), ("P", "/p/")], ids=["fast_path", "plain_rclpy"])
def test_record_guided_kinesthetic_demo(nodes, client, work, recorder, prefix):
    kin = RobotKinematics(SPEC)
    res = _start(client, "guided_1", prefix)
    assert res.success and res.code.value == ResultCode.SUCCESS, res.message
    assert client.call(SetBool, "set_kinesthetic", SetBool.Request(data=True)).success
    js = client.latest(client.joint_states)
    ee0 = kin.forward_kinematics(conv.reorder_joints(js.name, js.position, SPEC.joint_names)).position
    guide = PointStamped()
    guide.point.x, guide.point.y, guide.point.z = (ee0 + [0.0, 0.1, 0.0]).tolist()
    client.publish("guide_target", guide)
    client.spin_for(1.5)
    res = _stop(client, prefix)
    assert res.success, res.message + nodes[recorder].output_tail()
    print(res.message)
    guide.point.x = float("nan")
    client.publish("guide_target", guide)
    client.call(SetBool, "set_kinesthetic", SetBool.Request(data=False))
    client.call(Trigger, "reset")

    assert res.dataset_path == str(work / recorder / "guided_1.npz")
    demo = load_demo(res.dataset_path)
    assert res.n_samples == len(demo.t) > 500
    assert demo.joint_names == SPEC.joint_names and demo.q.shape == (len(demo.t), 6)
    dt = np.diff(demo.t)
    assert demo.t[0] == 0.0 and np.all(dt > 0)
    assert np.median(dt) == pytest.approx(1e-3, abs=1e-6)  # the sim's 1 kHz stamps
    assert 0.5 < demo.t[-1] < 4.0  # 1.5 s of wall time; a busy machine runs the sim slower
    moved = np.linalg.norm(kin.forward_kinematics(demo.q[-1]).position - kin.forward_kinematics(demo.q[0]).position)
    assert moved > 0.05, f"end effector moved only {moved:.3f} m"
    np.testing.assert_allclose(demo.contexts["object"], [CUBE], atol=5e-3)
    assert demo.images.shape == (3, 16, 24, 3) and demo.images.dtype == np.uint8
    assert demo.images.std() > 10

    bag = pathlib.Path(res.bag_path)
    assert bag == work / recorder / "bags" / "guided_1" / "guided_1_0.mcap"
    summary, msgs = _read_mcap(bag)
    meta = yaml.safe_load((bag.parent / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]}
    assert summary.statistics.message_count == meta["message_count"] == sum(counts.values()) == len(msgs)
    assert {s.name for s in summary.schemas.values()} == {
        "sensor_msgs/msg/JointState", "geometry_msgs/msg/PoseStamped", "sensor_msgs/msg/Image"}
    assert all(s.encoding == "ros2msg" and s.data for s in summary.schemas.values())
    assert counts["/joint_states"] >= res.n_samples and counts["/camera/image_raw"] >= 3
    assert counts["/objects/cube/pose"] >= 1
    js = [m for t, _, m in msgs if t == "/joint_states"]
    assert list(js[-1].name) == list(SPEC.joint_names)
    np.testing.assert_allclose(demo.q[-1], js[-1].position)  # the same data in both files


def test_bad_requests_get_clear_answers(nodes, client, work):
    res = _stop(client)
    assert not res.success and res.code.value == ResultCode.NOT_RECORDING
    assert _start(client, "to_discard").success
    res = _start(client, "second")
    assert not res.success and res.code.value == ResultCode.RECORDING_ACTIVE and "to_discard" in res.message
    client.spin_for(0.2)
    res = _stop(client, discard=True)
    assert res.success and "discarded" in res.message
    assert not (work / "A" / "to_discard.npz").exists()
    assert not any(p.name.startswith((".to_discard", "to_discard")) for p in (work / "A" / "bags").iterdir())
    for name, code, text in [("../evil", ResultCode.INVALID_REQUEST, "not valid"),
                             ("guided_1", ResultCode.INVALID_REQUEST, "exists")]:
        res = _start(client, name)
        assert not res.success and res.code.value == code and text in res.message, res.message
    req = StartRecording.Request(demo_name="ctx", context_topics=["no/publisher/here"])
    res = client.call(StartRecording, "start_recording", req)
    assert not res.success and "/no/publisher/here has no publisher" in res.message
    assert nodes["A"].running()


def test_no_joint_states_and_unwritable_folder(nodes, client):
    res = _start(client, "nope", prefix="/c/")
    assert not res.success and res.code.value == ResultCode.ROBOT_STATE_STALE
    assert "no JointState received on /c/nothing_here" in res.message, res.message
    assert "not a writable folder" in res.message
    assert nodes["C"].running()


def test_invalid_parameters_exit_with_clear_message(nodes):
    proc = nodes["D"]
    assert proc.wait(60.0) == 2, proc.output_tail()
    out = proc.output()
    assert "invalid configuration" in out and "Traceback" not in out
    for text in ["max_images = 0: expected a value in [1, 64]",
                 "phase_type = 'circular': expected one of 'linear', 'rhythmic'",
                 "context_topics: context name '9'"]:
        assert text in out, out


def test_killed_recorder_keeps_finished_demos(nodes, client, work):
    out = work / "B"
    assert _start(client, "first", prefix="/b/").success
    client.spin_for(0.5)
    first = _stop(client, prefix="/b/")
    assert first.success, first.message
    res = _start(client, "second", prefix="/b/")
    assert res.success, res.message
    client.spin_for(0.7)
    nodes["B"].kill()  # SIGKILL in the middle of the second recording
    assert nodes["B"].returncode == -9

    dataset = load_dataset(out)
    assert [d.name for d in dataset.demos] == ["first"]
    demo = dataset.demos[0]
    assert len(demo.t) == first.n_samples > 200 and np.all(np.diff(demo.t) > 0)
    assert "object" in demo.contexts
    summary, msgs = _read_mcap(first.bag_path)
    assert summary is not None and summary.statistics.message_count == len(msgs) > first.n_samples
    assert not (out / "second.npz").exists() and not (out / "bags" / "second").exists()
    leftovers = [p.name for p in (out / "bags").iterdir() if p.name.startswith(".second.")]
    assert len(leftovers) == 1 and leftovers[0].endswith(".part")  # the unfinished raw data, hidden
    assert not [p for p in out.iterdir() if p.suffix == ".part"]  # no half-written .npz
