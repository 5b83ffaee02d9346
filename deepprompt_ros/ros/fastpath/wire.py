"""Wire-level messages: serialized CDR bytes written and read without building rclpy messages.

The control-rate paths publish and take the same few message layouts hundreds of times a second:
a ``sensor_msgs/JointState`` command per control tick, JointTrajectory look-aheads,
``rosgraph_msgs/Clock`` and measured joint states per physics step. Building (or reading) such a
message field by field in Python costs a sizeable share of a 1 kHz period, and the thread doing
it holds the interpreter lock the control thread needs. Here the bytes are produced from a
template instead: a message with distinct sentinel numbers is serialized once with
``rclpy.serialization.serialize_message``, the offsets of the sentinels are found in its bytes,
and each call writes the current stamp and numbers there (rclpy publishers accept ``bytes``).
:class:`CommandReader` goes the other way for the one layout a consumer receives every tick.

CDR as rclpy writes it (little endian): a 4-byte encapsulation header (``00 01``), then the
fields in order, each aligned to its size relative to the end of that header; a string is a
uint32 length (terminating NUL included) then its bytes; a sequence is a uint32 count then its
elements. ``test/test_ros_fastpath_wire.py`` checks every class byte for byte against
``serialize_message`` (and ``deserialize_message`` for the reader) over random messages.
"""
from __future__ import annotations

import struct
from typing import Sequence

import numpy as np
from builtin_interfaces.msg import Time
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import JointState

from deepprompt_ros.ros import conversions as conv

__all__ = ["JointStateSerializer", "TrajectorySerializer", "ClockSerializer", "CommandReader"]

_CDR_LE = b"\x00\x01"  # encapsulation kind CDR_LE
_STAMP = struct.Struct("<iI")  # builtin_interfaces/Time: int32 sec, uint32 nanosec
_COUNT = struct.Struct("<I")
#: sentinel header.stamp of the templates (sec, nanosec): bytes that occur nowhere else in them
_SENTINEL_SEC, _SENTINEL_NSEC = 0x5A3C2E1F, 0x2B4D6F13


def _align(offset: int, size: int) -> int:
    """``offset`` (in the whole buffer) rounded up to a multiple of ``size`` after the 4-byte header."""
    return offset + (-(offset - 4)) % size


def _locate(data: bytes, fields, what: str) -> list[int]:
    """Offsets of the sentinel ``fields`` [(bytes, alignment), ...] in a serialized template, given
    in message order: each is the first occurrence after the previous field at an offset aligned
    like the field, and the only aligned occurrence before the end of the last field. (The bytes
    of neighbouring sentinels can form a pattern across their boundary, never at an aligned
    offset; rclpy's buffer can end with unused bytes that hold an earlier serialization.)"""
    found, start = [], 4
    for pattern, align in fields:
        i = data.find(pattern, start)
        while i >= 0 and (i - 4) % align:
            i = data.find(pattern, i + 1)
        if i < 0:
            raise ValueError(f"{what} template layout not recognised")
        found.append(i)
        start = i + len(pattern)
    content = data[:start]
    for (pattern, align), i in zip(fields, found):
        j = content.find(pattern)
        while j >= 0:
            if j != i and (j - 4) % align == 0:
                raise ValueError(f"{what} template layout not recognised")
            j = content.find(pattern, j + 1)
    return found


class JointStateSerializer:
    """``sensor_msgs/JointState`` bytes for fixed joint names (a per-tick command or a measured state).

    With fixed names the CDR bytes differ only in the stamp and the numbers, so a template is
    serialized once and those fields are overwritten in place (offsets found by serializing
    sentinel values). Where rclpy does not write little-endian CDR, each call builds and
    serializes the message instead.

    Parameters
    ----------
    names : sequence of str, length n
    frame_id : str
    effort : bool
        Also carry efforts (n,) — a measured state — instead of an empty effort field.
    """

    def __init__(self, names: Sequence[str], frame_id: str = "", effort: bool = False):
        n = len(names)
        self.names = tuple(str(x) for x in names)
        self.frame_id = frame_id
        sent_p = [1.0e300 + 1.0e285 * (i + 1) for i in range(n)]
        sent_v = [-1.0e300 - 1.0e285 * (i + 1) for i in range(n)]
        sent_e = [0.5e300 + 1.0e285 * (i + 1) for i in range(n)] if effort else []
        msg = JointState(name=list(self.names), position=sent_p, velocity=sent_v, effort=sent_e)
        msg.header.frame_id = frame_id
        msg.header.stamp = Time(sec=_SENTINEL_SEC, nanosec=_SENTINEL_NSEC)
        data = serialize_message(msg)
        self._with_effort = bool(effort)
        self._eff_view = None
        self._fallback = data[:2] != _CDR_LE  # not little-endian CDR: build messages instead
        self._template = np.frombuffer(data, dtype=np.uint8).copy()
        if not self._fallback:
            fields = [(np.int32(_SENTINEL_SEC).tobytes(), 4), (np.uint32(_SENTINEL_NSEC).tobytes(), 4)]
            if n:
                fields += [(np.float64(v[0]).tobytes(), 8) for v in ((sent_p, sent_v, sent_e) if effort else
                                                                      (sent_p, sent_v))]
            self._sec, self._nsec, *numbers = _locate(data, fields, "JointState")
            self._p, self._v, self._e = (numbers + [0, 0, 0])[:3]  # (no joints: empty views at 0)
        self._buf = self._template.copy()
        self._n = n
        if not self._fallback:
            # writable little-endian views of the numbers in the message buffer: each call
            # writes through them (no temporary arrays)
            b = self._buf
            self._pos_view = np.frombuffer(b, dtype="<f8", count=n, offset=self._p)
            self._vel_view = np.frombuffer(b, dtype="<f8", count=n, offset=self._v)
            if effort:
                self._eff_view = np.frombuffer(b, dtype="<f8", count=n, offset=self._e)
            self._sec_view = np.frombuffer(b, dtype="<i4", count=1, offset=self._sec)
            self._nsec_view = np.frombuffer(b, dtype="<u4", count=1, offset=self._nsec)

    def __call__(self, position, velocity, stamp_ns: int = 0, effort=None) -> bytes:
        """CDR bytes of a JointState with these positions / velocities (n,) and header.stamp (and the
        efforts (n,), required exactly when the serializer was made with ``effort=True``)."""
        if (effort is not None) != self._with_effort:
            raise ValueError("efforts are given exactly when the serializer was made with effort=True")
        if self._fallback:
            return serialize_message(conv.arrays_to_joint_state(self.names, position, velocity, effort,
                                                                stamp_ns=stamp_ns, frame_id=self.frame_id))
        pos, vel = self._pos_view, self._vel_view
        if type(position) is not np.ndarray or position.shape != pos.shape:
            self._check_shape("position", position)
        if type(velocity) is not np.ndarray or velocity.shape != vel.shape:
            self._check_shape("velocity", velocity)
        pos[:] = position
        vel[:] = velocity
        if effort is not None:
            if type(effort) is not np.ndarray or effort.shape != pos.shape:
                self._check_shape("effort", effort)
            self._eff_view[:] = effort
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        self._sec_view[0] = sec
        self._nsec_view[0] = nsec
        return self._buf.tobytes()

    def _check_shape(self, label: str, values) -> None:
        shape = np.shape(values)
        if shape != (self._n,):
            raise ValueError(f"{label} has shape {shape}; expected ({self._n},), one value per joint: "
                             f"{', '.join(self.names)}")


class TrajectorySerializer:
    """``trajectory_msgs/JointTrajectory`` bytes (positions, velocities, accelerations per point) for
    fixed joint names, equal to serializing :func:`~deepprompt_ros.ros.conversions.joint_trajectory`'s
    message.

    One template per number of points is serialized once with distinct sentinel numbers; each call
    writes the stamp, the numbers and the times_from_start into a copy.

    Parameters
    ----------
    names : sequence of str, length d
    """

    def __init__(self, names):
        self.names = [str(x) for x in names]
        self._templates: dict = {}

    def _template(self, n_points: int):
        from builtin_interfaces.msg import Duration
        from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

        d = len(self.names)
        values = 1.0e300 + 1.0e285 * np.arange(1, 3 * n_points * d + 1).reshape(n_points, 3, d)
        msg = JointTrajectory(joint_names=self.names)
        msg.header.stamp = Time(sec=_SENTINEL_SEC, nanosec=_SENTINEL_NSEC)
        msg.points = [JointTrajectoryPoint(positions=v[0].tolist(), velocities=v[1].tolist(),
                                           accelerations=v[2].tolist(),
                                           time_from_start=Duration(sec=0x3C000000 + i, nanosec=0x4D000000 + i))
                      for i, v in enumerate(values)]
        data = serialize_message(msg)
        if data[:2] != _CDR_LE:
            raise ValueError("JointTrajectory serialization is not little-endian CDR")

        # fields in message order: the stamp, then per point its numbers and its time_from_start
        fields = [(np.array([_SENTINEL_SEC, _SENTINEL_NSEC], "<u4").tobytes(), 4)]
        for i, v in enumerate(values):
            fields += [(np.float64(x).tobytes(), 8) for x in v.ravel()]
            fields.append((np.array([0x3C000000 + i, 0x4D000000 + i], "<u4").tobytes(), 4))
        found = np.array(_locate(data, fields, "JointTrajectory"), dtype=np.int64)
        is_time = np.array([a == 4 for _, a in fields])
        # every number is aligned to its size after the 4-byte encapsulation header: index the
        # buffer from there as float64 (numbers) and uint32 (stamp, times)
        f64, u32 = found[~is_time], found[is_time]
        return bytearray(data), (f64 - 4) // 8, (u32 - 4) // 4

    def __call__(self, times, q, qd, qdd, stamp_ns: int = 0) -> bytes:
        """times (P,) s, >= 0 and strictly increasing; q, qd, qdd (P, d); header.stamp in ns."""
        times = np.asarray(times, dtype=np.float64)
        if times.size and (times[0] < 0 or np.any(np.diff(times) <= 0)):
            raise ValueError(f"time_from_start must be >= 0 and strictly increasing; got {times.tolist()}")
        tpl = self._templates.get(times.size)
        if tpl is None:
            tpl = self._templates[times.size] = self._template(times.size)
        template, f64, u32 = tpl
        buf = bytearray(template)
        np.frombuffer(buf, "<f8", (len(buf) - 4) // 8, 4)[f64] = np.stack([q, qd, qdd], axis=1).ravel()
        ns = np.empty(times.size + 1, dtype=np.int64)
        ns[0], ns[1:] = stamp_ns, np.round(times * 1e9)
        stamps = np.stack([ns // 1_000_000_000, ns % 1_000_000_000], axis=1).astype("<u4")
        np.frombuffer(buf, "<u4", (len(buf) - 4) // 4, 4)[np.stack([u32, u32 + 1], axis=1)] = stamps
        return bytes(buf)


class ClockSerializer:
    """``rosgraph_msgs/Clock`` bytes for a stamp (a template with the time patched in)."""

    def __init__(self):
        from rosgraph_msgs.msg import Clock

        data = serialize_message(Clock(clock=Time(sec=_SENTINEL_SEC, nanosec=_SENTINEL_NSEC)))
        if data[:2] != _CDR_LE:
            raise ValueError("Clock serialization is not little-endian CDR")
        self._buf = bytearray(data)
        (self._stamp,) = _locate(data, [(_STAMP.pack(_SENTINEL_SEC, _SENTINEL_NSEC), 4)], "Clock")

    def __call__(self, stamp_ns: int) -> bytes:
        _STAMP.pack_into(self._buf, self._stamp, *divmod(stamp_ns, 1_000_000_000))
        return bytes(self._buf)


class CommandReader:
    """Serialized ``sensor_msgs/JointState`` joint command -> positions and velocities in the
    robot's joint order.

    The first message of a joint-name layout is deserialized and validated (names exactly the
    robot's joints, in any order; consistent array lengths); its bytes from the frame id to the
    end of the names are kept. A later message whose bytes agree there is read in place: only the
    counts and the numbers after the names are decoded (a streamer sends the same names every
    tick). Positions and velocities are checked against the limits by the simulation.

    Parameters
    ----------
    names : sequence of str
        The robot's joints, in its order.
    joints_text : str
        The joints for error messages.
    """

    def __init__(self, names, joints_text: str):
        self._names = tuple(names)
        self._joints_text = joints_text
        self._key = b""        # bytes 12 .. end of the names of the last valid layout
        self._order = None     # index array: robot joint k is message joint order[k]; None = same order

    def __call__(self, data: bytes) -> tuple[np.ndarray, np.ndarray | None]:
        """Returns (q, qd): arrays (n,), qd None when the message has no velocities.

        Raises
        ------
        ValueError
            Not a JointState, names that are not exactly the robot's joints, or array lengths that
            are neither the number of names nor (velocity) 0.
        """
        key = self._key
        if key and data.startswith(key, 12):
            try:
                return self._numbers(data, 12 + len(key))
            except (ValueError, struct.error):
                pass  # unexpected counts: the full path says what is wrong
        return self._validate(data)

    def _numbers(self, data: bytes, offset: int):
        n = len(self._names)
        out = []
        for field in range(2):  # position, velocity (effort is ignored)
            offset = _align(offset, 4)
            (count,) = _COUNT.unpack_from(data, offset)
            offset += 4
            if count != n and not (field == 1 and count == 0):
                raise ValueError("unexpected count")
            if count:
                offset = _align(offset, 8)
                values = np.frombuffer(data, dtype="<f8", count=count, offset=offset)
                offset += 8 * count
                out.append(values if self._order is None else values[self._order])
            else:
                out.append(None)
        return out[0], out[1]

    def _validate(self, data: bytes):
        try:
            msg = deserialize_message(data, JointState)
        except Exception as exc:
            raise ValueError(f"not a sensor_msgs/JointState ({type(exc).__name__}: {exc})") from None
        q, qd, order = conv.joint_command_to_arrays(msg, self._names, self._joints_text)
        # bytes from the frame id to the end of the names: the layout key
        offset = 12
        (length,) = _COUNT.unpack_from(data, offset)
        offset += 4 + length
        offset = _align(offset, 4)
        (count,) = _COUNT.unpack_from(data, offset)
        offset += 4
        for _ in range(count):
            offset = _align(offset, 4)
            (length,) = _COUNT.unpack_from(data, offset)
            offset += 4 + length
        self._key = bytes(data[12:offset])
        self._order = None if np.array_equal(order, np.arange(len(order))) else order
        return q, qd
