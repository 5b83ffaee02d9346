"""Point the ROS wheels' CMake export files at this interpreter's headers.

The ROS 2 wheels install CMake export files (``<prefix>/share/*/cmake/*.cmake``)
whose ``INTERFACE_INCLUDE_DIRECTORIES`` still name the wheel build machine's
paths, e.g. ``/opt/python/cp311-cp311/include/python3.11`` and
``/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include``.
CMake refuses such targets ("includes non-existent path"), so building an
interface package against the wheels fails until the paths are rewritten to

* ``sysconfig.get_paths()["include"]`` (Python headers) and
* ``numpy.get_include()`` (numpy headers; ``numpy/core/include`` for numpy 1.x,
  ``numpy/_core/include`` for 2.x).

Run with the interpreter of the prefix (``<venv>/bin/python``) after every
install or numpy change. Idempotent: entries that already name the right
directory are left alone, so a second run changes nothing.

Usage: ``python tools/fix_cmake_paths.py [--check] [PREFIX]`` (default: ``sys.prefix``).
"""
from __future__ import annotations

import argparse
import glob
import os
import re
import sys
import sysconfig
from typing import NamedTuple

# A quoted CMake list of include directories, e.g.
#   INTERFACE_INCLUDE_DIRECTORIES "/a/include;/b/include"
_INCLUDE_PROPERTY = re.compile(r'(INTERFACE_INCLUDE_DIRECTORIES\s+")([^"]*)(")')
_NUMPY_INCLUDE = re.compile(r"/numpy/(_core|core)/include/?$")
_PYTHON_INCLUDE = re.compile(r"/include/python3\.\d+[a-z]*/?$")


class FixReport(NamedTuple):
    """Outcome of one run.

    Attributes
    ----------
    scanned : int
        Number of ``*.cmake`` files read.
    changed : list of str
        Files that were rewritten (with ``check``: that would be).
    python_include, numpy_include : str
        Directories written into the files.
    """

    scanned: int
    changed: list
    python_include: str
    numpy_include: str


def _rewrite_entry(entry: str, python_include: str, numpy_include: str) -> str:
    """Map one include directory to its local equivalent (or keep it)."""
    if _NUMPY_INCLUDE.search(entry):
        return numpy_include
    if _PYTHON_INCLUDE.search(entry) and not os.path.isdir(entry):
        return python_include
    return entry


def rewrite_text(text: str, python_include: str, numpy_include: str) -> str:
    """Return ``text`` with Python/numpy include directories replaced.

    Only entries of ``INTERFACE_INCLUDE_DIRECTORIES`` lists are touched:
    any ``.../numpy/(_core|core)/include`` becomes ``numpy_include`` and any
    non-existent ``.../include/python3.X`` becomes ``python_include``.
    """

    def fix(match: re.Match) -> str:
        entries = match.group(2).split(";")
        fixed = [_rewrite_entry(e, python_include, numpy_include) for e in entries]
        return match.group(1) + ";".join(fixed) + match.group(3)

    return _INCLUDE_PROPERTY.sub(fix, text)


def fix_prefix(prefix: str, python_include: str | None = None,
               numpy_include: str | None = None, check: bool = False) -> FixReport:
    """Rewrite every ``<prefix>/share/*/cmake/*.cmake`` in place.

    Parameters
    ----------
    prefix : str
        Install prefix holding the ROS wheels (the venv).
    python_include, numpy_include : str, optional
        Target directories; default to this interpreter's
        ``sysconfig.get_paths()["include"]`` and ``numpy.get_include()``.
    check : bool
        Only report which files would change; write nothing.

    Raises
    ------
    FileNotFoundError
        If a target include directory does not exist (the build would fail
        with it just the same).
    """
    if python_include is None:
        python_include = sysconfig.get_paths()["include"]
    if numpy_include is None:
        import numpy  # imported late: only needed when no path is given
        numpy_include = numpy.get_include()
    for name, path in (("Python", python_include), ("numpy", numpy_include)):
        if not os.path.isdir(path):
            raise FileNotFoundError(
                f"{name} include directory {path!r} does not exist; expected the "
                f"headers of the interpreter that builds the interfaces "
                f"(install the Python development headers / numpy)")
    files = sorted(glob.glob(os.path.join(prefix, "share", "*", "cmake", "*.cmake")))
    changed = []
    for path in files:
        with open(path, encoding="utf-8") as f:
            text = f.read()
        if "INTERFACE_INCLUDE_DIRECTORIES" not in text:
            continue
        new = rewrite_text(text, python_include, numpy_include)
        if new != text:
            changed.append(path)
            if check:
                continue
            tmp = path + ".tmp"
            with open(tmp, "w", encoding="utf-8") as f:
                f.write(new)
            os.replace(tmp, path)
    return FixReport(len(files), changed, python_include, numpy_include)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("prefix", nargs="?", default=sys.prefix,
                        help="install prefix holding the ROS wheels (default: sys.prefix)")
    parser.add_argument("--check", action="store_true",
                        help="write nothing; exit 1 if any file would change")
    args = parser.parse_args(argv)
    report = fix_prefix(args.prefix, check=args.check)
    if args.check:
        for path in report.changed:
            print(f"would rewrite {path}")
        return 1 if report.changed else 0
    print(f"cmake paths: scanned {report.scanned} files, rewrote {len(report.changed)} "
          f"(python include {report.python_include}, numpy include {report.numpy_include})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
