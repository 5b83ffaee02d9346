"""One demonstration: the data format, its validation and construction from plain arrays.

On disk (one ``.npz`` file per demonstration, written with :func:`~deepprompt_ros.data.io.save_demo`,
read with ``np.load(..., allow_pickle=False)``; a dataset is a folder of such files plus nothing
else, :class:`~deepprompt_ros.data.demo_dataset.DemoDataset` in memory):

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

Import from plain arrays with :func:`demo_from_arrays` or :func:`~deepprompt_ros.data.io.load_csv`
(one demo per CSV: a header ``t,<joint names...>`` then one row per sample).
"""
from __future__ import annotations

import dataclasses
from typing import Mapping, Sequence

import numpy as np

__all__ = ["PHASE_TYPES", "DatasetError", "Demonstration", "validate_demo", "demo_from_arrays"]

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
