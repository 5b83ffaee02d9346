"""Round trips of the primitive-server conversions in deepprompt_ros.ros.conversions:
deepprompt_msgs requests/responses <-> the plain types of deepprompt_ros.server.requests, and
trajectory_msgs/JointTrajectory <-> arrays. Messages also go through CDR serialization."""
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message

from deepprompt_msgs.msg import Context, TrajectoryPreview
from deepprompt_msgs.srv import Condition, Sample
from trajectory_msgs.msg import JointTrajectory

from deepprompt_ros.server.images import decode_image
from deepprompt_ros.server.requests import Preview, PrimitiveDescription, SampleResult
from deepprompt_ros.ros import conversions as conv


def cdr(msg):
    return deserialize_message(serialize_message(msg), type(msg))


def test_via_points_round_trip_with_masks_and_weights():
    rng = np.random.default_rng(0)
    x, y = np.array([0.0, 0.25, 1.0]), rng.normal(size=(3, 6))
    masks = rng.random((3, 6)) > 0.5
    w = np.array([1.0, 0.0, 2.5])
    req = cdr(Condition.Request(primitive="reach", via_points=conv.via_points_to_msgs(x, y, masks, w)))
    back = conv.via_points_from_msgs(req.via_points)
    assert [v.phase for v in back] == x.tolist()
    np.testing.assert_array_equal(np.array([v.positions for v in back]), y)
    np.testing.assert_array_equal(np.array([v.joint_mask for v in back]), masks)
    assert [v.use_weight for v in back] == [True] * 3 and [v.weight for v in back] == w.tolist()
    plain = conv.via_points_from_msgs(conv.via_points_to_msgs(x, y))
    assert all(v.joint_mask.size == 0 and not v.use_weight and v.weight == 1.0 for v in plain)
    with pytest.raises(ValueError, match=r"shape \(3, d\)"):
        conv.via_points_to_msgs(x, y[:2])


def test_contexts_keep_values_and_raw_image_bytes():
    img = np.random.default_rng(1).integers(0, 255, (4, 5, 3), dtype=np.uint8)
    msgs = [Context(modality="object", values=[0.1, 0.2, 0.3], use_weight=True, weight=0.5),
            Context(modality="image", images=[conv.array_to_image(img, encoding="bgr8")])]
    back = conv.contexts_from_msgs(cdr(Condition.Request(contexts=msgs)).contexts)
    assert back[0].modality == "object" and back[0].values.tolist() == [0.1, 0.2, 0.3]
    assert back[0].use_weight and back[0].weight == 0.5 and back[0].images == ()
    im = back[1].images[0]
    assert (im.height, im.width, im.encoding, im.step) == (4, 5, "bgr8", 15)
    np.testing.assert_array_equal(decode_image(im, (4, 5)), img)  # decoded to RGB by the server


def test_preview_round_trip_and_row_major_layout():
    rng = np.random.default_rng(2)
    p = Preview(("a", "b", "c"), np.linspace(0, 1, 4), rng.normal(size=(4, 3)), rng.random((4, 3)))
    msg = cdr(conv.preview_to_msg(p))
    assert (msg.n_points, msg.n_joints) == (4, 3)
    assert msg.mean[2 * 3 + 1] == p.mean[2, 1]  # mean[t * n_joints + j]
    back = conv.preview_from_msg(msg)
    assert back.joint_names == p.joint_names
    np.testing.assert_array_equal(back.phases, p.phases)
    np.testing.assert_array_equal(back.mean, p.mean)
    np.testing.assert_array_equal(back.std, p.std)
    bad = TrajectoryPreview(joint_names=["a"], phases=[0.0, 1.0], mean=[1.0], std=[1.0], n_points=2, n_joints=1)
    with pytest.raises(ValueError, match="do not match"):
        conv.preview_from_msg(bad)


def test_primitive_info_carries_every_field():
    d = PrimitiveDescription("reach", ("j1", "j2"), np.array([-1.0, -2.0]), np.array([1.0, 2.0]), "linear",
                             ("object",), (3,), True, 64, 48, "rgb8", 16, "reach an object")
    m = cdr(conv.primitive_info_to_msg(d))
    assert (m.name, list(m.joint_names), list(m.position_lower), list(m.position_upper)) == (
        "reach", ["j1", "j2"], [-1.0, -2.0], [1.0, 2.0])
    assert (m.phase_type, list(m.context_modalities), list(m.context_dims)) == ("linear", ["object"], [3])
    assert (m.accepts_images, m.image_height, m.image_width, m.image_encoding, m.latent_dim, m.description) == (
        True, 64, 48, "rgb8", 16, "reach an object")


def test_samples_round_trip_and_layout():
    s = np.random.default_rng(3).normal(size=(2, 5, 3))
    res = cdr(conv.samples_to_response(SampleResult(("a", "b", "c"), np.linspace(0, 1, 5), s), Sample.Response()))
    assert (res.n_samples, res.n_points, res.n_joints) == (2, 5, 3)
    assert res.samples[(1 * 5 + 3) * 3 + 2] == s[1, 3, 2]
    np.testing.assert_array_equal(conv.samples_from_response(res), s)
    res.n_samples = 3
    with pytest.raises(ValueError, match="n_samples x n_points x n_joints"):
        conv.samples_from_response(res)


def test_joint_trajectory_round_trip_with_all_three_derivatives():
    rng = np.random.default_rng(4)
    t = np.array([0.001, 0.0105, 0.02, 1.25])
    q, qd, qdd = rng.normal(size=(3, 4, 6))
    msg = cdr(conv.joint_trajectory([f"joint_{i}" for i in range(1, 7)], t, q, qd, qdd, stamp_ns=5_000_000_123))
    assert isinstance(msg, JointTrajectory) and msg.header.stamp.sec == 5 and msg.header.stamp.nanosec == 123
    assert msg.points[1].time_from_start.nanosec == 10_500_000
    back = conv.joint_trajectory_to_arrays(msg)
    np.testing.assert_allclose(back.times, t, atol=1e-9)
    np.testing.assert_array_equal(back.q, q)
    np.testing.assert_array_equal(back.qd, qd)
    np.testing.assert_array_equal(back.qdd, qdd)
    assert back.stamp_ns == 5_000_000_123
    with pytest.raises(ValueError, match="strictly increasing"):
        conv.joint_trajectory(["a"], [0.1, 0.1], np.zeros((2, 1)), np.zeros((2, 1)), np.zeros((2, 1)))
    with pytest.raises(ValueError, match=r"expected \(2, 1\)"):
        conv.joint_trajectory(["a"], [0.1, 0.2], np.zeros((2, 2)), np.zeros((2, 1)), np.zeros((2, 1)))


def test_durations():
    d = conv.sec_to_duration(2.000000001)
    assert (d.sec, d.nanosec) == (2, 1)
    assert conv.duration_to_sec(conv.sec_to_duration(0.0015)) == pytest.approx(0.0015, abs=1e-12)
    with pytest.raises(ValueError):
        conv.sec_to_duration(-1.0)
