"""A dataset: a validated set of demonstrations sharing joint names, phase type and context layout,
kept as a folder of ``.npz`` files (:meth:`DemoDataset.save`, :func:`load_dataset`)."""
from __future__ import annotations

import dataclasses
import pathlib

import numpy as np

from deepprompt_ros.data.demonstration import DatasetError, Demonstration, validate_demo
from deepprompt_ros.data.io import load_csv, load_demo, save_demo

__all__ = ["DemoDataset", "load_dataset"]


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
        """Write every demonstration to ``folder`` (created) as ``<index>_<name>.npz``; returns the folder."""
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
