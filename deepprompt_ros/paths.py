"""Where the package's data folders (``config/``, ``models/``) are.

Search order, first hit wins for each file:

1. the installed share directory ``<prefix>/share/deepprompt_ros`` of every prefix that holds the
   ament index marker ``<prefix>/share/ament_index/resource_index/packages/deepprompt_ros``:
   ``sys.prefix`` first (the venv / interpreter this runs in), then the entries of
   ``AMENT_PREFIX_PATH`` in order (a colcon or apt install);
2. the source tree this module was imported from (a checkout: the folder holding
   ``package.xml`` next to the ``deepprompt_ros`` package).

A file that exists in the source tree but not (yet) in the share directory -- e.g. a model
trained after the last install -- is still found (:func:`find_data_file`).
"""
from __future__ import annotations

import os
import pathlib
import sys

PACKAGE = "deepprompt_ros"

__all__ = ["PACKAGE", "share_dirs", "source_dir", "data_dirs", "find_data_file"]


def _prefixes() -> list[pathlib.Path]:
    out = [pathlib.Path(sys.prefix)]
    for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if p:
            out.append(pathlib.Path(p))
    seen, unique = set(), []
    for p in out:
        key = os.path.realpath(p)
        if key not in seen:
            seen.add(key)
            unique.append(p)
    return unique


def share_dirs() -> list[pathlib.Path]:
    """Installed ``share/deepprompt_ros`` folders, in search order (may be empty)."""
    dirs = []
    for prefix in _prefixes():
        marker = prefix / "share" / "ament_index" / "resource_index" / "packages" / PACKAGE
        share = prefix / "share" / PACKAGE
        if marker.is_file() and share.is_dir():
            dirs.append(share)
    return dirs


def source_dir() -> pathlib.Path | None:
    """The checkout this package was imported from, or None for a non-editable install."""
    root = pathlib.Path(__file__).resolve().parent.parent
    return root if (root / "package.xml").is_file() and (root / PACKAGE).is_dir() else None


def data_dirs(kind: str) -> list[pathlib.Path]:
    """Existing folders named ``kind`` ("config" or "models"), in search order."""
    if kind not in ("config", "models"):
        raise ValueError(f"kind must be 'config' or 'models'; got {kind!r}")
    dirs = [d / kind for d in share_dirs()]
    src = source_dir()
    if src is not None:
        dirs.append(src / kind)
    return [d for d in dirs if d.is_dir()]


def find_data_file(kind: str, name: str | os.PathLike) -> pathlib.Path:
    """Resolve ``name``: an absolute path is returned as is; a relative one is looked up in
    every ``kind`` folder in search order and the first existing file is returned.

    Raises
    ------
    FileNotFoundError
        Naming every place that was searched.
    """
    path = pathlib.Path(name)
    if path.is_absolute():
        if not path.is_file():
            raise FileNotFoundError(f"'{path}' does not exist")
        return path
    dirs = data_dirs(kind)
    for d in dirs:
        if (d / path).is_file():
            return d / path
    raise FileNotFoundError(f"'{name}' not found in any {kind} folder; searched "
                            f"{[str(d) for d in dirs] or '(no ' + kind + ' folder found)'}")
