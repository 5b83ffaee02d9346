"""Round trips of the sensor conversions (JointState, Image, Pose, stamps, contexts) in
deepprompt_ros.ros.conversions, through real message objects and their CDR serialization."""
import numpy as np
import pytest
from geometry_msgs.msg import Point, PointStamped, Pose, PoseArray
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image, JointState
from std_msgs.msg import Float64MultiArray

from deepprompt_ros.ros import conversions as conv


def _cdr_round_trip(msg):
    return deserialize_message(serialize_message(msg), type(msg))


# ----------------------------------------------------------------------------------------------
# stamps
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("ns", [0, 1, 999_999_999, 1_000_000_000, 1_795_309_000_123_456_789])
def test_stamp_ns_round_trip(ns):
    stamp = conv.ns_to_stamp(ns)
    assert 0 <= stamp.nanosec < 1_000_000_000
    assert conv.stamp_to_ns(_cdr_round_trip(stamp)) == ns


def test_stamp_seconds_round_trip_and_errors():
    rng = np.random.default_rng(0)
    for t in rng.uniform(0, 2e9, 50):  # float64 resolution at 2e9 s is 2.4e-7 s; ns rounding adds 5e-10
        assert abs(conv.stamp_to_sec(conv.sec_to_stamp(t)) - t) <= 5e-7
    assert conv.stamp_to_ns(conv.sec_to_stamp(1.5)) == 1_500_000_000
    with pytest.raises(ValueError, match=">= 0"):
        conv.ns_to_stamp(-1)
    with pytest.raises(ValueError, match="finite"):
        conv.sec_to_stamp(float("nan"))


# ----------------------------------------------------------------------------------------------
# joint states
# ----------------------------------------------------------------------------------------------
def test_joint_state_round_trip():
    rng = np.random.default_rng(1)
    names = [f"joint_{i}" for i in range(1, 7)]
    q, qd, eff = rng.normal(size=(3, 6))
    msg = conv.arrays_to_joint_state(names, q, qd, eff, stamp_ns=123_456_789_012, frame_id="base")
    back = conv.joint_state_to_arrays(_cdr_round_trip(msg))
    assert back.names == tuple(names)
    np.testing.assert_array_equal(back.position, q)
    np.testing.assert_array_equal(back.velocity, qd)
    np.testing.assert_array_equal(back.effort, eff)
    assert back.stamp_ns == 123_456_789_012


def test_joint_state_optional_fields_are_none():
    msg = conv.arrays_to_joint_state(["a", "b"], [0.1, 0.2])
    assert len(msg.velocity) == 0 and len(msg.effort) == 0
    back = conv.joint_state_to_arrays(msg)
    assert back.velocity is None and back.effort is None
    np.testing.assert_array_equal(back.position, [0.1, 0.2])


@pytest.mark.parametrize("kwargs, match", [
    (dict(name=["a", "b"], position=[1.0]), "1 position values for 2 joint names"),
    (dict(name=["a", "b"], position=[1.0, 2.0], velocity=[1.0, 2.0, 3.0]), "3 velocity values"),
    (dict(name=["a", "a"], position=[1.0, 2.0]), "duplicate joint names"),
    (dict(name=["a", "b"]), "no positions"),
])
def test_joint_state_malformed(kwargs, match):
    with pytest.raises(ValueError, match=match):
        conv.joint_state_to_arrays(JointState(**kwargs))


def test_arrays_to_joint_state_wrong_length():
    with pytest.raises(ValueError, match="velocity has 2 values for 3 joint names"):
        conv.arrays_to_joint_state(["a", "b", "c"], [0, 0, 0], velocity=[1, 2])


def test_reorder_joints():
    rng = np.random.default_rng(2)
    names = ["j3", "j1", "extra", "j2"]
    values = rng.normal(size=4)
    out = conv.reorder_joints(names, values, ["j1", "j2", "j3"])
    np.testing.assert_array_equal(out, [values[1], values[3], values[0]])
    batch = rng.normal(size=(5, 4))
    np.testing.assert_array_equal(conv.reorder_joints(names, batch, ["j2"])[:, 0], batch[:, 3])
    with pytest.raises(ValueError, match=r"missing joint\(s\) \['j4'\]"):
        conv.reorder_joints(names, values, ["j1", "j4"])


# ----------------------------------------------------------------------------------------------
# images
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("encoding", ["rgb8", "bgr8"])
def test_image_round_trip(encoding):
    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, size=(7, 11, 3), dtype=np.uint8)
    msg = conv.array_to_image(img, encoding=encoding, stamp_ns=5, frame_id="camera")
    assert (msg.height, msg.width, msg.step, msg.encoding) == (7, 11, 33, encoding)
    raw = np.frombuffer(msg.data, dtype=np.uint8).reshape(7, 11, 3)
    np.testing.assert_array_equal(raw, img if encoding == "rgb8" else img[:, :, ::-1])
    back = conv.image_to_array(_cdr_round_trip(msg))
    assert back.dtype == np.uint8 and back.shape == (7, 11, 3)
    np.testing.assert_array_equal(back, img)


def test_image_with_row_padding():
    rng = np.random.default_rng(4)
    img = rng.integers(0, 256, size=(4, 5, 3), dtype=np.uint8)
    padded = np.zeros((4, 20), dtype=np.uint8)
    padded[:, :15] = img.reshape(4, 15)
    padded[:, 15:] = 77
    msg = Image(height=4, width=5, encoding="rgb8", step=20, data=padded.tobytes())
    np.testing.assert_array_equal(conv.image_to_array(msg), img)


@pytest.mark.parametrize("msg, match", [
    (Image(height=2, width=2, encoding="mono8", step=2, data=bytes(4)), "'mono8' is not supported; expected one of rgb8, bgr8"),
    (Image(height=2, width=2, encoding="rgb8", step=6, data=bytes(11)), "has 11 bytes.*needs 12"),
    (Image(height=2, width=2, encoding="rgb8", step=5, data=bytes(10)), "step 5 is shorter"),
    (Image(height=0, width=2, encoding="rgb8", step=6, data=b""), "empty"),
])
def test_image_malformed(msg, match):
    with pytest.raises(ValueError, match=match):
        conv.image_to_array(msg)


def test_array_to_image_rejects_bad_arrays():
    with pytest.raises(ValueError, match=r"uint8 array of shape \(H, W, 3\)"):
        conv.array_to_image(np.zeros((4, 4), dtype=np.uint8))
    with pytest.raises(ValueError, match=r"uint8 array"):
        conv.array_to_image(np.zeros((4, 4, 3), dtype=np.float32))
    with pytest.raises(ValueError, match="'rgba8' is not supported"):
        conv.array_to_image(np.zeros((4, 4, 3), dtype=np.uint8), encoding="rgba8")


# ----------------------------------------------------------------------------------------------
# poses and points
# ----------------------------------------------------------------------------------------------
def test_pose_round_trip():
    rng = np.random.default_rng(5)
    for _ in range(20):
        p = rng.normal(size=3)
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        msg = conv.pose_stamped(p, q, stamp_ns=42, frame_id="world")
        back = _cdr_round_trip(msg)
        assert back.header.frame_id == "world" and conv.stamp_to_ns(back.header.stamp) == 42
        p2, q2 = conv.pose_to_arrays(back.pose)
        np.testing.assert_array_equal(p2, p)
        np.testing.assert_array_equal(q2, q)
    np.testing.assert_array_equal(conv.point_to_array(Point(x=1.0, y=2.0, z=3.0)), [1, 2, 3])


def test_pose_errors():
    with pytest.raises(ValueError, match="3 finite position values and 4 finite quaternion"):
        conv.arrays_to_pose([0, 0], [0, 0, 0, 1])
    with pytest.raises(ValueError, match="finite"):
        conv.arrays_to_pose([0, 0, np.nan], [0, 0, 0, 1])


# ----------------------------------------------------------------------------------------------
# contexts
# ----------------------------------------------------------------------------------------------
def test_context_vectors():
    ps = conv.pose_stamped([0.4, -0.1, 0.02], [0.0, 0.0, 0.6, 0.8])
    np.testing.assert_array_equal(conv.context_vector(ps), [0.4, -0.1, 0.02])
    np.testing.assert_array_equal(conv.context_vector(ps, pose_fields="pose"), [0.4, -0.1, 0.02, 0, 0, 0.6, 0.8])
    np.testing.assert_array_equal(conv.context_vector(ps.pose), [0.4, -0.1, 0.02])
    pt = PointStamped(point=Point(x=1.0, y=2.0, z=3.0))
    np.testing.assert_array_equal(conv.context_vector(pt), [1, 2, 3])
    arr = PoseArray(poses=[conv.arrays_to_pose([1, 2, 3]), conv.arrays_to_pose([4, 5, 6])])
    np.testing.assert_array_equal(conv.context_vector(arr), [1, 2, 3, 4, 5, 6])
    np.testing.assert_array_equal(conv.context_vector(Float64MultiArray(data=[0.5, 1.5])), [0.5, 1.5])


def test_context_vector_errors():
    with pytest.raises(ValueError, match="sensor_msgs/msg/JointState cannot be turned into a context vector; "
                                         "supported: geometry_msgs/msg/PoseStamped"):
        conv.context_vector(JointState())
    with pytest.raises(ValueError, match="NaN or inf"):
        conv.context_vector(PointStamped(point=Point(x=float("nan"))))
    with pytest.raises(ValueError, match="empty context vector"):
        conv.context_vector(PoseArray())
    with pytest.raises(ValueError, match="pose_fields"):
        conv.context_vector(Pose(), pose_fields="xyz")
