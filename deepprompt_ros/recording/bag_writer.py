"""The raw messages of a recording: a rosbag2 bag folder with MCAP storage (:class:`BagWriter`)::

    <bag_directory>/<name>/
        metadata.yaml        rosbag2 metadata (format version 9, ROS 2 Jazzy)
        <name>_0.mcap        MCAP, profile "ros2": schemas "ros2msg", messages "cdr"

``ros2 bag info/play <bag_directory>/<name>`` read it, and so does any MCAP reader. While
recording, the folder is ``<bag_directory>/.<name>.<pid>.<ns>.part``; it is renamed to its final
name only after the MCAP summary and ``metadata.yaml`` are written and synced, so a crash leaves
finished bags untouched and at most one hidden ``.part`` folder (whose MCAP file, without summary,
most MCAP readers can still scan).

The MCAP schemas are the ROS 2 ``.msg`` definitions with their dependencies, read from the
``share/<package>/msg/`` folders of the installed interface packages
(:func:`message_definition`), concatenated as rosbag2 does: the top-level definition, then for
each nested type a line of 80 ``=``, a line ``MSG: <package>/<Type>`` and its definition.
No ROS import: the messages arrive already serialized.
"""
from __future__ import annotations

import dataclasses
import os
import pathlib
import re
import shutil
import sys
import time
from typing import Sequence

import yaml

from deepprompt_ros.recording.checks import RecordingError, validate_demo_name

__all__ = ["ROSBAG2_METADATA_VERSION", "message_definition", "qos_profile_yaml", "BagWriter"]

#: rosbag2 metadata format version written to metadata.yaml (the version of ROS 2 Jazzy).
ROSBAG2_METADATA_VERSION = 9

_PRIMITIVES = frozenset({
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
    "uint32", "int64", "uint64", "string", "wstring",
})


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
