"""The demonstration of a recording: samples buffered as they arrive, then one
:class:`~deepprompt_ros.data.demonstration.Demonstration` (:class:`DemoBuffer`).

A recording produces two outputs: this **demonstration**, one ``.npz`` file in the dataset format
of :mod:`deepprompt_ros.data.demonstration` (joint positions with time stamps, low-dimensional
contexts, a few downsampled images; written atomically by :func:`~deepprompt_ros.data.io.save_demo`),
and the **raw messages** in a rosbag2 bag (:mod:`deepprompt_ros.recording.bag_writer`).
"""
from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

from deepprompt_ros.data.demonstration import Demonstration, demo_from_arrays
from deepprompt_ros.recording.checks import RecordingError, validate_demo_name
from deepprompt_ros.recording.images import ImageKeeper

__all__ = ["RecordingStats", "DemoBuffer"]


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
