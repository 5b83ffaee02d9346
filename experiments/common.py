"""Shared pieces of the experiment harness: run sizes, task datasets, training configs, tables.

Tasks are named. Built-in generators (no simulator needed) are always available; the PyBullet task
datasets of :mod:`deepprompt_ros.sim.tasks.registry` (``make_task(name, split, quick, seed)``) plug in by
name when that module exists — it is imported lazily, only when one of its tasks is asked for.

==================  ==========================================================================
task                data
==================  ==========================================================================
``gen3_lite_reach`` :func:`sim.tasks.kinematic_reach.reach_demos` on the Kinova Gen3 lite (6 joints),
                    context ``object`` (3,) — the object position; no images
``wam_reach``       the same reaching demonstrator on the Barrett WAM (7 joints), context ``object``
``bimodal_sine``    :func:`data.synthetic.bimodal_sine` (1 joint, two modes), context ``mode`` (1,)
``reach``,          :func:`sim.tasks.registry.make_task` (PyBullet analogues of the paper's RLBench tasks on
``close_box``,      the WAM, and the Kinova pick-and-place; contexts and camera images), when
``pour``,           ``deepprompt_ros/sim/tasks/registry.py`` exists; generated splits are cached on disk
``kinova_pick_place`` (:func:`cached_task_split`)
==================  ==========================================================================

Length: over 400 lines because it is the harness every experiment imports as one: run sizes, the
task datasets with their on-disk cache and the digests that key it, training configs, and the
tables and output files. About a third is the cache (digests of data and code); the rest are
small helpers that a split would scatter without making any of them clearer.
"""
from __future__ import annotations

import dataclasses
import hashlib
import importlib.util
import json
import math
import os
import pathlib
import tempfile
import time
from typing import Callable, Mapping, Sequence

import numpy as np

from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.data.synthetic import bimodal_sine
from deepprompt_ros.training.config import TrainConfig

ROOT = pathlib.Path(__file__).resolve().parents[1]
MODELS = ROOT / "models"
PYBULLET_TASKS = ("reach", "close_box", "pour", "kinova_pick_place")
# Latent sizes of the paper (Sec. IV): 16 for Reach and Kinova, 32 for Close Box and Pour Water.
PAPER_LATENT_DIM = {"reach": 16, "kinova_pick_place": 16, "close_box": 32, "pour": 32}
# Seeds of the generated data: training / validation / test demonstrations come from one generated
# set split in that order; the models' own seeds never change the data.
DATA_SEED = 1000


@dataclasses.dataclass(frozen=True)
class Scale:
    """How big a run is: ``tiny`` (the smoke test), ``quick`` (≲ 2 min), ``medium`` (the run documented
    in EXPERIMENTS.md), ``full`` (the paper's sizes).

    Attributes
    ----------
    recon_tasks : task names of the reconstruction experiment; () = :func:`default_tasks`
    recon_seeds : models trained per (task, model) — ProMP: bootstrap resamples of the training set
    recon_steps, recon_val_every : updates per deep model and validation period
    builtin_sizes : (n_train, n_val, n_test) demonstrations of a built-in task
    task_sizes : (n_train, n_val, n_test) of a PyBullet task; None = ``make_task``'s own sizes
    task_quick : ``make_task(..., quick=)`` (its quick sizes and no simulation)
    max_test : at most this many test demonstrations are reconstructed (0 = all)
    refine_sets, refine_n_via, refine_budgets : refinement sets per N, the N's, iteration budgets
    rhythmic_cycles : cycles shown in the rhythmic experiment
    small_task, small_* : small-data experiment task and sizes
    goal_sets, goal_samples : the goals' random planner via-point sets per model and samples per
        conditioning (:func:`experiments.goal_metrics.measure`)
    """

    name: str
    recon_tasks: tuple[str, ...] = ()
    recon_seeds: int = 2
    recon_steps: int = 150
    recon_val_every: int = 50
    builtin_sizes: tuple[int, int, int] = (60, 15, 30)
    task_sizes: tuple[int, int, int] | None = None
    task_quick: bool = True
    max_test: int = 0
    refine_sets: int = 4
    refine_n_via: tuple[int, ...] = (1, 5, 50)
    refine_budgets: tuple[int, ...] = (1, 3, 10, 30, 200)
    rhythmic_cycles: int = 3
    rhythmic_train_steps: int = 300
    small_task: str = "wam_reach"
    small_n_train: int = 30
    small_n_test: int = 10
    small_seeds: int = 1
    small_steps: int = 150
    goal_sets: int = 50
    goal_samples: int = 50


SCALES = {
    "tiny": Scale("tiny", recon_tasks=("gen3_lite_reach",), recon_seeds=2, recon_steps=30, recon_val_every=15,
                  builtin_sizes=(40, 8, 10), refine_sets=2, refine_budgets=(1, 10, 200), small_n_test=5,
                  small_steps=30, rhythmic_train_steps=60, goal_sets=10, goal_samples=20),
    "quick": Scale("quick", recon_tasks=("gen3_lite_reach",), recon_seeds=2, recon_steps=100, recon_val_every=50,
                   builtin_sizes=(60, 15, 25), refine_sets=3, refine_budgets=(1, 3, 10, 200), small_n_test=10,
                   small_steps=150, goal_sets=20),
    "medium": Scale("medium", recon_seeds=2, recon_steps=500, recon_val_every=100, builtin_sizes=(100, 20, 50),
                    task_sizes=(60, 15, 30), task_quick=False, refine_sets=20,
                    refine_budgets=(1, 2, 3, 5, 10, 20, 50, 100, 200), small_task="close_box", small_n_test=30,
                    small_seeds=3, small_steps=1500, rhythmic_train_steps=3000, goal_sets=100),
    "full": Scale("full", recon_seeds=3, recon_steps=2000, recon_val_every=250, builtin_sizes=(200, 50, 100),
                  task_sizes=(200, 50, 100), task_quick=False, refine_sets=50,
                  refine_budgets=(1, 2, 3, 5, 10, 20, 50, 100, 200), small_task="close_box", small_n_test=50,
                  small_seeds=3, small_steps=3000, rhythmic_train_steps=3000, goal_sets=100),
}


# ------------------------------------------------------------------------------------------------
# Tasks
# ------------------------------------------------------------------------------------------------

def _reach(robot: str) -> Callable[[int, int], DemoDataset]:
    def make(n: int, seed: int) -> DemoDataset:
        from deepprompt_ros.sim.tasks.kinematic_reach import reach_demos  # pinocchio: imported when used

        return reach_demos(robot, n_demos=n, seed=seed)
    return make


BUILTIN_TASKS: dict[str, Callable[[int, int], DemoDataset]] = {
    "gen3_lite_reach": _reach("gen3_lite"),
    "wam_reach": _reach("wam"),
    "bimodal_sine": lambda n, seed: bimodal_sine(n_demos=n, seed=seed),
}


def pybullet_tasks_available() -> bool:
    """True when ``deepprompt_ros/sim/tasks/registry.py`` exists (checked without importing it)."""
    return importlib.util.find_spec("deepprompt_ros.sim.tasks.registry") is not None


def default_tasks(scale: Scale) -> tuple[str, ...]:
    """The task list when none is given: ``scale.recon_tasks`` if set, else the PyBullet tasks (when
    ``deepprompt_ros/sim/tasks/registry.py`` exists) followed by the built-in ``gen3_lite_reach`` and
    ``bimodal_sine``."""
    if scale.recon_tasks:
        return scale.recon_tasks
    return (PYBULLET_TASKS if pybullet_tasks_available() else ()) + ("gen3_lite_reach", "bimodal_sine")


def small_data_task(scale: Scale) -> str:
    """``scale.small_task``, or the built-in 7-joint ``wam_reach`` if it is a PyBullet task that is missing."""
    if scale.small_task in PYBULLET_TASKS and not pybullet_tasks_available():
        return "wam_reach"
    return scale.small_task


@dataclasses.dataclass(frozen=True)
class TaskData:
    name: str
    train: DemoDataset
    val: DemoDataset
    test: DemoDataset


def _subset(ds: DemoDataset, idx: Sequence[int], tag: str) -> DemoDataset:
    return DemoDataset(tuple(ds.demos[i] for i in idx), f"{ds.source}:{tag}")


def load_task(name: str, scale: Scale, sizes: tuple[int, int, int] | None = None) -> TaskData:
    """Train / validation / test demonstrations of task ``name``.

    Built-in tasks: one set of n_train + n_val + n_test demos generated with seed :data:`DATA_SEED`,
    split in that order. PyBullet tasks: ``make_task(name, split=..., n=..., quick=scale.task_quick,
    seed=0)`` (``n`` from ``sizes`` or ``scale.task_sizes``; None = the task's own sizes), cached on disk
    by :func:`cached_task_split`. The test set is cut to ``scale.max_test`` demos when that is > 0.
    """
    if name in BUILTIN_TASKS:
        n_tr, n_va, n_te = sizes or scale.builtin_sizes
        ds = BUILTIN_TASKS[name](n_tr + n_va + n_te, DATA_SEED)
        tr = _subset(ds, range(n_tr), "train")
        va = _subset(ds, range(n_tr, n_tr + n_va), "val")
        te = _subset(ds, range(n_tr + n_va, n_tr + n_va + n_te), "test")
    elif name in PYBULLET_TASKS:
        if not pybullet_tasks_available():
            raise ValueError(f"task '{name}' needs deepprompt_ros/sim/tasks/registry.py (make_task), which is not there; "
                             f"built-in tasks: {sorted(BUILTIN_TASKS)}")
        sz = sizes or scale.task_sizes or (None, None, None)
        tr, va, te = (cached_task_split(name, s, n, scale.task_quick) for s, n in zip(("train", "val", "test"), sz))
    else:
        raise ValueError(f"unknown task '{name}'; expected one of {sorted(BUILTIN_TASKS)} or the PyBullet tasks "
                         f"{list(PYBULLET_TASKS)}")
    if scale.max_test and len(te) > scale.max_test:
        te = _subset(te, range(scale.max_test), f"first{scale.max_test}")
    return TaskData(name, tr, va, te)


DATA_CACHE_ENV = ("DEEPPROMPT_DATA_CACHE", "DEEPPROMPT_EXPERIMENTS_DATA")  # the second: its former name
_DATA_CACHE: list[pathlib.Path] = []  # set by set_data_cache_dir (experiments/run.py: <out>/data_cache)


def data_cache_dir() -> pathlib.Path:
    """Where generated PyBullet task splits are kept between runs: the folder given to
    :func:`set_data_cache_dir` (``experiments/run.py`` gives ``--data-cache``, ``$DEEPPROMPT_DATA_CACHE``
    or ``<out>/data_cache``), else ``$DEEPPROMPT_DATA_CACHE`` (or its former name
    ``$DEEPPROMPT_EXPERIMENTS_DATA``), else ``<tmp>/deepprompt_experiments_data``."""
    if _DATA_CACHE:
        return _DATA_CACHE[-1]
    env = env_data_cache_dir()
    return env if env else pathlib.Path(tempfile.gettempdir()) / "deepprompt_experiments_data"


def env_data_cache_dir() -> pathlib.Path | None:
    """The data cache folder named by the environment (:data:`DATA_CACHE_ENV`), or None."""
    env = next((os.environ[k] for k in DATA_CACHE_ENV if os.environ.get(k)), None)
    return pathlib.Path(env) if env else None


def set_data_cache_dir(folder: str | pathlib.Path | None) -> None:
    """Use ``folder`` as :func:`data_cache_dir` from now on (None: back to the environment / tmp default)."""
    _DATA_CACHE.clear()
    if folder is not None:
        _DATA_CACHE.append(pathlib.Path(folder))


def file_digest(paths: Sequence[pathlib.Path]) -> str:
    """sha1 (10 hex digits) of the files' names (relative to the project root when inside it) and bytes."""
    h = hashlib.sha1()
    for f in sorted(pathlib.Path(p).resolve() for p in paths):
        name = f.relative_to(ROOT) if f.is_relative_to(ROOT) else f.name
        h.update(f"{name}\0".encode())
        h.update(f.read_bytes())
        h.update(b"\0")
    return h.hexdigest()[:10]


_SOURCE_DIGESTS: dict[tuple[str, ...], str] = {}


def source_digest(patterns: Sequence[str]) -> str:
    """:func:`file_digest` of the files matching the glob ``patterns`` (relative to the project root),
    taken once per process, like :func:`_tasks_module`'s: the code that computes a result is the code
    in memory, even if the files change later."""
    patterns = tuple(patterns)
    if patterns not in _SOURCE_DIGESTS:
        files = sorted({f for pat in patterns for f in ROOT.glob(pat) if f.is_file()})
        if not files:
            raise FileNotFoundError(f"no source files match {list(patterns)} under {ROOT}")
        _SOURCE_DIGESTS[patterns] = file_digest(files)
    return _SOURCE_DIGESTS[patterns]



def code_parts(patterns: Sequence[str]) -> dict:
    """The parts of a unit's key that identify the code computing it: the :func:`source_digest` of
    ``patterns`` and the torch / numpy versions."""
    import torch

    return {"sources": source_digest(patterns), "versions": {"torch": torch.__version__, "numpy": np.__version__}}

_TASKS: list = []


def import_closure(module: str) -> list[pathlib.Path]:
    """Source files of package module ``module`` and of every package module it imports, directly or
    through others (imports inside functions and the ``__init__.py`` of each package on the way
    included, except ``deepprompt_ros/__init__.py``), found by parsing the sources without importing
    them."""
    import ast

    def source(name: str) -> pathlib.Path | None:
        base = ROOT.joinpath(*name.split("."))
        return next((f for f in (base.with_suffix(".py"), base / "__init__.py") if f.is_file()), None)

    files: dict[str, pathlib.Path] = {}
    todo = [module]
    while todo:
        name = todo.pop()
        if name in files or not name.startswith("deepprompt_ros"):
            continue
        path = source(name)
        if path is None:  # a name imported from a module, not a module
            continue
        files[name] = path
        if "." in name.rpartition(".")[0]:  # its package's __init__ runs first (the top package's
            todo.append(name.rpartition(".")[0])  # holds only the lazy export table)
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                todo += [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                todo += [node.module] + [f"{node.module}.{a.name}" for a in node.names]
    return sorted(files.values())


def _tasks_module():
    """(:mod:`deepprompt_ros.sim.tasks.registry`, digest of the code and robot models that generate
    its data) — the digest taken once, when the module is first imported here: the code that
    generates the data is the code in memory, even if the files change later. The digest covers the
    whole ``sim/tasks`` package, every package module the registry imports, directly or not (the
    simulation, robot models, IK, geometry, the data format), and the URDF of each task's robot."""
    if not _TASKS:
        from deepprompt_ros.robots.spec import urdf_path
        from deepprompt_ros.sim.tasks import registry as tasks

        files = set(import_closure(tasks.__name__)) | set(ROOT.glob("deepprompt_ros/sim/tasks/**/*.py"))
        files |= {urdf_path(t.robot) for t in tasks.TASKS.values()}
        _TASKS.append((tasks, file_digest(sorted(files))))
    return _TASKS[0]


def cached_task_split(name: str, split: str, n: int | None, quick: bool, seed: int = 0) -> DemoDataset:
    """``sim.tasks.registry.make_task(name, split, n, quick, seed)``, generated once and then read from
    :func:`data_cache_dir` (the key includes the digest of the generating code of
    :func:`_tasks_module`, so a changed generator is never read from a stale cache). Each cache entry
    keeps ``cache_info.json`` (the dataset's source and the generation time, s), so a read entry has
    the source of the generated one."""
    from deepprompt_ros.data.demo_dataset import load_dataset

    tasks, digest = _tasks_module()
    folder = data_cache_dir() / f"{name}_{split}_n{n}_q{int(quick)}_s{seed}_{digest}"
    if not folder.is_dir():
        t0 = time.perf_counter()
        ds = tasks.make_task(name, split=split, n=n, quick=quick, seed=seed)
        gen_s = time.perf_counter() - t0
        part = folder.with_name(folder.name + f".part{os.getpid()}")
        ds.save(part)
        (part / "cache_info.json").write_text(json.dumps({"source": ds.source, "generate_s": gen_s}) + "\n")
        part.rename(folder)  # a crash never leaves a half-written cache entry under the final name
    info = folder / "cache_info.json"
    source = json.loads(info.read_text())["source"] if info.is_file() else None
    ds = load_dataset(folder)
    return DemoDataset(ds.demos, source or ds.source)


def dataset_digest(datasets: Sequence[DemoDataset]) -> str:
    """sha1 (12 hex digits) of the contents of ``datasets`` in order: every demonstration's name,
    time stamps, joint positions, joint names, phase type, contexts and images (not the ``source``
    label, which names a cache folder when the data were read from one)."""
    h = hashlib.sha1()

    def arr(a) -> None:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())

    for ds in datasets:
        h.update(f"dataset {len(ds)}\0".encode())
        for d in ds.demos:
            h.update(f"{d.name}\0{d.phase_type}\0{'|'.join(d.joint_names)}\0".encode())
            arr(d.t)
            arr(d.q)
            for k in sorted(d.contexts):
                h.update(f"ctx {k}\0".encode())
                arr(d.contexts[k])
            if d.images is not None:
                arr(d.images)
    return h.hexdigest()[:12]


def base_train_config(path: str | pathlib.Path | None = None) -> TrainConfig:
    """The deep models' base configuration: ``path`` (a TrainConfig YAML, used as is), or the shipped
    ``config/train_gen3_lite_reach.yaml`` (Neural-Process objective, Adam lr 1e-3) with the paper's
    mini-batches of 16 and ``train``'s default decoder selection (``auto_select``, as the file sets for
    the served reach model)."""
    if path:
        return TrainConfig.from_yaml(path)
    return dataclasses.replace(TrainConfig.from_yaml(ROOT / "config" / "train_gen3_lite_reach.yaml"), batch_size=16,
                               auto_select=True)


def train_config(base: TrainConfig, steps: int, val_every: int, seed: int, task: str | None = None) -> TrainConfig:
    """``base`` with the run's steps / seed, one torch thread, KL annealing over at most a quarter of
    the updates, and the paper's latent size for the paper's tasks."""
    kw = dict(steps=steps, val_every=min(val_every, steps), seed=seed, threads=1,
              kl_anneal_steps=max(1, min(base.kl_anneal_steps, steps // 4)))
    if task in PAPER_LATENT_DIM:
        kw["latent_dim"] = PAPER_LATENT_DIM[task]
    return dataclasses.replace(base, **kw)


# ------------------------------------------------------------------------------------------------
# Statistics and tables
# ------------------------------------------------------------------------------------------------

def mean_se(values: Sequence[float]) -> tuple[float, float]:
    """Mean and standard error (sample std / √n; NaN for n < 2) of finite values."""
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return float("nan"), float("nan")
    se = float(v.std(ddof=1) / math.sqrt(v.size)) if v.size > 1 else float("nan")
    return float(v.mean()), se


def fmt(x: float, digits: int = 2) -> str:
    if x is None or not math.isfinite(x):
        return "—"
    return f"{x:.{digits}e}"


def fmt_pm(mean: float, se: float) -> str:
    if mean is None or not math.isfinite(mean):
        return "—"
    return f"{mean:.2e} ± {se:.1e}" if math.isfinite(se) else f"{mean:.2e}"


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out) + "\n"


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if dataclasses.is_dataclass(o):
        return dataclasses.asdict(o)
    if isinstance(o, pathlib.Path):
        return str(o)
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


def write_outputs(out: pathlib.Path, stem: str, data: Mapping, markdown: str) -> list[pathlib.Path]:
    """``<out>/<stem>.json`` (NaN written as null) and ``<out>/<stem>.md``."""
    out.mkdir(parents=True, exist_ok=True)
    js = out / f"{stem}.json"
    js.write_text(json.dumps(_nan_to_none(data), indent=1, default=_json_default, allow_nan=False) + "\n")
    md = out / f"{stem}.md"
    md.write_text(markdown)
    return [js, md]


def _nan_to_none(o):
    if isinstance(o, float) and not math.isfinite(o):
        return None
    if isinstance(o, Mapping):
        return {str(k): _nan_to_none(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_nan_to_none(v) for v in o]
    if isinstance(o, np.ndarray):
        return _nan_to_none(o.tolist())
    if isinstance(o, np.floating):
        return _nan_to_none(float(o))
    return o
