"""Reading and writing demonstrations: ``.npz`` files (the format of
:mod:`deepprompt_ros.data.demonstration`) and CSV import."""
from __future__ import annotations

import os
import pathlib
from typing import Iterable

import numpy as np

from deepprompt_ros.data.demonstration import DatasetError, Demonstration, demo_from_arrays, validate_demo

__all__ = ["save_demo", "load_demo", "load_csv", "iter_demo_files"]


def save_demo(demo: Demonstration, path: str | pathlib.Path) -> pathlib.Path:
    """Write one demonstration atomically (temp file + rename: a crash never leaves a half file)."""
    validate_demo(demo)
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {"t": demo.t, "q": demo.q, "joint_names": np.array(demo.joint_names),
              "phase_type": np.array(demo.phase_type), "name": np.array(demo.name)}
    for k, v in demo.contexts.items():
        arrays[f"ctx/{k}"] = np.asarray(v)
    if demo.images is not None:
        arrays["images"] = demo.images
    tmp = path.with_name(path.name + ".part")
    with open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)
        f.flush()
        os.fsync(f.fileno())
    tmp.replace(path)
    return path


def load_demo(path: str | pathlib.Path) -> Demonstration:
    """Read and validate one ``.npz`` demonstration (no pickle)."""
    path = pathlib.Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            keys = set(z.files)
            missing = {"t", "q", "joint_names"} - keys
            if missing:
                raise DatasetError(f"demonstration '{path.name}': missing arrays {sorted(missing)}; "
                                   "expected t (T,), q (T, d), joint_names (d,)")
            ctx = {k[4:]: np.asarray(z[k], dtype=np.float64) for k in keys if k.startswith("ctx/")}
            ctx = {k: (v[None, :] if v.ndim == 1 else v) for k, v in ctx.items()}
            demo = Demonstration(
                name=str(z["name"]) if "name" in keys else path.stem,
                t=np.asarray(z["t"], dtype=np.float64), q=np.asarray(z["q"], dtype=np.float64),
                joint_names=tuple(str(s) for s in np.atleast_1d(z["joint_names"])), contexts=ctx,
                images=np.asarray(z["images"]) if "images" in keys else None,
                phase_type=str(z["phase_type"]) if "phase_type" in keys else "linear")
    except DatasetError:
        raise
    except (OSError, ValueError, KeyError) as exc:
        raise DatasetError(f"demonstration '{path.name}': cannot be read as a .npz demonstration ({exc})") from exc
    return validate_demo(demo)


def load_csv(path: str | pathlib.Path, phase_type: str = "linear") -> Demonstration:
    """Read one demonstration from a CSV file: header ``t,<joint names...>``, one row per sample."""
    path = pathlib.Path(path)
    with open(path) as f:
        header = f.readline().strip().split(",")
    if len(header) < 2 or header[0].strip() != "t":
        raise DatasetError(f"demonstration '{path.name}': CSV header must be 't,<joint_1>,...,<joint_d>', got {header}")
    try:
        data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except ValueError as exc:
        raise DatasetError(f"demonstration '{path.name}': CSV rows must be numbers ({exc})") from exc
    return demo_from_arrays(path.stem, data[:, 0], data[:, 1:], [h.strip() for h in header[1:]], phase_type=phase_type)


def iter_demo_files(folder: str | pathlib.Path) -> Iterable[pathlib.Path]:
    """The ``*.npz`` demonstration files of a folder, sorted by name."""
    return sorted(pathlib.Path(folder).glob("*.npz"))
