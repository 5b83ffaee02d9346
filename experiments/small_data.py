"""Experiment 4 — small data: ~30 demonstrations of a 7-joint task.

DeepProMP and ProMP are trained on ``n_train`` demonstrations (both hold out the same 10 % for
validation) and reconstruct held-out demonstrations from ``n_via`` random via-points per demo
(:func:`deepprompt_ros.evaluation.reconstruction.reconstruction_mse` with ``n_via``: the same seeded
points for every model):

``promp``                ProMP conditioned on the via-points (closed form; its regularizer and via-point
                         noise cross-validated on its training demos, the baseline's default)
``deepprompt``           DeepProMP conditioned on the via-points by its default path
                         (:meth:`DeepProMP.condition`), the mean trajectory
``deepprompt_refined``   the same, after :meth:`DeepProMP.refine` through the via-points (executed
                         trajectory μ_y(μ̃, x))
``deepprompt_map``       the same, after MAP refinement (:meth:`DeepProMP.refine_map`, prior ``map_prior``):
                         the regularized least-squares latent. Via-point noise: the model's ``via_noise``
                         (chosen by the training's cross-validation) for a decoder with a linear part;
                         otherwise f·σ_y·RMS(joint std) with f chosen from ``map_noise_factors`` on the
                         VALIDATION demos of the training split (never on the test demos)
``deepprompt_map_linear`` (residual decoders) the same MAP with the MLP residual switched off
``*_start``              conditioned on the start point only (x = 0)

:func:`run` trains the base configuration as it is — with ``auto_select`` (the default), the
training chooses the decoder's linear part, its latent size, regularizer and via-point noise by
cross-validation on its training demos and keeps or drops the MLP residual on its validation demos
(:mod:`deepprompt_ros.training.selection`; the choices are in each seed's ``selection``) — and, as the
reference, the same configuration with ``auto_select`` false (the base config's plain MLP decoder).

Call :func:`small_data` with any :class:`TrainConfig` to measure a change of the model or its training::

    from experiments.small_data import small_data
    res = small_data(TrainConfig(steps=4000, threads=1), seeds=(0, 1, 2))
    print(res.markdown())
"""
from __future__ import annotations

import dataclasses
import pathlib
import time
from typing import Callable, Sequence

import numpy as np

from deepprompt_ros.baselines.deep_promp_model import DeepProMPModel
from deepprompt_ros.baselines.promp_model import ProMPModel
from deepprompt_ros.evaluation.reconstruction import reconstruction_mse
from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.training.config import TrainConfig

from . import common
from .common import Scale
from .units import Unit, UnitCache, UnitReport, run_units

METHODS = ("promp", "deepprompt", "deepprompt_refined", "deepprompt_map", "deepprompt_map_linear", "promp_start",
           "deepprompt_start")
LABELS = {"promp": "ProMP, {n} via-points", "deepprompt": "DeepProMP, {n} via-points",
          "deepprompt_refined": "DeepProMP, {n} via-points + refinement",
          "deepprompt_map": "DeepProMP, {n} via-points + MAP refinement",
          "deepprompt_map_linear": "DeepProMP, {n} via-points + MAP refinement, MLP residual off",
          "promp_start": "ProMP, start point only",
          "deepprompt_start": "DeepProMP, start point only"}


@dataclasses.dataclass(frozen=True)
class SmallDataResult:
    """Per-seed held-out MSEs (rad²) of each method; ``check`` holds the DeepProMP 5-via-point MSE
    recomputed by this module's own loop (must equal ``deepprompt``: same via-points)."""

    task: str
    n_joints: int
    n_train: int
    n_test: int
    n_via: int
    seeds: tuple[int, ...]
    mse: dict  # method -> list over seeds
    check: list
    refine_reachable: list  # fraction of test demos whose via-points refinement met 1e-6 rad, per seed
    fit_s: list
    config: dict
    map_noise_factor: list = dataclasses.field(default_factory=list)  # f chosen on the validation demos, per seed
    map_prior: str = "standard"
    map_noise_std: list = dataclasses.field(default_factory=list)  # the MAP via-point noise used (rad, per joint), per seed
    # the training's model selection (auto_select; its checkpoint's "selection" metadata), per seed, or [] without it
    selection: list = dataclasses.field(default_factory=list)
    residual_used: list = dataclasses.field(default_factory=list)  # residual scale of the trained model, per seed
    promp_selection: dict = dataclasses.field(default_factory=dict)  # ProMP's cross-validated regularizer and noise
    units: dict = dataclasses.field(default_factory=dict, repr=False, compare=False)  # UnitReport; not in to_json

    def stats(self) -> dict:
        return {m: dict(zip(("mean", "se"), common.mean_se(v))) for m, v in self.mse.items()}

    def ratios(self) -> dict:
        s = self.stats()
        p = s["promp"]["mean"]
        return {"deepprompt/promp": s["deepprompt"]["mean"] / p,
                "deepprompt_refined/promp": s["deepprompt_refined"]["mean"] / p,
                "deepprompt_map/promp": s["deepprompt_map"]["mean"] / p,
                "deepprompt_start/promp_start": s["deepprompt_start"]["mean"] / s["promp_start"]["mean"]}

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        del d["units"]
        return {**d, "stats": self.stats(), "ratios": self.ratios()}

    def markdown(self) -> str:
        s = self.stats()
        rows = [[LABELS[m].format(n=self.n_via), common.fmt_pm(s[m]["mean"], s[m]["se"]),
                 f"{s[m]['mean'] / s['promp' if 'start' not in m else 'promp_start']['mean']:.2f}"] for m in METHODS
                if m in s]
        r = self.ratios()
        c = self.config
        dec = (f"decoder: residual over {c['decoder_basis']} RBFs (`basis_init` {c['basis_init']}, `basis_cov_reg` "
               f"{c['basis_cov_reg']}, `basis_lr_scale` {c['basis_lr_scale']}, `residual_scale` {c['residual_scale']})"
               if c.get("decoder_basis") else f"decoder: plain MLP, latent {c['latent_dim']}")
        if self.selection:
            lin = [sel["linear_part"] for sel in self.selection]
            res = [sel["residual"] for sel in self.selection]
            dec = ("decoder chosen by the training on its training demos (`auto_select`), per seed: "
                   + "; ".join(f"{x['decoder_basis']} RBFs, latent_linear {x['latent_linear']} of latent_dim "
                               f"{x['latent_dim']}, `basis_cov_reg` {x['basis_cov_reg']:g} ({x['basis_cov_reg_units']}), "
                               f"`via_noise` {x['via_noise']:g}, MLP residual "
                               f"{'kept' if y['kept'] else 'dropped'}" for x, y in zip(lin, res))
                   + f" ({lin[0]['method']}; the residual on the validation demos, one-standard-error rule)")
            map_txt = "noise: the model's `via_noise`"
        else:
            map_txt = f"noise factor f = {self.map_noise_factor} (chosen on the validation demos)"
        if self.promp_selection:
            ps = self.promp_selection
            map_txt += (f". ProMP: `cov_reg_scale` {ps['cov_reg_scale']:g}, `via_noise` {ps['via_noise']:g} "
                        f"({ps['folds']}-fold cross-validation on its {ps['n_demos']} training demos)")
        return (f"# Small data: {self.n_train} demonstrations of `{self.task}` ({self.n_joints} joints) ({self.n_test} held-out demos, "
                f"{len(self.seeds)} seed(s))\n\nHeld-out reconstruction MSE (rad², mean ± standard error over "
                f"seeds; ProMP is deterministic). DeepProMP: {c['steps']} updates, objective "
                f"`{c['objective']}`, {dec}. Refinement met 1e-6 rad on "
                f"{np.mean(self.refine_reachable):.0%} of the via-point sets. MAP refinement: prior "
                f"`{self.map_prior}`, {map_txt}.\n\n"
                + common.markdown_table(["method", "MSE (rad²)", "÷ ProMP (same conditioning)"], rows)
                + f"\nDeepProMP / ProMP: {r['deepprompt/promp']:.1f}× with {self.n_via} via-points, "
                  f"{r['deepprompt_refined/promp']:.1f}× after refinement, "
                  f"{r['deepprompt_map/promp']:.2f}× after MAP refinement, "
                  f"{r['deepprompt_start/promp_start']:.2f}× with the start point only.\n")


def refined_mse(model: DeepProMPModel, test: DemoDataset, n_via: int, n_points: int = 100, seed: int = 0,
                max_iterations: int = 200) -> tuple[float, float, float]:
    """(MSE after refinement, MSE before, fraction of demos refined within 1e-6 rad).

    Via-points: ``np.random.default_rng([seed, i]).choice(n_points, n_via, replace=False)`` for demo i —
    the rule of :func:`deepprompt_ros.evaluation.reconstruction.reconstruction_mse`; the returned
    MSE-before equals its value (a test checks it)."""
    prim = model.primitive
    x = np.linspace(0.0, 1.0, n_points)
    after, before, ok = [], [], []
    for i, demo in enumerate(test.demos):
        y = demo.resampled(n_points)
        sel = np.sort(np.random.default_rng([seed, i]).choice(n_points, int(n_via), replace=False))
        lat = prim.condition_planner(x[sel], y[sel]).latent  # the model's default conditioning (DeepProMPModel's)
        before.append(float(((prim.mean_trajectory(lat, x) - y) ** 2).mean()))
        res = prim.refine(lat, x[sel], y[sel], max_iterations=max_iterations)
        after.append(float(((prim.mean_trajectory(res.latent, x) - y) ** 2).mean()))
        ok.append(res.reachable)
    return float(np.mean(after)), float(np.mean(before)), float(np.mean(ok))


def map_mse(model: DeepProMPModel, test: DemoDataset, n_via: int, noise_factor: float, prior: str = "standard",
            n_points: int = 100, seed: int = 0, noise_std=None) -> float:
    """MSE after :meth:`DeepProMP.refine_map` from the posterior q(z | via-points); the via-points of
    :func:`refined_mse`. Via-point noise: ONE standard deviation for all joints (rad),
    ``noise_factor`` · σ_y · RMS of the joints' normalization stds (a per-joint σ_y · std would make
    the joints of small range stiff). ``noise_std`` (rad, a number or one per joint), if given, is
    used instead (``noise_factor`` is then ignored)."""
    return float(np.mean(map_errors(model, test, n_via, noise_factor, prior, n_points, seed, noise_std)))


def map_errors(model: DeepProMPModel, test: DemoDataset, n_via: int, noise_factor: float, prior: str = "standard",
               n_points: int = 100, seed: int = 0, noise_std=None) -> np.ndarray:
    """The per-demo MSEs (rad², one per demo of ``test``) whose mean is :func:`map_mse`."""
    prim = model.primitive
    x = np.linspace(0.0, 1.0, n_points)
    noise = np.asarray(noise_std, dtype=np.float64) if noise_std is not None else \
        noise_factor * prim.cfg.sigma_y * float(np.sqrt(np.mean(np.asarray(prim.norm.y_std, dtype=np.float64) ** 2)))
    errs = []
    for i, demo in enumerate(test.demos):
        y = demo.resampled(n_points)
        sel = np.sort(np.random.default_rng([seed, i]).choice(n_points, int(n_via), replace=False))
        res = prim.refine_map(prim.condition(x[sel], y[sel]), x[sel], y[sel], prior=prior, noise_std=noise)
        errs.append(float(((prim.mean_trajectory(res.latent, x) - y) ** 2).mean()))
    return np.asarray(errs)


def default_data(n_train: int = 30, n_test: int = 50, task: str = "wam_reach") -> tuple[DemoDataset, DemoDataset]:
    """``n_train`` training and ``n_test`` held-out demonstrations of ``task`` without their images
    (only via-points are used): a built-in task (default: the 7-joint WAM reaching task) or a PyBullet
    task (its train and test splits)."""
    if task in common.BUILTIN_TASKS:
        ds = common.BUILTIN_TASKS[task](n_train + n_test, common.DATA_SEED + 2)
        tr, te = ds.demos[:n_train], ds.demos[n_train:]
        src = ds.source
    else:
        tr = common.cached_task_split(task, "train", n_train, quick=False).demos
        te = common.cached_task_split(task, "test", n_test, quick=False).demos
        src = f"tasks.make_task('{task}')"
    strip = lambda demos: tuple(dataclasses.replace(d, images=None) for d in demos)  # noqa: E731
    return DemoDataset(strip(tr), f"{src}:train"), DemoDataset(strip(te), f"{src}:test")


def small_data(train_config: TrainConfig, data: tuple[DemoDataset, DemoDataset] | None = None, n_train: int = 30,
               n_test: int = 50, n_via: int = 5, seeds: Sequence[int] = (0,), task: str = "wam_reach",
               log: Callable[[str], None] = print, map_prior: str = "standard",
               map_noise_factors: Sequence[float] = (0.25, 0.5, 1.0, 2.0), cache: UnitCache | None = None,
               jobs: int = 1) -> SmallDataResult:
    """Train DeepProMP with ``train_config`` (its seed replaced by each of ``seeds``) and ProMP on the
    same demonstrations; measure held-out MSE with ``n_via`` via-points, with and without refinement.

    Parameters
    ----------
    train_config : TrainConfig for DeepProMP (steps, objective, ``auto_select``, …)
    data : (train, test) datasets; default :func:`default_data` (``n_train``, ``n_test``, ``task``)
    map_prior, map_noise_factors : MAP refinement (row ``deepprompt_map``): its prior and — for a decoder
        without a linear part — the noise factors f tried on the validation demos of each seed's training
        split (the best is used on the test demos); a decoder with one uses its ``via_noise``
    cache, jobs : each seed is a unit (:func:`seed_unit`): those in ``cache`` are read, the others computed
        (``jobs`` worker processes) and stored; ``units`` of the result is the :class:`UnitReport`
    """
    train_ds, test_ds = data if data is not None else default_data(n_train, n_test, task)
    n_points = train_config.n_points
    mse = {m: [] for m in METHODS}
    check, reach, fit_s, factors, noises, res_used, selection = [], [], [], [], [], [], []
    promp = ProMPModel(log=lambda s: None).fit(train_ds, train_config)
    p_via = reconstruction_mse(promp, test_ds, "via_point", n_via=n_via, n_points=n_points)
    p_start = _start_only(promp, test_ds, n_points)
    log(f"  ProMP: cov_reg_scale {promp.cov_reg_scale:g}, via_noise {promp.via_noise:g} (cross-validated on its "
        f"{len(train_ds) - (train_config.n_val or max(1, len(train_ds) // 10))} training demos)")
    params = dict(n_via=n_via, map_prior=map_prior, map_noise_factors=tuple(map_noise_factors))
    units = seed_units(train_ds, test_ds, train_config, seeds, params, n_points)

    def show(u: Unit, r: dict, reused: bool, wall_s: float) -> None:
        log(f"  seed {u.args[0]}: ProMP {p_via:.2e}  DeepProMP {r['deepprompt']:.2e}  refined {r['deepprompt_refined']:.2e}  "
            f"MAP {r['deepprompt_map']:.2e}  start-only ProMP {p_start:.2e} DeepProMP {r['deepprompt_start']:.2e}  "
            f"(fit {r['fit_s']:.1f} s)" + ("  (reused)" if reused else ""))

    shared = {"train": train_ds, "test": test_ds}
    results, report = run_units(units, seed_unit, shared, cache, jobs, SOURCES, show, log)
    for r in results:
        fit_s.append(r["fit_s"])
        factors.append(r["factor"])
        noises.append(r["noise"])
        check.append(r["check"])
        reach.append(r["reach"])
        res_used.append(r["residual_used"])
        if r["selection"]:
            selection.append(r["selection"])
        mse["promp"].append(p_via)
        mse["promp_start"].append(p_start)
        for m in ("deepprompt", "deepprompt_refined", "deepprompt_map", "deepprompt_map_linear", "deepprompt_start"):
            if m in r:
                mse[m].append(r[m])
    if not mse["deepprompt_map_linear"]:
        del mse["deepprompt_map_linear"]
    return SmallDataResult(train_ds.source, len(train_ds.joint_names), len(train_ds), len(test_ds), n_via,
                           tuple(int(s) for s in seeds), mse, check, reach, fit_s, dataclasses.asdict(train_config),
                           factors, map_prior, noises, selection, res_used,
                           promp.selection.to_json() if promp.selection else {}, units=report.to_json())


# The files whose code determines a unit's result (their digest is part of every unit's key).
SOURCES = ("experiments/small_data.py", "experiments/common.py", "deepprompt_ros/**/*.py")


def unit_context(train_ds: DemoDataset, test_ds: DemoDataset) -> dict:
    """The parts every unit of this experiment shares: the data digest, the digest of :data:`SOURCES`
    and the torch / numpy versions."""
    return {"experiment": "small_data",
            "data": {"sizes": [len(train_ds), len(test_ds)], "digest": common.dataset_digest([train_ds, test_ds])},
            **common.code_parts(SOURCES)}


def seed_units(train_ds: DemoDataset, test_ds: DemoDataset, train_config: TrainConfig, seeds: Sequence[int],
               params: dict, n_points: int) -> list[Unit]:
    """One unit per seed (:func:`seed_unit`); its parts: :func:`unit_context`, the training config with
    the seed, ``params`` and ``n_points``."""
    fixed = {**unit_context(train_ds, test_ds), "params": params, "n_points": n_points}
    tag = "auto" if train_config.auto_select else ("residual" if train_config.decoder_basis else "plain")
    units = []
    for seed in seeds:
        cfg = dataclasses.replace(train_config, seed=int(seed))
        units.append(Unit(f"{tag}__s{int(seed)}", {**fixed, "train_config": dataclasses.asdict(cfg)},
                          (int(seed), cfg, params, n_points)))
    return units


def seed_unit(shared: dict, seed: int, cfg: TrainConfig, params: dict, n_points: int) -> dict:
    """One unit: DeepProMP trained with ``cfg`` (seed ``seed``) on ``shared["train"]`` and every
    DeepProMP row of the table measured on ``shared["test"]`` (ProMP's rows do not depend on the seed)."""
    train_ds, test_ds = shared["train"], shared["test"]
    n_via, map_prior, map_noise_factors = params["n_via"], params["map_prior"], params["map_noise_factors"]
    r = {}
    t0 = time.perf_counter()
    model = DeepProMPModel().fit(train_ds, cfg)
    r["fit_s"] = time.perf_counter() - t0
    prim = model.primitive
    r["selection"] = prim.metadata.get("selection", {})
    r["deepprompt"] = reconstruction_mse(model, test_ds, "via_point", n_via=n_via, n_points=n_points)
    r["deepprompt_refined"], r["check"], r["reach"] = refined_mse(model, test_ds, n_via, n_points)
    std = np.asarray(prim.norm.y_std, dtype=np.float64)
    if prim.cfg.decoder_basis:  # the via-point noise the training chose, in rad per joint
        f, noise = float("nan"), prim.cfg.via_noise * std
    else:
        _, val_ds = train_ds.split(cfg.n_val or max(1, len(train_ds) // 10), seed=cfg.seed)  # DeepProMPModel.fit's split
        f = min(map_noise_factors, key=lambda f: map_mse(model, val_ds, n_via, f, map_prior, n_points, seed=12345))
        noise = np.full(std.shape, f * prim.cfg.sigma_y * float(np.sqrt(np.mean(std ** 2))))
    r["factor"], r["noise"] = float(f), noise.tolist()
    r["residual_used"] = float(prim.cfg.residual_scale)
    if prim.cfg.decoder_basis and prim.cfg.residual_scale > 0:
        r["deepprompt_map_linear"] = map_mse(_residual_off(model), test_ds, n_via, f, map_prior, n_points,
                                             noise_std=noise)
    r["deepprompt_map"] = map_mse(model, test_ds, n_via, f, map_prior, n_points, noise_std=noise)
    r["deepprompt_start"] = _start_only(model, test_ds, n_points)
    return r


def _residual_off(model: DeepProMPModel) -> DeepProMPModel:
    """``model`` with its decoder's MLP residual switched off (scale 0): the linear part alone."""
    linear = DeepProMPModel()
    linear._set(model.primitive.with_residual_scale(0.0))
    return linear


def _start_only(model, test: DemoDataset, n_points: int) -> float:
    """MSE when conditioned on the first point (x = 0) only."""
    x = np.linspace(0.0, 1.0, n_points)
    errs = []
    for demo in test.demos:
        y = demo.resampled(n_points)
        errs.append(float(((model.mean_trajectory(model.condition(x[:1], y[:1]), x) - y) ** 2).mean()))
    return float(np.mean(errs))


def run(scale: Scale, out: pathlib.Path, train_config: TrainConfig | None = None,
        log: Callable[[str], None] = print, cache: UnitCache | None = None, jobs: int = 1) -> dict:
    """Experiment 4 at ``scale``; writes ``small_data.{json,md}`` under ``out``: the base config as it is
    (with ``auto_select``, the training's own model selection; top level of the JSON) and the same with
    ``auto_select`` false (``plain``: the base config's decoder, MAP noise factor chosen on the validation
    demos). ``cache`` / ``jobs``: see :func:`small_data`; the returned dict's ``units`` is the summed
    :class:`UnitReport` (not in the JSON)."""
    base = train_config or common.base_train_config()
    cfg = common.train_config(base, scale.small_steps, max(1, scale.small_steps // 8), 0)
    kw = dict(n_train=scale.small_n_train, n_test=scale.small_n_test, seeds=range(scale.small_seeds),
              task=common.small_data_task(scale), log=log, cache=cache, jobs=jobs)
    data = default_data(kw["n_train"], kw["n_test"], kw["task"])
    log(" the base configuration (auto_select: the training's model selection on its training demos):")
    res = small_data(dataclasses.replace(cfg, auto_select=True), data=data, **kw)
    log(" the base configuration without auto_select (its plain decoder):")
    plain = small_data(dataclasses.replace(cfg, auto_select=False), data=data, **kw)
    md = (res.markdown() + "\n## Reference: the base configuration without `auto_select`\n\n"
          + plain.markdown().split("\n", 2)[2])
    files = common.write_outputs(out, "small_data", {**res.to_json(), "plain": plain.to_json()}, md)
    units = UnitReport(**res.units).add(UnitReport(**plain.units)).to_json()
    return {**res.to_json(), "plain": plain.to_json(), "files": [str(f) for f in files], "units": units}
