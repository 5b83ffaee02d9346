"""A sharded on-disk dataset for more demonstrations than fit in memory, beside the folder of
``.npz`` files of :mod:`deepprompt_ros.data.demonstration`, and the converter between the two.

On disk: a folder with ``index.json`` and one sub-folder ``shard_<k>`` per shard of up to N
demonstrations, each array a ``.npy`` file read through a memory map (``np.load(..., mmap_mode="r")``,
no pickle). The ragged arrays of a shard are concatenated along their first axis; ``<key>_rows``
(n + 1,) int64 gives demo i's rows ``rows[i]:rows[i + 1]``:

=====================  =========================  ===========================================
file                   shape / dtype              meaning
=====================  =========================  ===========================================
``t.npy``              (ΣT,) float64              time stamps of every demo of the shard
``q.npy``              (ΣT, d) float64            joint positions
``t_rows.npy``         (n + 1,) int64             row offsets of each demo in ``t`` and ``q``
``ctx_<name>.npy``     (Σm, c) float64            context vectors of modality ``<name>``
``ctx_<name>_rows``    (n + 1,) int64             their row offsets
``images.npy``         (Σn_img, H, W, 3) uint8    camera images (when the dataset has images)
``images_rows.npy``    (n + 1,) int64             their row offsets
``names.npy``          (n,) str                   the demos' names
=====================  =========================  ===========================================

``index.json``: ``format`` (:data:`FORMAT`), ``version``, ``joint_names``, ``phase_type``,
``context_dims`` {name: c}, ``image_shape`` [H, W] or null, ``max_contexts`` {name: largest m},
``max_images``, ``n_demos`` and ``shards`` [{``dir``, ``first`` (index of its first demo),
``n_demos``, ``rows`` (ΣT), ``context_rows`` {name: Σm}, ``image_rows``}]. A folder with an
``index.json`` is a sharded dataset (:func:`is_sharded`); opening it
(:class:`ShardedDataset`) checks every shard's files against the index.

Convert a documented folder with ``python -m deepprompt_ros.data.sharded SRC DST`` (or the
``shard_dataset`` command): the demos are read one at a time and written one shard at a time.
"""
from __future__ import annotations

import argparse
import json
import mmap
import pathlib
import shutil
import sys
from typing import Iterable, Iterator, Sequence

import numpy as np

from deepprompt_ros.data.demonstration import DatasetError, Demonstration, validate_demo
from deepprompt_ros.data.io import load_csv, load_demo

__all__ = ["FORMAT", "INDEX", "DEFAULT_SHARD_SIZE", "ShardedDataset", "is_sharded", "write_shards",
           "convert_folder", "main"]

FORMAT = "deepprompt_ros.shards"
VERSION = 1
INDEX = "index.json"
DEFAULT_SHARD_SIZE = 256


def is_sharded(folder: str | pathlib.Path) -> bool:
    """True when ``folder`` holds a sharded dataset (its ``index.json``)."""
    return (pathlib.Path(folder) / INDEX).is_file()


class ShardedDataset:
    """A sharded dataset on disk, read lazily: only the demos asked for are read (through memory
    maps opened for the read and closed after it, so the pages read do not stay mapped).

    Attributes as :class:`~deepprompt_ros.data.demo_dataset.DemoDataset`: ``joint_names``,
    ``phase_type``, ``context_dims``, ``image_shape``, ``source``, ``len()``; plus ``max_contexts``
    and ``max_images``, the largest counts of any demo (the padding of a batch)."""

    def __init__(self, folder: str | pathlib.Path):
        self.folder = pathlib.Path(folder)
        self.source = str(self.folder)
        path = self.folder / INDEX
        if not path.is_file():
            raise DatasetError(f"sharded dataset '{self.folder}': no {INDEX}; expected a folder written by "
                               "deepprompt_ros.data.sharded")
        try:
            index = json.loads(path.read_text())
            if index.get("format") != FORMAT or index.get("version") != VERSION:
                raise DatasetError(f"sharded dataset '{self.folder}': {INDEX} has format {index.get('format')!r} "
                                   f"version {index.get('version')!r}; expected {FORMAT!r} version {VERSION}")
            self.joint_names = tuple(str(j) for j in index["joint_names"])
            self.phase_type = str(index["phase_type"])
            self.context_dims = {str(k): int(v) for k, v in sorted(index["context_dims"].items())}
            shape = index["image_shape"]
            self.image_shape = None if shape is None else (int(shape[0]), int(shape[1]))
            self.max_contexts = {str(k): int(v) for k, v in index["max_contexts"].items()}
            self.max_images = int(index["max_images"])
            self.shards = [{"dir": _shard_dir(s["dir"]), "first": int(s["first"]), "n_demos": int(s["n_demos"]),
                            "rows": int(s["rows"]), "image_rows": int(s["image_rows"]),
                            "context_rows": {k: int(s["context_rows"][k]) for k in self.context_dims}}
                           for s in index["shards"]]
            self._n = int(index["n_demos"])
        except (ValueError, KeyError, TypeError, IndexError) as exc:  # json.JSONDecodeError is a ValueError
            if isinstance(exc, DatasetError):
                raise
            raise DatasetError(f"sharded dataset '{self.folder}': {INDEX} cannot be read ({exc!r}); expected the "
                               "index written by deepprompt_ros.data.sharded") from exc
        self._firsts = np.array([int(s["first"]) for s in self.shards], dtype=np.int64)
        # (shard, key) -> the array's data offset in its file, dtype, shape
        self._layout: dict[tuple[str, str], tuple[int, np.dtype, tuple]] = {}
        self._check()

    def _check(self):
        """Every shard's files exist and agree with the index (counts, shapes, dtypes, offsets)."""
        where = f"sharded dataset '{self.folder}'"
        if self._n < 1 or not self.shards:
            raise DatasetError(f"{where}: {INDEX} lists no demonstrations; expected at least one")
        expected_first, d = 0, len(self.joint_names)
        for s in self.shards:
            name = s.get("dir")
            if int(s["first"]) != expected_first or int(s["n_demos"]) < 1:
                raise DatasetError(f"{where}: shard '{name}' starts at demo {s['first']} with {s['n_demos']} demos; "
                                   f"the index expects it to start at {expected_first} with at least one")
            n = int(s["n_demos"])
            shapes = {"t": ((int(s["rows"]),), np.float64), "q": ((int(s["rows"]), d), np.float64),
                      "t_rows": ((n + 1,), np.int64)}
            for k, c in self.context_dims.items():
                shapes[f"ctx_{k}"] = ((int(s["context_rows"][k]), c), np.float64)
                shapes[f"ctx_{k}_rows"] = ((n + 1,), np.int64)
            if self.image_shape is not None:
                shapes["images"] = ((int(s["image_rows"]), *self.image_shape, 3), np.uint8)
                shapes["images_rows"] = ((n + 1,), np.int64)
            for key, (shape, dtype) in shapes.items():
                arr = self._open(name, key)
                self._layout[(name, key)] = (int(arr.offset), arr.dtype, arr.shape)
                if arr.shape != shape or arr.dtype != dtype:
                    raise DatasetError(f"{where}: shard '{name}' file {key}.npy has shape {arr.shape} {arr.dtype}; "
                                       f"the index expects {shape} {np.dtype(dtype)}")
                if key.endswith("_rows"):
                    rows = np.asarray(arr)
                    total = shapes[key[:-5]][0][0]
                    if rows[0] != 0 or rows[-1] != total or np.any(np.diff(rows) < 0):
                        raise DatasetError(f"{where}: shard '{name}' file {key}.npy: offsets must rise from 0 to "
                                           f"{total}; got {rows[0]} … {rows[-1]}")
                del arr
            names = self._open(name, "names")
            self._layout[(name, "names")] = (int(names.offset), names.dtype, names.shape)
            if names.shape != (n,) or names.dtype.kind != "U":
                raise DatasetError(f"{where}: shard '{name}' file names.npy has shape {names.shape} {names.dtype}; "
                                   f"the index expects ({n},) str")
            del names
            expected_first += n
        if expected_first != self._n:
            raise DatasetError(f"{where}: the shards hold {expected_first} demonstrations; {INDEX} says {self._n}")

    def _open(self, shard: str, key: str) -> np.ndarray:
        path = self.folder / shard / f"{key}.npy"
        try:
            return np.load(path, mmap_mode="r", allow_pickle=False)
        except FileNotFoundError:
            raise DatasetError(f"sharded dataset '{self.folder}': shard '{shard}' has no file {key}.npy; "
                               "expected every file the index lists (convert the dataset again)") from None
        except (OSError, ValueError) as exc:
            raise DatasetError(f"sharded dataset '{self.folder}': shard '{shard}' file {key}.npy cannot be read "
                               f"({exc}); expected a .npy array (convert the dataset again)") from exc

    def __len__(self) -> int:
        return self._n

    def shard_of(self, i: int) -> int:
        """The shard holding demo ``i``."""
        if not 0 <= i < self._n:
            raise IndexError(f"demo {i} out of range: the dataset has {self._n} demonstrations")
        return int(np.searchsorted(self._firsts, i, side="right") - 1)

    def _rows(self, shard: str, key: str, ranges: Sequence[tuple[int, int]]) -> list[np.ndarray]:
        """Copies of the rows ``a:b`` of each range of the shard's array ``key``, read through a memory
        map that is closed before returning (its pages do not stay mapped). The array's layout was read
        from its header when the dataset was opened (``np.load``)."""
        offset, dtype, shape = self._layout[(shard, key)]
        path = self.folder / shard / f"{key}.npy"
        size = offset + int(np.prod(shape)) * dtype.itemsize
        try:
            with open(path, "rb") as f:
                mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        except (OSError, ValueError) as exc:
            raise DatasetError(f"sharded dataset '{self.folder}': shard '{shard}' file {key}.npy cannot be read "
                               f"({exc}); expected the file the dataset was opened with") from exc
        try:
            if mm.size() != size:
                raise DatasetError(f"sharded dataset '{self.folder}': shard '{shard}' file {key}.npy has "
                                   f"{mm.size()} bytes, {size} when the dataset was opened; expected it unchanged")
            arr = np.frombuffer(mm, dtype=dtype, count=int(np.prod(shape)), offset=offset).reshape(shape)
            out = [arr[a:b].copy() for a, b in ranges]
            del arr
        finally:
            mm.close()
        return out

    def read(self, indices: Sequence[int], images: bool = True) -> list[Demonstration]:
        """The demos ``indices`` (in that order), read from their shards (each file of a shard mapped
        once per call). ``images`` False: without their images (``images`` None)."""
        indices = [int(i) for i in indices]
        by_shard: dict[int, list[int]] = {}
        for i in indices:
            by_shard.setdefault(self.shard_of(i), []).append(i)
        out = {}
        for k, members in by_shard.items():
            name, first = self.shards[k]["dir"], int(self.shards[k]["first"])
            local = [i - first for i in members]

            def ranges(key: str) -> list[tuple[int, int]]:  # each member's rows of the arrays ``key`` indexes
                return [(int(r[0]), int(r[1])) for r in self._rows(name, f"{key}_rows", [(j, j + 2) for j in local])]

            def ragged(key: str) -> list[np.ndarray]:
                return self._rows(name, key, ranges(key))

            t_rows = ranges("t")
            t, q = self._rows(name, "t", t_rows), self._rows(name, "q", t_rows)
            names = self._rows(name, "names", [(j, j + 1) for j in local])
            ctx = {c: ragged(f"ctx_{c}") for c in self.context_dims}
            ims = ragged("images") if images and self.image_shape is not None else None
            for m, i in enumerate(members):
                out[i] = validate_demo(Demonstration(
                    name=str(names[m][0]), t=t[m], q=q[m], joint_names=self.joint_names,
                    contexts={c: v[m] for c, v in ctx.items()}, images=None if ims is None else ims[m],
                    phase_type=self.phase_type))
        return [out[i] for i in indices]

    def iter_shards(self, indices: Iterable[int] | None = None,
                    images: bool = False) -> Iterator[tuple[int, Demonstration]]:
        """(index, demo) for ``indices`` (all when None) in index order, one shard in memory at a time."""
        wanted = np.arange(self._n) if indices is None else np.unique(np.asarray(list(indices), dtype=np.int64))
        shard = np.searchsorted(self._firsts, wanted, side="right") - 1
        for k in np.unique(shard):
            members = wanted[shard == k]
            yield from zip(members.tolist(), self.read(members, images=images))


class _ShardWriter:
    """Collects demos into shards of ``shard_size`` and writes each when full (bounded memory)."""

    def __init__(self, folder: pathlib.Path, shard_size: int):
        self.folder, self.shard_size = folder, shard_size
        self.pending: list[Demonstration] = []
        self.shards: list[dict] = []
        self.first = None  # the first demo: the layout every other must match
        self.n = 0
        self.max_contexts: dict[str, int] = {}
        self.max_images = 0

    def add(self, demo: Demonstration):
        validate_demo(demo)
        f = self.first
        if f is None:
            self.first = f = demo
            self.max_contexts = {k: 0 for k in demo.contexts}
        elif demo.joint_names != f.joint_names:
            raise DatasetError(f"demonstration '{demo.name}': joint names {list(demo.joint_names)} do not match the "
                               f"dataset's {list(f.joint_names)} (from '{f.name}')")
        elif demo.phase_type != f.phase_type:
            raise DatasetError(f"demonstration '{demo.name}': phase_type '{demo.phase_type}' but the dataset is "
                               f"'{f.phase_type}' (from '{f.name}')")
        elif _dims(demo) != _dims(f):
            raise DatasetError(f"demonstration '{demo.name}': contexts {_dims(demo)} differ from the dataset's "
                               f"{_dims(f)} (name: dimension, from '{f.name}')")
        elif (demo.images is None) != (f.images is None) or (
                demo.images is not None and demo.images.shape[1:] != f.images.shape[1:]):
            raise DatasetError(f"demonstration '{demo.name}': images "
                               f"{None if demo.images is None else demo.images.shape[1:3]} but the dataset's are "
                               f"{None if f.images is None else f.images.shape[1:3]}; expected all demos with images "
                               "of one size, or none")
        for k, v in demo.contexts.items():
            self.max_contexts[k] = max(self.max_contexts[k], int(v.shape[0]))
        if demo.images is not None:
            self.max_images = max(self.max_images, int(demo.images.shape[0]))
        self.pending.append(demo)
        self.n += 1
        if len(self.pending) == self.shard_size:
            self.flush()

    def flush(self):
        if not self.pending:
            return
        demos, self.pending = self.pending, []
        name = f"shard_{len(self.shards):05d}"
        out = self.folder / name
        out.mkdir(parents=True, exist_ok=True)

        def ragged(key: str, parts: list[np.ndarray]) -> int:
            rows = np.concatenate([[0], np.cumsum([len(p) for p in parts])]).astype(np.int64)
            np.save(out / f"{key}.npy", np.concatenate(parts, 0))
            np.save(out / f"{key}_rows.npy", rows)
            return int(rows[-1])

        rows = ragged("t", [d.t.astype(np.float64) for d in demos])
        np.save(out / "q.npy", np.concatenate([d.q.astype(np.float64) for d in demos], 0))
        context_rows = {k: ragged(f"ctx_{k}", [np.asarray(d.contexts[k], dtype=np.float64) for d in demos])
                        for k in sorted(self.first.contexts)}
        image_rows = ragged("images", [d.images for d in demos]) if self.first.images is not None else 0
        np.save(out / "names.npy", np.array([d.name for d in demos]))
        self.shards.append({"dir": name, "first": self.n - len(demos), "n_demos": len(demos), "rows": rows,
                            "context_rows": context_rows, "image_rows": image_rows})

    def close(self) -> dict:
        self.flush()
        if self.first is None:
            raise DatasetError(f"sharded dataset '{self.folder}': no demonstrations to write; expected at least one")
        f = self.first
        index = {"format": FORMAT, "version": VERSION, "joint_names": list(f.joint_names),
                 "phase_type": f.phase_type,
                 "context_dims": {k: int(v.shape[1]) for k, v in sorted(f.contexts.items())},
                 "image_shape": None if f.images is None else [int(f.images.shape[1]), int(f.images.shape[2])],
                 "max_contexts": self.max_contexts, "max_images": self.max_images, "n_demos": self.n,
                 "shards": self.shards}
        tmp = self.folder / (INDEX + ".part")
        tmp.write_text(json.dumps(index, indent=1))
        tmp.replace(self.folder / INDEX)  # the index last: a folder without it is no dataset
        return index


def _shard_dir(name) -> str:
    """A shard's folder as the index names it: one plain name inside the dataset's folder."""
    if not isinstance(name, str) or name in ("", ".", "..") or pathlib.PurePath(name).name != name or "\\" in name:
        raise ValueError(f"shard dir {name!r} is not a folder name inside the dataset")
    return name


def _dims(demo: Demonstration) -> dict[str, int]:
    return {k: int(v.shape[1]) for k, v in sorted(demo.contexts.items())}


def write_shards(demos: Iterable[Demonstration], folder: str | pathlib.Path,
                 shard_size: int = DEFAULT_SHARD_SIZE) -> ShardedDataset:
    """Write ``demos`` (any iterable, consumed once; at most ``shard_size`` demos held at a time) as a
    sharded dataset in ``folder`` (created; it must not hold a dataset yet) and open it."""
    folder = pathlib.Path(folder)
    if shard_size < 1:
        raise DatasetError(f"shard_size = {shard_size}: expected at least 1 demonstration per shard")
    if folder.exists() and any(folder.iterdir()):
        raise DatasetError(f"output folder '{folder}' is not empty; expected a new or empty folder")
    existed = folder.is_dir()
    folder.mkdir(parents=True, exist_ok=True)
    writer = _ShardWriter(folder, shard_size)
    try:
        for demo in demos:
            writer.add(demo)
        writer.close()
    except BaseException:  # no half dataset left behind; a folder that was there before stays, empty
        for part in list(folder.iterdir()) if existed else [folder]:
            if part.is_dir():
                shutil.rmtree(part, ignore_errors=True)
            else:
                part.unlink(missing_ok=True)
        raise
    return ShardedDataset(folder)


def _folder_demos(folder: pathlib.Path) -> Iterator[Demonstration]:
    files = sorted(list(folder.glob("*.npz")) + list(folder.glob("*.csv")))
    if not files:
        raise DatasetError(f"dataset folder '{folder}' has no .npz or .csv demonstrations")
    for f in files:  # the order of deepprompt_ros.data.demo_dataset.load_dataset
        yield load_demo(f) if f.suffix == ".npz" else load_csv(f)


def convert_folder(src: str | pathlib.Path, dst: str | pathlib.Path,
                   shard_size: int = DEFAULT_SHARD_SIZE) -> ShardedDataset:
    """Convert a documented folder of ``.npz``/``.csv`` demonstrations to a sharded dataset, one
    demonstration read at a time; the demos keep the order of
    :func:`~deepprompt_ros.data.demo_dataset.load_dataset`."""
    src = pathlib.Path(src)
    if not src.is_dir():
        raise DatasetError(f"dataset folder '{src}' does not exist; expected a folder of .npz/.csv demonstrations")
    return write_shards(_folder_demos(src), dst, shard_size)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="shard_dataset", description="Convert a folder of .npz/.csv demonstrations "
                                 "to a sharded dataset that train --data reads lazily.")
    ap.add_argument("src", help="folder of .npz/.csv demonstrations (deepprompt_ros.data.demonstration)")
    ap.add_argument("dst", help="output folder (new or empty)")
    ap.add_argument("--shard-size", type=int, default=DEFAULT_SHARD_SIZE,
                    help=f"demonstrations per shard (default {DEFAULT_SHARD_SIZE})")
    args = ap.parse_args(argv)
    try:
        ds = convert_folder(args.src, args.dst, args.shard_size)
    except DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {len(ds)} demonstrations in {len(ds.shards)} shards to {pathlib.Path(args.dst).resolve()}: "
          f"joints {list(ds.joint_names)}, contexts {ds.context_dims or 'none'}, images {ds.image_shape or 'none'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
