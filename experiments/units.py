"""Resumable, optionally parallel experiment units.

An experiment that loops over independent pieces of work (reconstruction: task × model × seed) makes
each piece a :class:`Unit`: a name, the ``parts`` that determine its result (configuration, data
digest, source digest, ...) and the arguments of a module-level function ``fn(shared, *args)``.
:func:`run_units` reads the finished units from a :class:`UnitCache` — one JSON file per unit,
``<folder>/<name>__<key>.json`` with ``key`` = :func:`unit_key` of the parts, written atomically
(temp file + rename) as soon as the unit is done — and computes only the missing ones, in this
process or in ``jobs`` worker processes (``spawn`` context, one torch / BLAS thread each). A run that
is stopped loses only the units in progress; the same command continues it. A unit computed in a
worker is the same computation as in this process (the functions seed themselves), so the results
do not depend on ``jobs``; ``test/test_experiments.py`` checks it.

This module decides where and when units run, never what they compute: it is not part of the units'
keys (the experiments hash their own sources, :func:`experiments.common.source_digest`). With
``jobs`` > 1 the calling script must guard its entry point (``if __name__ == "__main__":``), as
``spawn`` imports it in every worker; ``experiments/run.py`` does.
"""
from __future__ import annotations

import contextlib
import dataclasses
import datetime
import hashlib
import json
import multiprocessing
import os
import pathlib
import time
from typing import Any, Callable, Mapping, Sequence

THREAD_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def _json_default(o):
    from .common import _json_default as default

    return default(o)


def unit_key(parts: Mapping) -> str:
    """sha1 (12 hex digits) of ``parts`` as canonical JSON (sorted keys)."""
    text = json.dumps(parts, sort_keys=True, default=_json_default, separators=(",", ":"))
    return hashlib.sha1(text.encode()).hexdigest()[:12]


@dataclasses.dataclass(frozen=True)
class Unit:
    """One independent piece of an experiment: ``fn(shared, *args)`` gives its result (JSON-able).

    ``name`` is the stem of its cache file (``<task>__<kind>__s<seed>``); ``parts`` is everything that
    determines the result — two units with equal parts have equal results."""

    name: str
    parts: Mapping
    args: tuple = ()
    cost: float = 1.0  # relative cost: costly units are started first (not part of the key)

    @property
    def key(self) -> str:
        return unit_key(self.parts)


class UnitCache:
    """Finished units of one experiment, one JSON file each under ``folder``:
    ``{"name", "key", "parts", "result", "wall_s", "finished"}``. ``folder`` None: nothing is read or
    written. ``fresh``: nothing is read (every unit is computed again and its file overwritten)."""

    def __init__(self, folder: str | pathlib.Path | None, fresh: bool = False):
        self.folder = pathlib.Path(folder) if folder is not None else None
        self.fresh = fresh

    def sub(self, name: str) -> "UnitCache":
        """The cache of experiment ``name``: ``<folder>/<name>``."""
        return UnitCache(None if self.folder is None else self.folder / name, self.fresh)

    def path(self, unit: Unit) -> pathlib.Path | None:
        return None if self.folder is None else self.folder / f"{unit.name}__{unit.key}.json"

    def get(self, unit: Unit) -> dict | None:
        """The stored record of ``unit`` (same name and key), or None."""
        p = self.path(unit)
        if p is None or self.fresh or not p.is_file():
            return None
        try:
            rec = json.loads(p.read_text())
        except (OSError, ValueError):
            return None  # unreadable: computed again (and overwritten)
        return rec if rec.get("key") == unit.key and "result" in rec else None

    def put(self, unit: Unit, result: Any, wall_s: float) -> pathlib.Path | None:
        """Write the record of ``unit`` atomically (temp file, fsync, rename)."""
        p = self.path(unit)
        if p is None:
            return None
        p.parent.mkdir(parents=True, exist_ok=True)
        rec = {"name": unit.name, "key": unit.key, "parts": unit.parts, "result": result, "wall_s": wall_s,
               "finished": datetime.datetime.now().astimezone().isoformat(timespec="seconds")}
        tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
        with open(tmp, "w") as f:
            f.write(json.dumps(rec, indent=1, default=_json_default) + "\n")  # NaN kept (read back as NaN)
            f.flush()
            os.fsync(f.fileno())
        tmp.replace(p)
        return p


@dataclasses.dataclass
class UnitReport:
    """What :func:`run_units` did: units reused from the cache and computed now; ``compute_s`` sums the
    wall time of every unit of the result (whichever invocation computed it), ``computed_s`` that of
    the units computed now."""

    units: int = 0
    reused: int = 0
    computed: int = 0
    compute_s: float = 0.0
    computed_s: float = 0.0
    jobs: int = 1
    folder: str | None = None

    def add(self, other: "UnitReport") -> "UnitReport":
        return UnitReport(self.units + other.units, self.reused + other.reused, self.computed + other.computed,
                          self.compute_s + other.compute_s, self.computed_s + other.computed_s,
                          max(self.jobs, other.jobs), self.folder or other.folder)

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


# ------------------------------------------------------------------------------------------------
# Worker processes
# ------------------------------------------------------------------------------------------------

_WORKER: dict = {}


def _init_worker(shared, sources: tuple[str, ...]) -> None:
    import torch

    torch.set_num_threads(1)
    _WORKER["shared"] = shared
    _WORKER["sources"] = sources


def _source_digest(sources: tuple[str, ...]) -> str | None:
    from .common import source_digest

    return source_digest(sources) if sources else None


def _call(job: tuple[int, Callable, tuple]) -> tuple[int, Any, float, str | None]:
    i, fn, args = job
    t0 = time.perf_counter()
    result = fn(_WORKER["shared"], *args)
    return i, result, time.perf_counter() - t0, _source_digest(_WORKER["sources"])


@contextlib.contextmanager
def _one_thread_env():
    """OPENBLAS / OMP / MKL threads = 1 in the environment the workers are started with."""
    old = {k: os.environ.get(k) for k in THREAD_ENV}
    os.environ.update({k: "1" for k in THREAD_ENV})
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def run_units(units: Sequence[Unit], fn: Callable, shared: Any, cache: UnitCache | None = None, jobs: int = 1,
              sources: Sequence[str] = (), on_result: Callable[[Unit, Any, bool, float], None] | None = None,
              log: Callable[[str], None] = print) -> tuple[list, UnitReport]:
    """Results of ``fn(shared, *unit.args)`` for every unit, in the order of ``units``.

    Units found in ``cache`` are read; the others are computed in this process (``jobs`` 1) or in
    ``min(jobs, missing)`` spawned worker processes, each given ``shared`` once and one torch thread,
    and stored in ``cache`` as each finishes. ``sources``: glob patterns whose
    :func:`common.source_digest` the units' parts include; a worker that sees other sources (files
    edited during the run) is an error. ``on_result(unit, result, reused, wall_s)`` is called for
    each unit as its result is known (reused ones first, in order; computed ones as they finish).
    """
    if jobs < 1:
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    cache = cache or UnitCache(None)
    results: list = [None] * len(units)
    report = UnitReport(units=len(units), jobs=jobs, folder=None if cache.folder is None else str(cache.folder))
    records = [cache.get(u) for u in units]
    todo = [i for i, rec in enumerate(records) if rec is None]
    n_workers = min(jobs, len(todo))
    if n_workers > 1:
        todo.sort(key=lambda i: -units[i].cost)  # costly units first: less idle time at the end
    if units:
        msg = f"  units: {len(units)}, {len(units) - len(todo)} reused"
        if len(todo) < len(units):
            msg += f" from {cache.folder}"
        if todo:
            msg += f", {len(todo)} to compute" + (f" in {n_workers} worker processes" if n_workers > 1 else "")
        log(msg)
    for i, (u, rec) in enumerate(zip(units, records)):
        if rec is None:
            continue
        results[i] = rec["result"]
        wall_s = float(rec.get("wall_s") or 0.0)
        report.reused += 1
        report.compute_s += wall_s
        if on_result:
            on_result(u, rec["result"], True, wall_s)
    want = _source_digest(tuple(sources))

    def done(i: int, result: Any, wall_s: float) -> None:
        # as it will be read back from the cache: a fresh and a resumed run give the same objects
        result = json.loads(json.dumps(result, default=_json_default))
        results[i] = result
        cache.put(units[i], result, wall_s)
        report.computed += 1
        report.compute_s += wall_s
        report.computed_s += wall_s
        if on_result:
            on_result(units[i], result, False, wall_s)

    if n_workers <= 1:
        for i in todo:
            t0 = time.perf_counter()
            result = fn(shared, *units[i].args)
            done(i, result, time.perf_counter() - t0)
        return results, report
    ctx = multiprocessing.get_context("spawn")
    with _one_thread_env(), ctx.Pool(n_workers, initializer=_init_worker,
                                     initargs=(shared, tuple(sources))) as pool:
        for i, result, wall_s, digest in pool.imap_unordered(_call, [(i, fn, units[i].args) for i in todo]):
            if digest != want:
                raise RuntimeError(f"unit {units[i].name}: the worker's sources (digest {digest}) differ from this "
                                   f"process's ({want}) — were files edited during the run?")
            done(i, result, wall_s)
    return results, report
