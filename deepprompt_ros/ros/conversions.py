"""The one module converting ROS messages <-> numpy arrays.

Every node goes through these functions, so units, orderings and error messages are the same
everywhere. Errors are ``ValueError`` whose message says what was wrong and what is expected;
nodes turn them into a ``success=false`` response or a throttled warning.

Conventions: float64 arrays; quaternions (x, y, z, w) as in ROS and PyBullet; images uint8
RGB of shape (H, W, 3); time stamps as ``builtin_interfaces/Time`` <-> integer nanoseconds or
float seconds.

Sections: time stamps, joint states, images, poses and points, low-dimensional contexts,
primitive server. Kept as one module (about 600 lines) on purpose: a reader finds every
message <-> array conversion, and the one wording of its errors, in one place.
"""
from __future__ import annotations

import array
from typing import NamedTuple, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion
from sensor_msgs.msg import Image, JointState

from deepprompt_ros.server.requests import ContextIn, ImageIn, ViaPointIn

__all__ = [
    # time stamps
    "stamp_to_ns", "ns_to_stamp", "stamp_to_sec", "sec_to_stamp",
    # joint states
    "JointStateArrays", "joint_state_to_arrays", "arrays_to_joint_state", "joint_command_to_arrays", "reorder_joints",
    # images
    "SUPPORTED_IMAGE_ENCODINGS", "image_to_array", "array_to_image",
    # poses and points
    "pose_to_arrays", "arrays_to_pose", "pose_stamped", "point_to_array",
    # contexts
    "CONTEXT_TYPES", "context_vector",
    # primitive server (deepprompt_msgs, trajectory_msgs)
    "sec_to_duration", "duration_to_sec", "via_points_from_msgs", "via_points_to_msgs", "image_fields",
    "contexts_from_msgs", "preview_to_msg", "PreviewArrays", "preview_from_msg", "primitive_info_to_msg",
    "samples_to_response", "samples_from_response", "joint_trajectory", "TrajectoryArrays",
    "joint_trajectory_to_arrays",
]


# ----------------------------------------------------------------------------------------------
# time stamps
# ----------------------------------------------------------------------------------------------
def stamp_to_ns(stamp: Time) -> int:
    """``builtin_interfaces/Time`` -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> Time:
    """Integer nanoseconds (>= 0) -> ``builtin_interfaces/Time``."""
    ns = int(ns)
    if ns < 0:
        raise ValueError(f"time stamp must be >= 0 ns; got {ns}")
    sec, nanosec = divmod(ns, 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def stamp_to_sec(stamp: Time) -> float:
    """``builtin_interfaces/Time`` -> float seconds (ns resolution is lost beyond ~2**53 ns)."""
    return int(stamp.sec) + int(stamp.nanosec) * 1e-9


def sec_to_stamp(t: float) -> Time:
    """Float seconds (finite, >= 0) -> ``builtin_interfaces/Time`` (rounded to the nanosecond)."""
    if not (np.isfinite(t) and t >= 0):
        raise ValueError(f"time stamp must be a finite number of seconds >= 0; got {t}")
    return ns_to_stamp(round(t * 1e9))


# ----------------------------------------------------------------------------------------------
# joint states
# ----------------------------------------------------------------------------------------------
class JointStateArrays(NamedTuple):
    """Contents of a ``sensor_msgs/JointState`` as arrays, in the message's joint order.

    Attributes
    ----------
    names : tuple of str, length n
    position : array, shape (n,)
    velocity : array, shape (n,), or None when the message has no velocities
    effort : array, shape (n,), or None when the message has no efforts
    stamp_ns : int
        ``header.stamp`` in nanoseconds (0 when unset).
    """

    names: tuple[str, ...]
    position: np.ndarray
    velocity: np.ndarray | None
    effort: np.ndarray | None
    stamp_ns: int


def joint_state_to_arrays(msg: JointState, *, require_position: bool = True) -> JointStateArrays:
    """``sensor_msgs/JointState`` -> :class:`JointStateArrays`.

    Raises
    ------
    ValueError
        Duplicate joint names, or position / velocity / effort arrays whose length is neither 0
        (absent) nor the number of names; with ``require_position``, an empty position array.
    """
    names = tuple(msg.name)
    n = len(names)
    if len(set(names)) != n:
        dup = sorted({x for x in names if names.count(x) > 1})
        raise ValueError(f"JointState has duplicate joint names {dup}; expected each joint once")
    out = []
    for field in ("position", "velocity", "effort"):
        values = getattr(msg, field)
        m = len(values)
        if m == 0:
            if field == "position" and require_position:
                raise ValueError(f"JointState has no positions for its {n} joints; expected {n} positions")
            out.append(None)
        elif m != n:
            raise ValueError(f"JointState has {m} {field} values for {n} joint names; expected {n} "
                             f"(one per name) or 0")
        else:
            out.append(np.asarray(values, dtype=np.float64))
    return JointStateArrays(names, out[0], out[1], out[2], stamp_to_ns(msg.header.stamp))


def arrays_to_joint_state(names: Sequence[str], position, velocity=None, effort=None, *,
                          stamp_ns: int = 0, frame_id: str = "") -> JointState:
    """Arrays -> ``sensor_msgs/JointState``.

    Parameters
    ----------
    names : sequence of str, length n
    position : array_like, shape (n,)
    velocity, effort : array_like, shape (n,), optional
        Left empty in the message when None.
    stamp_ns : int
        ``header.stamp`` in nanoseconds.
    """
    names = [str(x) for x in names]
    n = len(names)
    msg = JointState()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.name = names
    for field, values in (("position", position), ("velocity", velocity), ("effort", effort)):
        if values is None:
            continue
        arr = np.asarray(values, dtype=np.float64).reshape(-1)
        if arr.shape != (n,):
            raise ValueError(f"{field} has {arr.size} values for {n} joint names; expected {n}")
        setattr(msg, field, arr.tolist())
    return msg


def joint_command_to_arrays(msg: JointState, names: Sequence[str], joints_text: str):
    """A joint command (``sensor_msgs/JointState`` naming exactly the robot's joints, in any order)
    -> its positions and velocities in the robot's joint order.

    Parameters
    ----------
    msg : JointState
    names : sequence of str, length n
        The robot's joints, in its order.
    joints_text : str
        The joints for the error message.

    Returns
    -------
    q : array, shape (n,)
    qd : array, shape (n,), or None when the message has no velocities
    order : int array, shape (n,)
        Robot joint k is message joint ``order[k]``.

    Raises
    ------
    ValueError
        Array lengths that are neither the number of names nor (velocity, effort) 0 (see
        :func:`joint_state_to_arrays`), or names that are not exactly ``names``.
    """
    js = joint_state_to_arrays(msg)
    if len(js.names) != len(names) or set(js.names) != set(names):
        raise ValueError(f"joint command names {list(js.names)}; expected exactly the "
                         f"{len(names)} joints {joints_text} (any order)")
    order = np.array([js.names.index(w) for w in names])
    return js.position[order], (js.velocity[order] if js.velocity is not None else None), order


def reorder_joints(names: Sequence[str], values, wanted: Sequence[str], *, label: str = "JointState"):
    """Values given for ``names`` -> the same values in the order of ``wanted``.

    Parameters
    ----------
    names : sequence of str, length n
    values : array_like, shape (n,) or (..., n)
    wanted : sequence of str, length m
        The joints to return; each must be in ``names`` (extra names are dropped).

    Returns
    -------
    array, shape (m,) or (..., m)

    Raises
    ------
    ValueError
        A wanted joint is missing; the message lists the missing and the expected joints.
    """
    names = list(names)
    index = {nm: i for i, nm in enumerate(names)}
    missing = [w for w in wanted if w not in index]
    if missing:
        raise ValueError(f"{label} is missing joint(s) {missing}; it has {names}, expected all of "
                         f"{list(wanted)}")
    arr = np.asarray(values, dtype=np.float64)
    return arr[..., [index[w] for w in wanted]]


# ----------------------------------------------------------------------------------------------
# images
# ----------------------------------------------------------------------------------------------
#: Encodings read by :func:`image_to_array` (sensor_msgs/image_encodings names).
SUPPORTED_IMAGE_ENCODINGS = ("rgb8", "bgr8")


def image_to_array(msg: Image) -> np.ndarray:
    """``sensor_msgs/Image`` (rgb8 or bgr8) -> RGB array.

    Row padding (``step > 3 * width``) is removed; bgr8 is converted to RGB.

    Returns
    -------
    image : array of uint8, shape (height, width, 3), RGB

    Raises
    ------
    ValueError
        Unsupported encoding, big-endian flag on a multi-byte encoding, a step shorter than a
        row, or data of the wrong length; the message gives the numbers.
    """
    enc = msg.encoding
    if enc not in SUPPORTED_IMAGE_ENCODINGS:
        raise ValueError(f"image encoding '{enc}' is not supported; expected one of "
                         f"{', '.join(SUPPORTED_IMAGE_ENCODINGS)}")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h == 0 or w == 0:
        raise ValueError(f"image is empty ({w}x{h}); expected width and height >= 1")
    if step < 3 * w:
        raise ValueError(f"image step {step} is shorter than one row of {w} {enc} pixels "
                         f"({3 * w} bytes)")
    try:
        buf = np.frombuffer(msg.data, dtype=np.uint8)  # array.array('B') or bytes: no copy
    except TypeError:
        buf = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if buf.size != step * h:
        raise ValueError(f"image data has {buf.size} bytes; a {w}x{h} {enc} image with step {step} "
                         f"needs {step * h}")
    img = buf.reshape(h, step)[:, : 3 * w].reshape(h, w, 3)
    if enc == "bgr8":
        img = img[:, :, ::-1]
    return np.ascontiguousarray(img)


def array_to_image(image, *, encoding: str = "rgb8", stamp_ns: int = 0, frame_id: str = "") -> Image:
    """RGB array -> ``sensor_msgs/Image``.

    Parameters
    ----------
    image : array of uint8, shape (H, W, 3), RGB
    encoding : {"rgb8", "bgr8"}
        Encoding of the message (the array is always RGB; "bgr8" swaps the channels).
    """
    arr = np.asarray(image)
    if arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"image must be a uint8 array of shape (H, W, 3); got {arr.dtype} {arr.shape}")
    if encoding not in SUPPORTED_IMAGE_ENCODINGS:
        raise ValueError(f"image encoding '{encoding}' is not supported; expected one of "
                         f"{', '.join(SUPPORTED_IMAGE_ENCODINGS)}")
    if encoding == "bgr8":
        arr = arr[:, :, ::-1]
    h, w, _ = arr.shape
    msg = Image()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.height, msg.width = h, w
    msg.encoding = encoding
    msg.is_bigendian = 0
    msg.step = 3 * w
    data = array.array("B")
    data.frombytes(np.ascontiguousarray(arr).tobytes())  # array.array skips the per-byte check
    msg.data = data
    return msg


# ----------------------------------------------------------------------------------------------
# poses and points
# ----------------------------------------------------------------------------------------------
def pose_to_arrays(pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """``geometry_msgs/Pose`` -> (position, shape (3,); quaternion (x, y, z, w), shape (4,))."""
    p, o = pose.position, pose.orientation
    return np.array([p.x, p.y, p.z]), np.array([o.x, o.y, o.z, o.w])


def arrays_to_pose(position, orientation_xyzw=(0.0, 0.0, 0.0, 1.0)) -> Pose:
    """(position (3,), quaternion (x, y, z, w) (4,)) -> ``geometry_msgs/Pose``.

    Raises
    ------
    ValueError
        Wrong sizes or non-finite values.
    """
    p = np.asarray(position, dtype=np.float64).reshape(-1)
    q = np.asarray(orientation_xyzw, dtype=np.float64).reshape(-1)
    if p.shape != (3,) or q.shape != (4,) or not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        raise ValueError(f"pose needs 3 finite position values and 4 finite quaternion values "
                         f"(x, y, z, w); got position {p.tolist()}, quaternion {q.tolist()}")
    return Pose(position=Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))


def pose_stamped(position, orientation_xyzw=(0.0, 0.0, 0.0, 1.0), *, stamp_ns: int = 0,
                 frame_id: str = "world") -> PoseStamped:
    """Arrays -> ``geometry_msgs/PoseStamped`` (see :func:`arrays_to_pose`)."""
    msg = PoseStamped(pose=arrays_to_pose(position, orientation_xyzw))
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    return msg


def point_to_array(point: Point) -> np.ndarray:
    """``geometry_msgs/Point`` -> array, shape (3,)."""
    return np.array([point.x, point.y, point.z])


# ----------------------------------------------------------------------------------------------
# low-dimensional contexts (for recorded demonstrations and conditioning)
# ----------------------------------------------------------------------------------------------
#: Message types :func:`context_vector` turns into a low-dimensional context vector, and how.
CONTEXT_TYPES = {
    "geometry_msgs/msg/PoseStamped": "position (3) or, with pose_fields='pose', position + quaternion (7)",
    "geometry_msgs/msg/Pose": "as PoseStamped",
    "geometry_msgs/msg/PointStamped": "point (3)",
    "geometry_msgs/msg/Point": "point (3)",
    "geometry_msgs/msg/PoseArray": "the poses concatenated, 3 or 7 values each",
    "std_msgs/msg/Float64MultiArray": "data (any length)",
    "std_msgs/msg/Float32MultiArray": "data (any length)",
}


def _type_name(msg) -> str:
    mod = type(msg).__module__.split(".")  # e.g. geometry_msgs.msg._pose_stamped
    return f"{mod[0]}/msg/{type(msg).__name__}"


def context_vector(msg, *, pose_fields: str = "position") -> np.ndarray:
    """A message of one of :data:`CONTEXT_TYPES` -> context vector, shape (c,).

    Parameters
    ----------
    pose_fields : {"position", "pose"}
        For pose messages: the position only (3 values) or position + quaternion (x, y, z, w).

    Raises
    ------
    ValueError
        Unsupported message type (the message lists the supported ones), bad ``pose_fields``,
        an empty vector or non-finite values.
    """
    if pose_fields not in ("position", "pose"):
        raise ValueError(f"pose_fields must be 'position' or 'pose'; got {pose_fields!r}")
    name = _type_name(msg)

    def pose_vec(pose):
        p, q = pose_to_arrays(pose)
        return p if pose_fields == "position" else np.concatenate([p, q])

    if name == "geometry_msgs/msg/PoseStamped":
        vec = pose_vec(msg.pose)
    elif name == "geometry_msgs/msg/Pose":
        vec = pose_vec(msg)
    elif name == "geometry_msgs/msg/PointStamped":
        vec = point_to_array(msg.point)
    elif name == "geometry_msgs/msg/Point":
        vec = point_to_array(msg)
    elif name == "geometry_msgs/msg/PoseArray":
        vec = np.concatenate([pose_vec(p) for p in msg.poses]) if msg.poses else np.zeros(0)
    elif name in ("std_msgs/msg/Float64MultiArray", "std_msgs/msg/Float32MultiArray"):
        vec = np.asarray(msg.data, dtype=np.float64)
    else:
        raise ValueError(f"message type {name} cannot be turned into a context vector; supported: "
                         f"{', '.join(CONTEXT_TYPES)}")
    if vec.size == 0:
        raise ValueError(f"{name} message gives an empty context vector; expected at least one value")
    if not np.all(np.isfinite(vec)):
        raise ValueError(f"{name} message contains NaN or inf; expected finite context values")
    return vec


# ----------------------------------------------------------------------------------------------
# primitive server (deepprompt_msgs requests / responses, trajectory_msgs output)
# ----------------------------------------------------------------------------------------------
# The plain request / result types are those of deepprompt_ros.server.requests (numpy only).

def sec_to_duration(t: float):
    """Float seconds (finite, >= 0) -> ``builtin_interfaces/Duration`` (rounded to the ns)."""
    from builtin_interfaces.msg import Duration

    if not (np.isfinite(t) and t >= 0):
        raise ValueError(f"duration must be a finite number of seconds >= 0; got {t}")
    sec, nanosec = divmod(round(t * 1e9), 1_000_000_000)
    return Duration(sec=int(sec), nanosec=int(nanosec))


def duration_to_sec(d) -> float:
    """``builtin_interfaces/Duration`` -> float seconds."""
    return int(d.sec) + int(d.nanosec) * 1e-9


def via_points_from_msgs(msgs) -> list:
    """``deepprompt_msgs/ViaPoint[]`` -> list of ``server.requests.ViaPointIn`` (no validation here:
    the server checks phases, sizes and weights against the primitive)."""
    return [ViaPointIn(float(m.phase), np.asarray(m.positions, dtype=np.float64),
                       np.asarray(m.joint_mask, dtype=bool), bool(m.use_weight), float(m.weight))
            for m in msgs]


def via_points_to_msgs(phases, positions, joint_masks=None, weights=None) -> list:
    """Arrays -> ``deepprompt_msgs/ViaPoint[]`` (client side).

    Parameters
    ----------
    phases : array_like, shape (n,)
    positions : array_like, shape (n, d)
    joint_masks : array_like of bool, shape (n, d), optional (default: every joint constrained)
    weights : array_like, shape (n,), optional (default: ω = 1, use_weight false)
    """
    from deepprompt_msgs.msg import ViaPoint

    x = np.asarray(phases, dtype=np.float64).reshape(-1)
    y = np.asarray(positions, dtype=np.float64)
    if y.ndim != 2 or y.shape[0] != x.size:
        raise ValueError(f"positions must have shape ({x.size}, d), one row per phase; got {y.shape}")
    out = []
    for i in range(x.size):
        m = ViaPoint(phase=float(x[i]), positions=y[i].tolist())
        if joint_masks is not None:
            m.joint_mask = [bool(v) for v in np.asarray(joint_masks, dtype=bool)[i]]
        if weights is not None:
            m.use_weight, m.weight = True, float(np.asarray(weights, dtype=np.float64).reshape(-1)[i])
        out.append(m)
    return out


def image_fields(msg: Image):
    """``sensor_msgs/Image`` -> ``server.requests.ImageIn`` (raw bytes, no copy; the server checks
    encoding and size against the primitive)."""
    try:
        buf = np.frombuffer(msg.data, dtype=np.uint8)
    except TypeError:
        buf = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    return ImageIn(int(msg.height), int(msg.width), str(msg.encoding), int(msg.step), buf)


def contexts_from_msgs(msgs) -> list:
    """``deepprompt_msgs/Context[]`` -> list of ``server.requests.ContextIn``."""
    return [ContextIn(str(m.modality), np.asarray(m.values, dtype=np.float64),
                      tuple(image_fields(im) for im in m.images), bool(m.use_weight), float(m.weight))
            for m in msgs]


def _float64s(values) -> array.array:
    """A ``float64[]`` field's value, row-major: array.array('d') is taken as it is, where a list
    is checked value by value in Python (most of the time of building a preview message)."""
    out = array.array("d")
    out.frombytes(np.ascontiguousarray(values, dtype=np.float64).tobytes())
    return out


def preview_to_msg(preview):
    """``server.requests.Preview`` (phases (T,), mean/std (T, d)) -> ``deepprompt_msgs/TrajectoryPreview``
    (row-major T x d)."""
    from deepprompt_msgs.msg import TrajectoryPreview

    mean = np.asarray(preview.mean, dtype=np.float64)
    t, d = mean.shape
    return TrajectoryPreview(joint_names=list(preview.joint_names), phases=_float64s(preview.phases),
                             mean=_float64s(mean), std=_float64s(preview.std), n_points=t, n_joints=d)


class PreviewArrays(NamedTuple):
    """A ``TrajectoryPreview`` as arrays: phases (T,), mean and std (T, d)."""

    joint_names: tuple[str, ...]
    phases: np.ndarray
    mean: np.ndarray
    std: np.ndarray


def preview_from_msg(msg) -> PreviewArrays:
    """``deepprompt_msgs/TrajectoryPreview`` -> :class:`PreviewArrays` (ValueError on bad sizes)."""
    t, d = int(msg.n_points), int(msg.n_joints)
    x = np.asarray(msg.phases, dtype=np.float64)
    mean = np.asarray(msg.mean, dtype=np.float64)
    std = np.asarray(msg.std, dtype=np.float64)
    if x.size != t or mean.size != t * d or std.size != t * d or len(msg.joint_names) != d:
        raise ValueError(f"TrajectoryPreview sizes do not match n_points={t}, n_joints={d}: "
                         f"{x.size} phases, {mean.size} mean and {std.size} std values, "
                         f"{len(msg.joint_names)} joint names")
    return PreviewArrays(tuple(msg.joint_names), x, mean.reshape(t, d), std.reshape(t, d))


def primitive_info_to_msg(desc):
    """``server.requests.PrimitiveDescription`` -> ``deepprompt_msgs/PrimitiveInfo``."""
    from deepprompt_msgs.msg import PrimitiveInfo

    return PrimitiveInfo(
        name=desc.name, joint_names=list(desc.joint_names),
        position_lower=np.asarray(desc.position_lower, dtype=np.float64).tolist(),
        position_upper=np.asarray(desc.position_upper, dtype=np.float64).tolist(),
        phase_type=desc.phase_type, context_modalities=list(desc.context_modalities),
        context_dims=[int(v) for v in desc.context_dims], accepts_images=bool(desc.accepts_images),
        image_height=int(desc.image_height), image_width=int(desc.image_width),
        image_encoding=desc.image_encoding, latent_dim=int(desc.latent_dim), description=desc.description)


def samples_to_response(result, response):
    """Fill a ``Sample.Response`` from ``server.requests.SampleResult`` (samples (S, T, d), row-major)."""
    s = np.asarray(result.samples, dtype=np.float64)
    response.joint_names = list(result.joint_names)
    response.phases = np.asarray(result.phases, dtype=np.float64).tolist()
    response.samples = s.reshape(-1).tolist()
    response.n_samples, response.n_points, response.n_joints = (int(v) for v in s.shape)
    return response


def samples_from_response(response) -> np.ndarray:
    """``Sample.Response`` -> samples, array shape (S, T, d) (ValueError on bad sizes)."""
    s, t, d = int(response.n_samples), int(response.n_points), int(response.n_joints)
    arr = np.asarray(response.samples, dtype=np.float64)
    if arr.size != s * t * d:
        raise ValueError(f"Sample response has {arr.size} values; n_samples x n_points x n_joints = {s * t * d}")
    return arr.reshape(s, t, d)


def joint_trajectory(joint_names: Sequence[str], times, q, qd, qdd, *, stamp_ns: int = 0):
    """Arrays -> ``trajectory_msgs/JointTrajectory`` with positions, velocities and accelerations.

    Parameters
    ----------
    times : array_like, shape (P,)
        time_from_start of each point (s), strictly increasing, >= 0.
    q, qd, qdd : array_like, shape (P, d)
    stamp_ns : int
        header.stamp (0 = start when received, the JointTrajectoryController convention).
    """
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    t = np.asarray(times, dtype=np.float64).reshape(-1)
    arrays = [np.asarray(a, dtype=np.float64) for a in (q, qd, qdd)]
    d = len(joint_names)
    for name, a in zip(("q", "qd", "qdd"), arrays):
        if a.shape != (t.size, d):
            raise ValueError(f"{name} has shape {a.shape}; expected ({t.size}, {d}): one row per time, "
                             "one column per joint")
    if np.any(np.diff(t) <= 0) or (t.size and t[0] < 0):
        raise ValueError(f"time_from_start must be >= 0 and strictly increasing; got {t.tolist()}")
    msg = JointTrajectory()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.joint_names = [str(n) for n in joint_names]
    msg.points = [JointTrajectoryPoint(positions=arrays[0][i].tolist(), velocities=arrays[1][i].tolist(),
                                       accelerations=arrays[2][i].tolist(), time_from_start=sec_to_duration(t[i]))
                  for i in range(t.size)]
    return msg


class TrajectoryArrays(NamedTuple):
    """A ``JointTrajectory`` as arrays: times (P,) s; q, qd, qdd (P, d) (qd/qdd None if absent)."""

    joint_names: tuple[str, ...]
    stamp_ns: int
    times: np.ndarray
    q: np.ndarray
    qd: np.ndarray | None
    qdd: np.ndarray | None


def joint_trajectory_to_arrays(msg) -> TrajectoryArrays:
    """``trajectory_msgs/JointTrajectory`` -> :class:`TrajectoryArrays` (ValueError on ragged points)."""
    d = len(msg.joint_names)
    pts = msg.points
    t = np.array([duration_to_sec(p.time_from_start) for p in pts])
    out = []
    for field in ("positions", "velocities", "accelerations"):
        lens = {len(getattr(p, field)) for p in pts}
        if lens <= {0} and field != "positions":
            out.append(None)
            continue
        if lens != {d}:
            raise ValueError(f"JointTrajectory point {field} have lengths {sorted(lens)}; expected {d}")
        out.append(np.array([np.asarray(getattr(p, field), dtype=np.float64) for p in pts]).reshape(len(pts), d))
    return TrajectoryArrays(tuple(msg.joint_names), stamp_to_ns(msg.header.stamp), t, *out)
