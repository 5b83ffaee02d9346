"""Recording demonstrations: sample buffering and crash-safe output files (no ROS needed).

A recording produces two outputs:

* the **demonstration**, one ``.npz`` file in the dataset format of
  :mod:`deepprompt_ros.data.dataset` (joint positions with time stamps, low-dimensional contexts,
  a few downsampled images), built by :class:`DemoBuffer` and written atomically by
  :func:`~deepprompt_ros.data.dataset.save_demo`;
* the **raw messages**, a rosbag2 bag folder with MCAP storage written by :class:`BagWriter`::

      <bag_directory>/<name>/
          metadata.yaml        rosbag2 metadata (format version 9, ROS 2 Jazzy)
          <name>_0.mcap        MCAP, profile "ros2": schemas "ros2msg", messages "cdr"

  ``ros2 bag info/play <bag_directory>/<name>`` read it, and so does any MCAP reader.
  While recording, the folder is ``<bag_directory>/.<name>.<pid>.<ns>.part``; it is renamed to
  its final name only after the MCAP summary and ``metadata.yaml`` are written and synced, so
  a crash leaves finished bags untouched and at most one hidden ``.part`` folder (whose MCAP
  file, without summary, most MCAP readers can still scan).

The MCAP schemas are the ROS 2 ``.msg`` definitions with their dependencies, read from the
``share/<package>/msg/`` folders of the installed interface packages
(:func:`message_definition`), concatenated as rosbag2 does: the top-level definition, then for
each nested type a line of 80 ``=``, a line ``MSG: <package>/<Type>`` and its definition.
"""
from __future__ import annotations

import dataclasses
import datetime
import os
import pathlib
import re
import shutil
import sys
import time
from typing import NamedTuple, Sequence

import numpy as np
import yaml

from deepprompt_ros.data.demonstration import Demonstration, demo_from_arrays

__all__ = [
    "RecordingError",
    "message_definition",
    "qos_profile_yaml",
    "BagWriter",
    "resize_image",
    "ImageKeeper",
    "RecordingStats",
    "DemoBuffer",
    "validate_demo_name",
    "default_demo_name",
    "parse_context_spec",
    "check_writable_directory",
]

#: rosbag2 metadata format version written to metadata.yaml (the version of ROS 2 Jazzy).
ROSBAG2_METADATA_VERSION = 9

_PRIMITIVES = frozenset({
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
    "uint32", "int64", "uint64", "string", "wstring",
})
_DEMO_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,99}$")


class RecordingError(ValueError):
    """A recording request or file operation failed; the message says what and what is expected."""


# ----------------------------------------------------------------------------------------------
# message definitions (MCAP "ros2msg" schemas)
# ----------------------------------------------------------------------------------------------
def _default_search_paths() -> list[pathlib.Path]:
    paths = [pathlib.Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    paths.append(pathlib.Path(sys.prefix))
    out = []
    for p in paths:
        if p not in out:
            out.append(p)
    return out


def _split_type(type_name: str, current_package: str | None = None) -> tuple[str, str]:
    """'pkg/msg/Type', 'pkg/Type' or (inside package ``current_package``) 'Type' -> (pkg, Type)."""
    parts = type_name.split("/")
    if len(parts) == 3 and parts[1] == "msg":
        return parts[0], parts[2]
    if len(parts) == 2:
        return parts[0], parts[1]
    if len(parts) == 1 and current_package:
        if parts[0] == "Header":  # legacy short form of std_msgs/Header
            return "std_msgs", "Header"
        return current_package, parts[0]
    raise RecordingError(f"message type '{type_name}' is not of the form <package>/msg/<Type>")


def _msg_file(package: str, name: str, search_paths: Sequence[pathlib.Path]) -> pathlib.Path:
    for prefix in search_paths:
        f = pathlib.Path(prefix) / "share" / package / "msg" / f"{name}.msg"
        if f.is_file():
            return f
    raise RecordingError(
        f"no message definition for {package}/msg/{name}: looked for share/{package}/msg/{name}.msg "
        f"under {[str(p) for p in search_paths]}; install the interface package or add its prefix "
        f"to AMENT_PREFIX_PATH")


def _field_types(text: str) -> list[str]:
    """Non-primitive field types named in a .msg text, in order of appearance."""
    out = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        tok = line.split()[0]
        base = re.sub(r"\[[^\]]*\]$", "", tok).split("<=")[0]
        if base not in _PRIMITIVES:
            out.append(base)
    return out


def message_definition(type_name: str, search_paths: Sequence[str | os.PathLike] | None = None) -> str:
    """Full ROS 2 message definition (MCAP schema encoding ``ros2msg``) of a message type.

    Parameters
    ----------
    type_name : str
        ``"<package>/msg/<Type>"``, e.g. ``"sensor_msgs/msg/JointState"``.
    search_paths : sequence of path, optional
        Install prefixes holding ``share/<package>/msg/<Type>.msg``; default: the entries of
        ``AMENT_PREFIX_PATH`` then ``sys.prefix`` (a venv with the ROS wheels).

    Returns
    -------
    str
        The type's ``.msg`` text followed, for every nested type (depth first, each once), by
        ``"=" * 80``, ``MSG: <package>/<Type>`` and that type's ``.msg`` text.

    Raises
    ------
    RecordingError
        A definition file was not found (the message names it and the folders searched).
    """
    paths = _default_search_paths() if search_paths is None else [pathlib.Path(p) for p in search_paths]
    pkg, name = _split_type(type_name)
    root = _msg_file(pkg, name, paths).read_text()
    parts = [root.rstrip("\n")]
    seen = {(pkg, name)}
    stack = [(pkg, t) for t in reversed(_field_types(root))]
    while stack:
        cur_pkg, t = stack.pop()
        dep = _split_type(t, cur_pkg)
        if dep in seen:
            continue
        seen.add(dep)
        text = _msg_file(dep[0], dep[1], paths).read_text()
        parts.append("=" * 80 + f"\nMSG: {dep[0]}/{dep[1]}\n" + text.rstrip("\n"))
        stack.extend((dep[0], x) for x in reversed(_field_types(text)))
    return "\n".join(parts) + "\n"


def qos_profile_yaml(*, reliability: str = "reliable", durability: str = "volatile",
                     depth: int = 10) -> str:
    """rosbag2 (Jazzy) ``offered_qos_profiles`` text for one publisher with this QoS.

    Durations of 0 mean "not set" (the RMW default, infinite).
    """
    if reliability not in ("reliable", "best_effort"):
        raise RecordingError(f"reliability must be 'reliable' or 'best_effort'; got {reliability!r}")
    if durability not in ("volatile", "transient_local"):
        raise RecordingError(f"durability must be 'volatile' or 'transient_local'; got {durability!r}")
    def zero():  # separate dicts: a shared one would be written as a YAML anchor
        return {"sec": 0, "nsec": 0}

    profile = {"history": "keep_last", "depth": int(depth), "reliability": reliability,
               "durability": durability, "deadline": zero(), "lifespan": zero(),
               "liveliness": "automatic", "liveliness_lease_duration": zero(),
               "avoid_ros_namespace_conventions": False}
    return yaml.safe_dump([profile], sort_keys=False)


# ----------------------------------------------------------------------------------------------
# rosbag2 MCAP writer
# ----------------------------------------------------------------------------------------------
@dataclasses.dataclass
class _Topic:
    name: str
    type: str
    channel_id: int
    qos: str
    count: int = 0


def _fsync_dir(path: pathlib.Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class BagWriter:
    """Write raw (CDR-serialized) ROS 2 messages into a rosbag2 bag folder with MCAP storage.

    The folder is written under a hidden temporary name and renamed by :meth:`close` (see the
    module docstring). Not thread-safe: call it from one thread.

    Parameters
    ----------
    directory : path
        Where the bag folder ``<name>`` is created (created if missing).
    name : str
        Bag name (see :func:`validate_demo_name`); ``directory/name`` must not exist.
    compression : {"zstd", "lz4", "none"}
        MCAP chunk compression (rosbag2 reads all three).
    chunk_size : int
        Bytes per MCAP chunk: the most a crash can lose of an unfinished bag.
    search_paths : sequence of path, optional
        Passed to :func:`message_definition`.

    Raises
    ------
    RecordingError
        Invalid name, existing bag, or the folder cannot be created.
    """

    def __init__(self, directory: str | os.PathLike, name: str, *, compression: str = "zstd",
                 chunk_size: int = 256 * 1024, search_paths: Sequence[str | os.PathLike] | None = None):
        from mcap.writer import CompressionType, Writer

        validate_demo_name(name)
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
        if compression not in comp:
            raise RecordingError(f"compression must be one of {sorted(comp)}; got {compression!r}")
        self.directory = pathlib.Path(directory)
        self.name = name
        self.final_dir = self.directory / name
        if self.final_dir.exists():
            raise RecordingError(f"bag '{self.final_dir}' exists already; choose another name")
        self.tmp_dir = self.directory / f".{name}.{os.getpid()}.{time.time_ns()}.part"
        self.file_name = f"{name}_0.mcap"
        self._search_paths = search_paths
        try:
            self.tmp_dir.mkdir(parents=True)
            self._file = open(self.tmp_dir / self.file_name, "wb")
        except OSError as exc:
            raise RecordingError(f"cannot create the bag folder in '{self.directory}': {exc}") from exc
        self._writer = Writer(self._file, chunk_size=int(chunk_size), compression=comp[compression])
        self._writer.start(profile="ros2", library="deepprompt_ros")
        self._compression = compression
        self._schemas: dict[str, int] = {}
        self._topics: dict[str, _Topic] = {}
        self._first_ns: int | None = None
        self._last_ns: int | None = None
        self._count = 0
        self._closed = False

    @property
    def message_count(self) -> int:
        return self._count

    @property
    def topics(self) -> dict[str, tuple[str, int]]:
        """topic -> (type, message count)."""
        return {t.name: (t.type, t.count) for t in self._topics.values()}

    def add_topic(self, topic: str, type_name: str, *, offered_qos_profiles: str = "") -> None:
        """Declare a topic (a channel) before writing its messages; idempotent for the same type.

        Parameters
        ----------
        topic : str
            Fully qualified topic name, e.g. ``"/joint_states"``.
        type_name : str
            ``"<package>/msg/<Type>"``.
        offered_qos_profiles : str
            QoS of the publisher, see :func:`qos_profile_yaml`.
        """
        self._check_open()
        if topic in self._topics:
            if self._topics[topic].type != type_name:
                raise RecordingError(f"topic '{topic}' was added with type {self._topics[topic].type}; "
                                     f"got {type_name}")
            return
        if type_name not in self._schemas:
            text = message_definition(type_name, self._search_paths)
            self._schemas[type_name] = self._writer.register_schema(type_name, "ros2msg", text.encode())
        cid = self._writer.register_channel(
            topic, "cdr", self._schemas[type_name],
            {"offered_qos_profiles": offered_qos_profiles, "topic_type_hash": ""})
        self._topics[topic] = _Topic(topic, type_name, cid, offered_qos_profiles)

    def write(self, topic: str, data: bytes, log_time_ns: int, publish_time_ns: int | None = None) -> None:
        """Append one serialized message of a declared topic.

        Parameters
        ----------
        data : bytes
            CDR bytes as received from the middleware.
        log_time_ns : int
            Receive time (ns since the epoch); rosbag2 orders and plays messages by it.
        publish_time_ns : int, optional
            Send time; default ``log_time_ns``.
        """
        self._check_open()
        t = self._topics.get(topic)
        if t is None:
            raise RecordingError(f"topic '{topic}' was not added to bag '{self.name}'; call add_topic first")
        log_time_ns = int(log_time_ns)
        self._writer.add_message(t.channel_id, log_time_ns, bytes(data),
                                 log_time_ns if publish_time_ns is None else int(publish_time_ns),
                                 sequence=t.count)
        t.count += 1
        self._count += 1
        self._first_ns = log_time_ns if self._first_ns is None else min(self._first_ns, log_time_ns)
        self._last_ns = log_time_ns if self._last_ns is None else max(self._last_ns, log_time_ns)

    def metadata(self) -> dict:
        """rosbag2 ``metadata.yaml`` contents (format version 9) for what has been written."""
        start = self._first_ns or 0
        duration = (self._last_ns - self._first_ns) if self._first_ns is not None else 0
        topics = [{"topic_metadata": {"name": t.name, "type": t.type, "serialization_format": "cdr",
                                      "offered_qos_profiles": t.qos, "type_description_hash": ""},
                   "message_count": t.count} for t in self._topics.values()]
        return {"rosbag2_bagfile_information": {
            "version": ROSBAG2_METADATA_VERSION,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": self._count,
            "topics_with_message_count": topics,
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [self.file_name],
            "files": [{"path": self.file_name, "starting_time": {"nanoseconds_since_epoch": start},
                       "duration": {"nanoseconds": duration}, "message_count": self._count}],
            "custom_data": {"recorder": "deepprompt_ros demo_recorder",
                            "mcap_chunk_compression": self._compression},
            "ros_distro": "jazzy",
        }}

    def close(self) -> pathlib.Path:
        """Finish the MCAP file, write metadata.yaml, sync, rename the folder to its final name.

        Returns
        -------
        pathlib.Path
            The final ``.mcap`` file, ``<directory>/<name>/<name>_0.mcap``.

        Raises
        ------
        RecordingError
            The files could not be written or renamed (the temporary folder is left in place).
        """
        self._check_open()
        self._closed = True
        try:
            self._writer.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
            meta = self.tmp_dir / "metadata.yaml"
            with open(meta, "w") as f:
                yaml.safe_dump(self.metadata(), f, sort_keys=False)
                f.flush()
                os.fsync(f.fileno())
            _fsync_dir(self.tmp_dir)
            if self.final_dir.exists():
                raise RecordingError(f"bag '{self.final_dir}' appeared while recording; the recording "
                                     f"stays in '{self.tmp_dir}'")
            os.rename(self.tmp_dir, self.final_dir)
            _fsync_dir(self.directory)
        except OSError as exc:
            raise RecordingError(f"could not write bag '{self.final_dir}': {exc}; the recording stays "
                                 f"in '{self.tmp_dir}'") from exc
        return self.final_dir / self.file_name

    def abort(self) -> None:
        """Drop the bag: close and delete the temporary folder (idempotent)."""
        if not self._closed:
            self._closed = True
            try:
                self._file.close()
            except OSError:
                pass
        shutil.rmtree(self.tmp_dir, ignore_errors=True)

    def _check_open(self) -> None:
        if self._closed:
            raise RecordingError(f"bag '{self.name}' is closed")


# ----------------------------------------------------------------------------------------------
# images
# ----------------------------------------------------------------------------------------------
def _area_weights(n_in: int, n_out: int) -> np.ndarray:
    """Matrix (n_out, n_in): output pixel i averages input interval [i, i+1) * n_in / n_out."""
    edges = np.arange(n_out + 1) * (n_in / n_out)
    lo, hi = edges[:-1, None], edges[1:, None]
    px = np.arange(n_in)[None, :]
    overlap = np.clip(np.minimum(hi, px + 1) - np.maximum(lo, px), 0.0, None)
    return overlap / overlap.sum(axis=1, keepdims=True)


def resize_image(image, height: int, width: int) -> np.ndarray:
    """Resize an RGB image by area averaging (each output pixel is the mean of the input area it
    covers; for enlargement this is a nearest / linear mix).

    Parameters
    ----------
    image : array of uint8, shape (H, W, 3)
    height, width : int
        Output size (>= 1).

    Returns
    -------
    array of uint8, shape (height, width, 3)
    """
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise RecordingError(f"image must be uint8 with shape (H, W, 3); got {img.dtype} {img.shape}")
    height, width = int(height), int(width)
    if height < 1 or width < 1:
        raise RecordingError(f"image size must be >= 1 pixel per side; got {width}x{height}")
    if img.shape[:2] == (height, width):
        return img.copy()
    wy = _area_weights(img.shape[0], height).astype(np.float32)
    wx = _area_weights(img.shape[1], width).astype(np.float32)
    out = np.einsum("ih,hwc,jw->ijc", wy, img.astype(np.float32), wx, optimize=True)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


class ImageKeeper:
    """Keep a bounded, roughly evenly spaced set of downsampled images of a recording.

    Images arrive at the camera rate for an unknown duration. Each is resized on arrival; when
    ``capacity`` images are held, every other one is dropped (the rest stay evenly spaced).
    :meth:`selected` returns ``max_images`` of them evenly spread over the recording.

    Parameters
    ----------
    max_images : int
        Images per demonstration (>= 1).
    height, width : int
        Stored image size.
    """

    def __init__(self, max_images: int, height: int, width: int):
        if int(max_images) < 1:
            raise RecordingError(f"max_images must be >= 1; got {max_images}")
        self.max_images = int(max_images)
        self.height, self.width = int(height), int(width)
        if self.height < 1 or self.width < 1:
            raise RecordingError(f"image size must be >= 1 pixel per side; got {width}x{height}")
        self.capacity = max(4 * self.max_images, 16)
        self._images: list[np.ndarray] = []
        self._stride = 1  # keep one of every `_stride` arriving images
        self._seen = 0

    def __len__(self) -> int:
        return len(self._images)

    def add(self, image) -> None:
        """Offer one RGB uint8 image, shape (H, W, 3), of any size."""
        self._seen += 1
        if (self._seen - 1) % self._stride:
            return
        self._images.append(resize_image(image, self.height, self.width))
        if len(self._images) >= self.capacity:
            self._images = self._images[::2]
            self._stride *= 2

    def selected(self) -> np.ndarray | None:
        """Up to ``max_images`` images evenly spread over the recording, shape (n, H, W, 3) uint8,
        or None when no image arrived."""
        if not self._images:
            return None
        n = len(self._images)
        idx = np.unique(np.rint(np.linspace(0, n - 1, min(self.max_images, n))).astype(int))
        return np.stack([self._images[i] for i in idx])


# ----------------------------------------------------------------------------------------------
# demonstration buffer
# ----------------------------------------------------------------------------------------------
class RecordingStats(NamedTuple):
    """Counts of one recording, for logs and service responses.

    Attributes
    ----------
    n_samples : int
        Joint samples kept.
    duration : float
        Time between the first and the last kept sample (s).
    missing_joints : int
        Joint messages dropped because they lacked one of the recorded joints.
    not_increasing : int
        Joint messages dropped because their time stamp was not after the previous one.
    non_finite : int
        Joint messages dropped because of NaN / inf positions.
    n_images : int
        Images held (before the final selection).
    contexts : tuple of str
        Context names with an observation.
    """

    n_samples: int
    duration: float
    missing_joints: int
    not_increasing: int
    non_finite: int
    n_images: int
    contexts: tuple[str, ...]


class DemoBuffer:
    """Collect the samples of one demonstration as they arrive, then build it.

    Parameters
    ----------
    name : str
        Demonstration name (see :func:`validate_demo_name`).
    joint_names : sequence of str, optional
        The joints to keep, in this order. Default: those of the first joint sample, in its order.
    max_images, image_height, image_width : int
        See :class:`ImageKeeper`.
    phase_type : {"linear", "rhythmic"}
    """

    def __init__(self, name: str, joint_names: Sequence[str] | None = None, *, max_images: int = 4,
                 image_height: int = 64, image_width: int = 64, phase_type: str = "linear"):
        validate_demo_name(name)
        self.name = name
        self.joint_names = None if not joint_names else tuple(str(j) for j in joint_names)
        if self.joint_names is not None and len(set(self.joint_names)) != len(self.joint_names):
            raise RecordingError(f"joint_names has duplicates: {list(self.joint_names)}")
        self.phase_type = phase_type
        self._t: list[int] = []
        self._q: list[np.ndarray] = []
        self._index_cache: dict[tuple[str, ...], np.ndarray | None] = {}
        self._missing = self._not_increasing = self._non_finite = 0
        self._contexts: dict[str, np.ndarray] = {}
        self.images = ImageKeeper(max_images, image_height, image_width)

    # -- input ----------------------------------------------------------------------------------
    def _index(self, names: tuple[str, ...]) -> np.ndarray | None:
        idx = self._index_cache.get(names, False)
        if idx is False:
            pos = {n: i for i, n in enumerate(names)}
            idx = (np.array([pos[j] for j in self.joint_names])
                   if all(j in pos for j in self.joint_names) else None)
            self._index_cache[names] = idx
        return idx

    def add_joint_state(self, t_ns: int, names: Sequence[str], positions) -> bool:
        """Add one joint sample.

        Parameters
        ----------
        t_ns : int
            Time stamp (ns); must be after the previous kept sample.
        names : sequence of str, length m
        positions : array_like, shape (m,)

        Returns
        -------
        bool
            Whether the sample was kept (dropped: a recorded joint missing, time not increasing,
            non-finite values; each counted in :meth:`stats`).
        """
        names = tuple(names)
        if self.joint_names is None:
            self.joint_names = names
        idx = self._index(names)
        if idx is None:
            self._missing += 1
            return False
        q = np.asarray(positions, dtype=np.float64)[idx]
        if not np.all(np.isfinite(q)):
            self._non_finite += 1
            return False
        t_ns = int(t_ns)
        if self._t and t_ns <= self._t[-1]:
            self._not_increasing += 1
            return False
        self._t.append(t_ns)
        self._q.append(q)
        return True

    def has_context(self, name: str) -> bool:
        return name in self._contexts

    def add_context(self, name: str, vector) -> bool:
        """Set context ``name`` (shape (c,)) if it has none yet; returns whether it was set.

        The first observation is the demonstration's context: the scene as the demonstration
        starts.
        """
        if name in self._contexts:
            return False
        v = np.asarray(vector, dtype=np.float64).reshape(-1)
        if v.size == 0 or not np.all(np.isfinite(v)):
            raise RecordingError(f"context '{name}' must be a non-empty finite vector; got {v}")
        self._contexts[name] = v
        return True

    def add_image(self, image) -> None:
        """Offer one RGB image (uint8, (H, W, 3)); see :class:`ImageKeeper`."""
        self.images.add(image)

    # -- output ---------------------------------------------------------------------------------
    @property
    def n_samples(self) -> int:
        return len(self._t)

    def stats(self) -> RecordingStats:
        dur = (self._t[-1] - self._t[0]) * 1e-9 if self._t else 0.0
        return RecordingStats(len(self._t), dur, self._missing, self._not_increasing, self._non_finite,
                              len(self.images), tuple(sorted(self._contexts)))

    def to_demonstration(self) -> Demonstration:
        """The recorded demonstration; ``t`` starts at 0 (s since the first sample).

        Raises
        ------
        RecordingError
            Fewer than 2 joint samples (the message says how many were dropped and why).
        """
        if len(self._t) < 2:
            s = self.stats()
            why = []
            if self.joint_names is None:
                why.append("no joint state arrived")
            if s.missing_joints:
                why.append(f"{s.missing_joints} message(s) lacked one of the joints {list(self.joint_names)}")
            if s.not_increasing:
                why.append(f"{s.not_increasing} message(s) had non-increasing time stamps")
            if s.non_finite:
                why.append(f"{s.non_finite} message(s) had NaN/inf positions")
            raise RecordingError(
                f"demonstration '{self.name}' has {len(self._t)} joint sample(s); at least 2 are needed"
                + (f" ({'; '.join(why)})" if why else ""))
        t = np.asarray(self._t, dtype=np.int64)
        t_rel = (t - t[0]).astype(np.float64) * 1e-9
        return demo_from_arrays(self.name, t_rel, np.stack(self._q), self.joint_names,
                                contexts=dict(self._contexts), images=self.images.selected(),
                                phase_type=self.phase_type)


# ----------------------------------------------------------------------------------------------
# small helpers for recorders
# ----------------------------------------------------------------------------------------------
def validate_demo_name(name: str) -> str:
    """Check a demonstration / bag name: 1-100 characters of letters, digits, ``_ . -``, starting
    with a letter or digit (so it is a safe file name). Returns the name."""
    if not isinstance(name, str) or not _DEMO_NAME.match(name):
        raise RecordingError(f"demonstration name {name!r} is not valid; expected 1-100 characters of "
                             f"letters, digits, '_', '.', '-', starting with a letter or digit")
    return name


def default_demo_name(now: datetime.datetime | None = None) -> str:
    """``demo_YYYYmmdd_HHMMSS_fff`` from the local time."""
    now = datetime.datetime.now() if now is None else now
    return now.strftime("demo_%Y%m%d_%H%M%S_") + f"{now.microsecond // 1000:03d}"


def parse_context_spec(spec: str) -> tuple[str, str]:
    """``"name=topic"`` or ``"topic"`` -> (context name, topic).

    Without a name, the name is the topic without leading '/' and with '/' replaced by '_'
    (``"objects/cube/pose"`` -> ``"objects_cube_pose"``).
    """
    spec = spec.strip()
    if "=" in spec:
        name, topic = (s.strip() for s in spec.split("=", 1))
    else:
        topic = spec
        name = topic.strip("/").replace("/", "_")
    if not topic or not re.match(r"^[A-Za-z0-9_./~{}\-]+$", topic):
        raise RecordingError(f"context topic spec {spec!r} is not valid; expected 'topic' or "
                             f"'name=topic', e.g. 'object=objects/cube/pose'")
    if not re.match(r"^[A-Za-z_][A-Za-z0-9_]*$", name):
        raise RecordingError(f"context name {name!r} (from {spec!r}) is not valid; expected letters, "
                             f"digits and '_', starting with a letter")
    return name, topic


def check_writable_directory(path: str | os.PathLike, label: str = "output directory") -> pathlib.Path:
    """Create ``path`` if needed and check a file can be created in it.

    Raises
    ------
    RecordingError
        Naming the folder and the OS error.
    """
    p = pathlib.Path(path).expanduser()
    try:
        p.mkdir(parents=True, exist_ok=True)
        probe = p / f".write_test.{os.getpid()}.{time.time_ns()}"
        with open(probe, "wb"):
            pass
        probe.unlink()
    except OSError as exc:
        raise RecordingError(f"{label} '{p}' is not a writable folder ({exc.strerror or exc})") from exc
    return p
