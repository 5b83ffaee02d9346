"""Demonstration datasets: the on-disk format, validation, import and built-in generators.

Format (one ``.npz`` file per demonstration, written with :func:`save_demo`, read with
``np.load(..., allow_pickle=False)``; a dataset is a folder of such files plus nothing else):

==================  =====================  ===================================================
key                 shape / dtype          meaning
==================  =====================  ===================================================
``t``               (T,) float64           time stamps in seconds, strictly increasing
``q``               (T, d) float64         joint positions, rad (or m for prismatic joints)
``joint_names``     (d,) str               joint names, identical across a dataset
``phase_type``      () str                 ``"linear"`` or ``"rhythmic"`` (one cycle per demo)
``ctx/<name>``      (m, c) or (c,) float   optional low-dimensional context vectors of modality
                                           ``<name>`` (an object position, a one-hot task id…)
``images``          (n, H, W, 3) uint8     optional camera images of the scene (RGB)
==================  =====================  ===================================================

Import from plain arrays with :func:`demo_from_arrays` or :func:`load_csv` (one demo per CSV:
a header ``t,<joint names...>`` then one row per sample).
"""
from __future__ import annotations

import dataclasses
import pathlib
from typing import Iterable, Mapping, Sequence

import numpy as np

PHASE_TYPES = ("linear", "rhythmic")


class DatasetError(ValueError):
    """A demonstration or dataset is malformed; the message names the demo and the problem."""


@dataclasses.dataclass(frozen=True)
class Demonstration:
    """One demonstration.

    Attributes
    ----------
    name : str
    t : array, shape (T,)
        Time stamps (s), strictly increasing.
    q : array, shape (T, d)
        Joint positions.
    joint_names : tuple of str, length d
    contexts : mapping str -> array, shape (m, c)
        Low-dimensional context vectors per modality (m vectors of dimension c).
    images : array, shape (n, H, W, 3), uint8, or None
    phase_type : {"linear", "rhythmic"}
    """

    name: str
    t: np.ndarray
    q: np.ndarray
    joint_names: tuple[str, ...]
    contexts: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)
    images: np.ndarray | None = None
    phase_type: str = "linear"

    @property
    def n_joints(self) -> int:
        return int(self.q.shape[1])

    def phase(self) -> np.ndarray:
        """Normalized phase x = (t - t_0) / (t_end - t_0) in [0, 1], shape (T,)."""
        return (self.t - self.t[0]) / (self.t[-1] - self.t[0])

    def resampled(self, n_points: int) -> np.ndarray:
        """Joint positions linearly interpolated on ``n_points`` equally spaced phases.

        Returns
        -------
        q : array, shape (n_points, d)
        """
        x = self.phase()
        grid = np.linspace(0.0, 1.0, n_points)
        return np.stack([np.interp(grid, x, self.q[:, j]) for j in range(self.n_joints)], axis=1)


def validate_demo(demo: Demonstration) -> Demonstration:
    """Check one demonstration; raise :class:`DatasetError` naming the demo and the problem."""
    who = f"demonstration '{demo.name}'"
    t = np.asarray(demo.t)
    q = np.asarray(demo.q)
    if t.ndim != 1:
        raise DatasetError(f"{who}: time stamps t must be 1-D with shape (T,), got shape {t.shape}")
    if q.ndim != 2:
        raise DatasetError(f"{who}: joint positions q must be 2-D with shape (T, d), got shape {q.shape}")
    if q.shape[0] != t.shape[0]:
        raise DatasetError(
            f"{who}: ragged shapes: {t.shape[0]} time stamps but {q.shape[0]} rows of joint positions; "
            "expected one row of q per time stamp")
    if t.shape[0] < 2:
        raise DatasetError(f"{who}: needs at least 2 samples, got {t.shape[0]}")
    if len(demo.joint_names) != q.shape[1]:
        raise DatasetError(
            f"{who}: {q.shape[1]} joint columns but {len(demo.joint_names)} joint names; expected one name per column")
    if not np.all(np.isfinite(t)):
        raise DatasetError(f"{who}: time stamps contain NaN or inf at index {int(np.argmin(np.isfinite(t)))}")
    bad = ~np.isfinite(q)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise DatasetError(
            f"{who}: joint positions contain NaN or inf (first at sample {i}, joint '{demo.joint_names[j]}'); "
            "expected finite values")
    dt = np.diff(t)
    if np.any(dt <= 0):
        i = int(np.argmax(dt <= 0))
        raise DatasetError(
            f"{who}: time stamps are not strictly increasing (t[{i}]={t[i]:.6g} s, t[{i + 1}]={t[i + 1]:.6g} s)")
    if demo.phase_type not in PHASE_TYPES:
        raise DatasetError(f"{who}: phase_type '{demo.phase_type}' unknown; expected one of {PHASE_TYPES}")
    for name, c in demo.contexts.items():
        c = np.asarray(c)
        if c.ndim != 2 or c.shape[0] < 1:
            raise DatasetError(f"{who}: context '{name}' must have shape (m, c) with m >= 1, got {c.shape}")
        if not np.all(np.isfinite(c)):
            raise DatasetError(f"{who}: context '{name}' contains NaN or inf; expected finite values")
    if demo.images is not None:
        im = np.asarray(demo.images)
        if im.ndim != 4 or im.shape[-1] != 3 or im.dtype != np.uint8 or im.shape[0] < 1:
            raise DatasetError(
                f"{who}: images must be uint8 with shape (n, H, W, 3), n >= 1; got dtype {im.dtype}, shape {im.shape}")
    return demo


def demo_from_arrays(name: str, t: Sequence[float], q, joint_names: Sequence[str],
                     contexts: Mapping[str, np.ndarray] | None = None, images=None,
                     phase_type: str = "linear") -> Demonstration:
    """Build and validate a :class:`Demonstration` from plain arrays.

    Parameters
    ----------
    t : array, shape (T,)
    q : array, shape (T, d)
    contexts : mapping str -> array, shape (c,) or (m, c)
    images : array, shape (n, H, W, 3) uint8, optional
    """
    ctx = {}
    for k, v in (contexts or {}).items():
        v = np.asarray(v, dtype=np.float64)
        ctx[str(k)] = v[None, :] if v.ndim == 1 else v
    demo = Demonstration(
        name=str(name), t=np.asarray(t, dtype=np.float64), q=np.asarray(q, dtype=np.float64),
        joint_names=tuple(str(j) for j in joint_names), contexts=ctx,
        images=None if images is None else np.asarray(images), phase_type=phase_type)
    return validate_demo(demo)


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
        import os
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


@dataclasses.dataclass(frozen=True)
class DemoDataset:
    """A validated set of demonstrations sharing joint names, phase type and context layout."""

    demos: tuple[Demonstration, ...]
    source: str = "memory"

    def __post_init__(self):
        if not self.demos:
            raise DatasetError(f"dataset '{self.source}' is empty; expected at least one demonstration")
        first = self.demos[0]
        for d in self.demos:
            validate_demo(d)
            if d.joint_names != first.joint_names:
                raise DatasetError(
                    f"demonstration '{d.name}': joint names {list(d.joint_names)} do not match the dataset's "
                    f"{list(first.joint_names)} (from '{first.name}')")
            if d.phase_type != first.phase_type:
                raise DatasetError(f"demonstration '{d.name}': phase_type '{d.phase_type}' but the dataset is "
                                   f"'{first.phase_type}'")
            if set(d.contexts) != set(first.contexts):
                raise DatasetError(f"demonstration '{d.name}': context modalities {sorted(d.contexts)} differ from "
                                   f"the dataset's {sorted(first.contexts)}")
            for k, v in d.contexts.items():
                if v.shape[1] != first.contexts[k].shape[1]:
                    raise DatasetError(f"demonstration '{d.name}': context '{k}' has dimension {v.shape[1]}, "
                                       f"expected {first.contexts[k].shape[1]}")
            if (d.images is None) != (first.images is None):
                raise DatasetError(f"demonstration '{d.name}': images must be given for all demonstrations or none")
            if d.images is not None and d.images.shape[1:] != first.images.shape[1:]:
                raise DatasetError(f"demonstration '{d.name}': image size {d.images.shape[1:3]} differs from "
                                   f"{first.images.shape[1:3]}")

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.demos[0].joint_names

    @property
    def phase_type(self) -> str:
        return self.demos[0].phase_type

    @property
    def context_dims(self) -> dict[str, int]:
        return {k: int(v.shape[1]) for k, v in sorted(self.demos[0].contexts.items())}

    @property
    def image_shape(self) -> tuple[int, int] | None:
        im = self.demos[0].images
        return None if im is None else (int(im.shape[1]), int(im.shape[2]))

    def __len__(self) -> int:
        return len(self.demos)

    def split(self, n_val: int, seed: int = 0) -> tuple["DemoDataset", "DemoDataset"]:
        """Random (seeded) train / validation split."""
        if not 0 < n_val < len(self.demos):
            raise DatasetError(f"validation split of {n_val} needs 0 < n_val < {len(self.demos)} demonstrations")
        idx = np.random.default_rng(seed).permutation(len(self.demos))
        val = tuple(self.demos[i] for i in sorted(idx[:n_val]))
        train = tuple(self.demos[i] for i in sorted(idx[n_val:]))
        return DemoDataset(train, self.source + ":train"), DemoDataset(val, self.source + ":val")

    def save(self, folder: str | pathlib.Path) -> pathlib.Path:
        folder = pathlib.Path(folder)
        for i, d in enumerate(self.demos):
            save_demo(d, folder / f"{i:05d}_{_safe(d.name)}.npz")
        return folder


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name)[:60]


def load_dataset(folder: str | pathlib.Path) -> DemoDataset:
    """Load every ``*.npz`` (and ``*.csv``) demonstration of a folder, validated."""
    folder = pathlib.Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"dataset folder '{folder}' does not exist; expected a folder of .npz/.csv demonstrations")
    files = sorted(list(folder.glob("*.npz")) + list(folder.glob("*.csv")))
    if not files:
        raise DatasetError(f"dataset folder '{folder}' has no .npz or .csv demonstrations")
    demos = tuple(load_demo(f) if f.suffix == ".npz" else load_csv(f) for f in files)
    return DemoDataset(demos, source=str(folder))


# ----------------------------------------------------------------------------------------------
# Built-in data: the paper's bimodal sine family (Fig. "DeepProMPs used in different situations").
# ----------------------------------------------------------------------------------------------

def bimodal_sine(n_demos: int = 200, n_points: int = 100, n_joints: int = 1, seed: int = 0,
                 amplitude: tuple[float, float] = (0.8, 1.2), noise_std: float = 0.01,
                 duration: float = 2.0) -> DemoDataset:
    """Two modes of sinusoids: y_j(x) = s * A_j * sin(2π x) + small noise, s = ±1 with equal probability.

    Both modes cross zero at x = 0, 0.5, 1 (via-points there cannot tell the modes apart); at
    x = 0.25 they are ±A apart. Each demo carries a 1-D context ``mode`` = s (the low-dim context).

    Returns
    -------
    DemoDataset with ``n_demos`` demonstrations of ``n_points`` samples and ``n_joints`` joints.
    """
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, 1.0, n_points)
    t = x * duration
    names = tuple(f"joint_{j + 1}" for j in range(n_joints))
    demos = []
    for i in range(n_demos):
        s = 1.0 if rng.random() < 0.5 else -1.0
        amp = rng.uniform(*amplitude, size=n_joints)
        q = s * amp[None, :] * np.sin(2 * np.pi * x)[:, None] + noise_std * rng.standard_normal((n_points, n_joints))
        demos.append(Demonstration(name=f"sine_{i:04d}", t=t.copy(), q=q, joint_names=names,
                                   contexts={"mode": np.array([[s]])}))
    return DemoDataset(tuple(demos), source=f"bimodal_sine(seed={seed})")


def rhythmic_shake(n_demos: int = 30, n_points: int = 100, n_joints: int = 7, seed: int = 0,
                   period: float = 2.0, offset=None, joint_names: Sequence[str] | None = None) -> DemoDataset:
    """One-cycle shaking demonstrations for rhythmic primitives (phase = [sin 2πx, cos 2πx]).

    Each joint oscillates around ``offset`` (default: spread over ±0.3 rad) with a per-demo
    amplitude (0.08–0.2 rad), phase and a second harmonic (≤ 0.04 rad); the demo is exactly one
    period long, so its start and end coincide up to noise. Peak speed ≤ 0.9 rad/s at period 2 s.
    """
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, 1.0, n_points, endpoint=True)
    names = tuple(joint_names) if joint_names is not None else tuple(f"joint_{j + 1}" for j in range(n_joints))
    n_joints = len(names)
    offset = np.linspace(-0.3, 0.3, n_joints) if offset is None else np.asarray(offset, dtype=np.float64)
    demos = []
    for i in range(n_demos):
        a1 = rng.uniform(0.08, 0.2, n_joints)
        a2 = rng.uniform(0.0, 0.04, n_joints)
        ph = rng.uniform(-0.2, 0.2, n_joints)
        q = offset + a1 * np.sin(2 * np.pi * x[:, None] + ph) + a2 * np.sin(4 * np.pi * x[:, None])
        q = q + 0.002 * rng.standard_normal(q.shape)
        demos.append(Demonstration(name=f"shake_{i:04d}", t=x * period, q=q, joint_names=names,
                                   phase_type="rhythmic"))
    return DemoDataset(tuple(demos), source=f"rhythmic_shake(seed={seed})")


# Barrett WAM joint names and ready pose of deepprompt_ros/resources/urdf/wam.urdf.
WAM_JOINTS = tuple(f"wam_j{i}" for i in range(1, 8))
WAM_READY = (0.0, 0.5, 0.0, 2.0, 0.0, 0.6, 0.0)


def wam_shake(seed: int = 0, **kwargs) -> DemoDataset:
    """Shaking ("make a mojito") cycles on the Barrett WAM around its ready pose."""
    return rhythmic_shake(seed=seed, joint_names=WAM_JOINTS, offset=WAM_READY, **kwargs)


def gen3_lite_reach(seed: int = 0, **kwargs) -> DemoDataset:
    """Reaching demonstrations on the Kinova Gen3 lite with the object position as context
    (see :mod:`deepprompt_ros.data.reach`; imported lazily: it needs pinocchio)."""
    from deepprompt_ros.data.reach import reach_demos

    return reach_demos("gen3_lite", seed=seed, **kwargs)


def _task_builtin(name: str):
    """Lazy entry for a task of :mod:`deepprompt_ros.sim.tasks.registry` (which imports this module): its
    train split, ``make_task(name, seed=seed, **kwargs)``."""
    def generate(seed: int = 0, **kwargs) -> DemoDataset:
        from deepprompt_ros.sim.tasks.registry import make_task

        return make_task(name, seed=seed, **kwargs)

    generate.__doc__ = f"Train split of the PyBullet task '{name}' (see deepprompt_ros.sim.tasks.registry)."
    return generate


BUILTIN = {"bimodal_sine": bimodal_sine, "rhythmic_shake": rhythmic_shake, "wam_shake": wam_shake,
           "gen3_lite_reach": gen3_lite_reach,
           **{name: _task_builtin(name) for name in ("reach", "close_box", "pour", "kinova_pick_place")}}


def builtin_dataset(name: str, **kwargs) -> DemoDataset:
    if name not in BUILTIN:
        raise DatasetError(f"unknown built-in dataset '{name}'; available: {sorted(BUILTIN)}")
    return BUILTIN[name](**kwargs)


def iter_demo_files(folder: str | pathlib.Path) -> Iterable[pathlib.Path]:
    return sorted(pathlib.Path(folder).glob("*.npz"))
