"""ros/fastpath/wire.py against rclpy's own serialization, byte for byte, over many random messages:
joint counts (0 included), names, frame ids, stamps up to 2**31 s, NaN-free values over many
magnitudes, empty arrays and point counts; the command reader against ``deserialize_message``
(every joint order, with and without velocities, the in-place path and the validating one).

``serialize_message`` leaves the alignment padding between fields, and the unused bytes at the end
of its buffer (its length is the type's size estimate), as it found the memory: two
serializations of one message can differ there. The comparison therefore covers every byte that
carries a field (stamps, string lengths and characters, sequence counts, numbers) and requires
equal lengths; :func:`content_bytes` finds those bytes by walking the message's CDR layout."""
import string

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from deepprompt_ros.ros import conversions as conv
from deepprompt_ros.ros.fastpath import wire

N_RANDOM = 200
NAME_CHARS = string.ascii_letters + string.digits + "_/"


_SIZES = {"boolean": 1, "octet": 1, "char": 1, "int8": 1, "uint8": 1, "int16": 2, "uint16": 2, "int32": 4,
          "uint32": 4, "float": 4, "int64": 8, "uint64": 8, "double": 8}


def _walk(value, typ, off: int, keep: list) -> int:
    """Append to ``keep`` the payload offsets (after the 4-byte encapsulation header) of every byte
    of ``value`` (of rosidl type ``typ``) that carries a field; returns the offset after it."""
    from rosidl_parser import definition as d

    if isinstance(typ, d.BasicType):
        size = _SIZES[typ.typename]
        off += -off % size
        keep.extend(range(off, off + size))
        return off + size
    if isinstance(typ, d.AbstractString):
        off += -off % 4
        n = 4 + len(value.encode()) + 1  # length, characters, NUL
        keep.extend(range(off, off + n))
        return off + n
    if isinstance(typ, d.AbstractSequence):
        off += -off % 4
        keep.extend(range(off, off + 4))
        off += 4
        for v in value:
            off = _walk(v, typ.value_type, off, keep)
        return off
    assert isinstance(typ, d.NamespacedType), typ
    for name, t in zip(value.get_fields_and_field_types(), value.SLOT_TYPES):
        off = _walk(getattr(value, name), t, off, keep)
    return off


def content_bytes(msg) -> tuple[bytes, int]:
    """(the bytes of ``serialize_message(msg)`` that carry a field, in order; the serialized length)."""
    from rosidl_parser import definition as d

    data = serialize_message(msg)
    keep: list = []
    end = _walk(msg, d.NamespacedType([], type(msg).__name__), 0, keep)
    assert end + 4 <= len(data), (end + 4, len(data))  # rclpy's length can include unused bytes at the end
    return data[:4] + bytes(data[4 + k] for k in keep), len(data)


def assert_same_wire(got: bytes, msg) -> None:
    """``got`` equals ``serialize_message(msg)`` in length and in every byte that carries a field."""
    from rosidl_parser import definition as d

    want, length = content_bytes(msg)
    assert len(got) == length
    keep: list = []
    _walk(msg, d.NamespacedType([], type(msg).__name__), 0, keep)
    assert got[:4] + bytes(got[4 + k] for k in keep) == want


def _names(rng, n):
    out = set()
    while len(out) < n:
        out.add("".join(rng.choice(list(NAME_CHARS), int(rng.integers(1, 24)))))
    return [str(x) for x in rng.permutation(sorted(out))]


def _values(rng, *shape):
    """Finite float64 values of many magnitudes and signs (zeros and subnormals included)."""
    v = rng.normal(size=shape) * 10.0 ** rng.integers(-300, 300, size=shape)
    v[rng.random(shape) < 0.05] = 0.0
    v[rng.random(shape) < 0.02] = 5e-324
    return v


def _stamp(rng):
    return int(rng.choice([0, 1, 2**31 * 10**9 - 1, int(rng.integers(0, 2**31 * 10**9))]))


def test_joint_state_bytes_equal_serialize_message():
    rng = np.random.default_rng(0)
    for i in range(N_RANDOM):
        n = int(rng.integers(0, 9))
        names = _names(rng, n)
        frame_id = "" if rng.random() < 0.5 else "".join(rng.choice(list(NAME_CHARS), int(rng.integers(1, 12))))
        effort = bool(rng.random() < 0.5)
        ser = wire.JointStateSerializer(names, frame_id=frame_id, effort=effort)
        for _ in range(3):  # the buffer is reused: every call carries its own numbers
            q, qd, eff = _values(rng, 3, n)
            stamp = _stamp(rng)
            got = ser(q, qd, stamp, eff if effort else None)
            msg = conv.arrays_to_joint_state(names, q, qd, eff if effort else None, stamp_ns=stamp, frame_id=frame_id)
            assert_same_wire(got, msg)


def test_joint_state_serializer_refuses_wrong_shapes_and_effort_mismatch():
    ser = wire.JointStateSerializer(["a", "b"])
    with pytest.raises(ValueError, match=r"position has shape \(3,\); expected \(2,\), one value per joint: a, b"):
        ser(np.zeros(3), np.zeros(2))
    with pytest.raises(ValueError, match="effort=True"):
        ser(np.zeros(2), np.zeros(2), 0, effort=np.zeros(2))
    with pytest.raises(ValueError, match="effort=True"):
        wire.JointStateSerializer(["a"], effort=True)(np.zeros(1), np.zeros(1), 0)
    # sequences are accepted too (converted like an array)
    assert_same_wire(ser([1.0, 2.0], (3.0, 4.0), 5), conv.arrays_to_joint_state(["a", "b"], [1, 2], [3, 4], stamp_ns=5))


def test_trajectory_bytes_equal_serialize_message():
    rng = np.random.default_rng(1)
    for i in range(N_RANDOM):
        d = int(rng.integers(0, 8))
        names = _names(rng, d)
        ser = wire.TrajectorySerializer(names)
        for n_points in rng.integers(0, 10, size=3):  # repeated counts use the cached template
            n_points = int(n_points)
            times = np.cumsum(rng.uniform(1e-9, 2.5, n_points))
            if n_points and rng.random() < 0.3:
                times -= times[0]  # a first point at time 0
            q, qd, qdd = _values(rng, 3, n_points, d)
            stamp = _stamp(rng)
            got = ser(times, q, qd, qdd, stamp_ns=stamp)
            assert_same_wire(got, conv.joint_trajectory(names, times, q, qd, qdd, stamp_ns=stamp))


def test_trajectory_serializer_refuses_bad_times():
    ser = wire.TrajectorySerializer(["a"])
    with pytest.raises(ValueError, match="strictly increasing"):
        ser(np.array([0.1, 0.1]), *np.zeros((3, 2, 1)))
    with pytest.raises(ValueError, match=">= 0"):
        ser(np.array([-0.1]), *np.zeros((3, 1, 1)))


def test_clock_bytes_equal_serialize_message():
    rng = np.random.default_rng(2)
    ser = wire.ClockSerializer()
    for _ in range(N_RANDOM):
        stamp = _stamp(rng)
        assert_same_wire(ser(stamp), Clock(clock=conv.ns_to_stamp(stamp)))


def test_command_reader_equals_deserialize_message():
    rng = np.random.default_rng(3)
    for i in range(N_RANDOM // 4):
        n = int(rng.integers(1, 9))
        robot = _names(rng, n)
        read = wire.CommandReader(robot, ", ".join(robot))
        for _ in range(4):  # a new layout (validated), then the same layout read in place
            perm = rng.permutation(n)
            frame_id = "" if rng.random() < 0.5 else "base"
            with_velocity, with_effort = bool(rng.random() < 0.8), bool(rng.random() < 0.5)
            for _ in range(2):
                q, qd, eff = _values(rng, 3, n)
                msg = conv.arrays_to_joint_state([robot[k] for k in perm], q[perm], qd[perm] if with_velocity else None,
                                                 eff if with_effort else None, stamp_ns=_stamp(rng), frame_id=frame_id)
                data = serialize_message(msg)
                ref = conv.joint_state_to_arrays(deserialize_message(data, JointState))
                want_q = conv.reorder_joints(ref.names, ref.position, robot)
                got_q, got_qd = read(data)
                np.testing.assert_array_equal(got_q, want_q)
                np.testing.assert_array_equal(got_q, q)
                if with_velocity:
                    np.testing.assert_array_equal(got_qd, conv.reorder_joints(ref.names, ref.velocity, robot))
                else:
                    assert got_qd is None, i


def test_command_reader_refuses_what_it_cannot_read():
    names = ["a", "b", "c"]
    read = wire.CommandReader(names, "[a, b, c]")
    read(serialize_message(conv.arrays_to_joint_state(names, np.zeros(3))))  # caches the layout
    bad = [(JointState(name=names, position=[0.0] * 3, velocity=[0.0] * 2), "2 velocity values"),
           (JointState(name=["a", "b", "d"], position=[0.0] * 3), "expected exactly the 3 joints"),
           (JointState(name=names, position=[0.0] * 2), "2 position values"),
           (JointState(name=names), "no positions")]
    for m, text in bad:  # the same names as the cached layout, other counts: refused too
        with pytest.raises(ValueError, match=text):
            read(serialize_message(m))
    with pytest.raises(ValueError, match="not a sensor_msgs/JointState"):
        read(serialize_message(Clock()))


def test_joint_state_serializer_matches_a_built_message():
    names = [f"joint_{i}" for i in range(1, 7)]
    ser = wire.JointStateSerializer(names)
    rng = np.random.default_rng(5)
    for _ in range(3):  # the same buffer is reused: every call carries its own numbers
        q, qd = rng.normal(size=6), rng.normal(size=6)
        m = deserialize_message(ser(q, qd, 1_700_000_000_123_456_789), JointState)
        assert list(m.name) == names and list(m.effort) == []
        np.testing.assert_array_equal(m.position, q)
        np.testing.assert_array_equal(m.velocity, qd)
        assert (m.header.stamp.sec, m.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    with pytest.raises(ValueError, match="effort=True"):
        ser(q, qd, 0, effort=np.zeros(6))  # this serializer carries no efforts


def test_trajectory_bytes_equal_the_built_message():
    """The JointTrajectory template writer gives the message conversions.joint_trajectory builds
    (every point count, stamps up to 2**31 s, times with ns resolution); bad times are refused."""
    from trajectory_msgs.msg import JointTrajectory

    names = [f"joint_{i}" for i in range(1, 7)]
    ser = wire.TrajectorySerializer(names)
    rng = np.random.default_rng(4)
    for n_points in (0, 1, 3, 6, 9, 3):  # the last one from the cached template
        times = np.cumsum(rng.uniform(1e-9, 2.5, n_points))
        q, qd, qdd = rng.normal(size=(3, n_points, 6))
        stamp = int(rng.integers(0, 2**31 * 10**9))
        got = deserialize_message(ser(times, q, qd, qdd, stamp_ns=stamp), JointTrajectory)
        assert got == conv.joint_trajectory(names, times, q, qd, qdd, stamp_ns=stamp), n_points
    with pytest.raises(ValueError, match="strictly increasing"):
        ser(np.array([0.1, 0.1]), *np.zeros((3, 2, 6)))
