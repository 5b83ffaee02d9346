"""What every part of a recording checks: its error type, demonstration and bag names, context
topic specs and output folders (no ROS needed)."""
from __future__ import annotations

import datetime
import os
import pathlib
import re
import time

__all__ = ["RecordingError", "validate_demo_name", "default_demo_name", "parse_context_spec",
           "check_writable_directory"]

_DEMO_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,99}$")


class RecordingError(ValueError):
    """A recording request or file operation failed; the message says what and what is expected."""


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
