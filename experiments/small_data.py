"""Experiment 4 — small data: ~30 demonstrations of a 7-joint task.

DeepProMP and ProMP are trained on ``n_train`` demonstrations (both hold out the same 10 % for
validation) and reconstruct held-out demonstrations from ``n_via`` random via-points per demo
(:func:`deepprompt_ros.evaluation.reconstruction.reconstruction_mse` with ``n_via``: the same seeded
points for every model):

``promp``                ProMP conditioned on the via-points (closed form)
``deepprompt``           DeepProMP decoded at the posterior mean q(z | via-points)
``deepprompt_refined``   the same, after :meth:`DeepProMP.refine` through the via-points (executed
                         trajectory μ_y(μ̃, x))
``deepprompt_map``       the same, after MAP refinement (:meth:`DeepProMP.refine_map`, prior ``map_prior``):
                         the regularized least-squares latent. Via-point noise: with ``cv_grid`` one value
                         in rad chosen by cross-validation on the training demos; otherwise
                         f·σ_y·RMS(joint std) with f chosen from ``map_noise_factors`` on the VALIDATION
                         demos of the training split (never on the test demos)
``deepprompt_map_linear`` (residual decoders) the same MAP with the MLP residual switched off
``*_start``              conditioned on the start point only (x = 0)

:data:`RESIDUAL_CONFIG` is the configuration :func:`run` uses (the plain decoder is run too, as the
reference): a decoder that is a residual over a linear RBF basis, its linear part initialized as the
PPCA of the demonstrations with ProMP's covariance regularizer and kept fixed; its latent size, that
regularizer, its units (normalized or rad) and the MAP noise are chosen by leave-one-out cross-validation
on the training demos (:data:`CV_GRID`), the MLP residual is kept only where it helps by more than one
standard error (:func:`keep_residual`) on the held-out demos of a :data:`RESIDUAL_FOLDS`-fold
cross-validation of the whole training on the training demos (:func:`residual_cv_errors`)
(EXPERIMENTS.md section 4 has the measurements behind each choice).

Call :func:`small_data` with any :class:`TrainConfig` to measure a change of the model or its training::

    from experiments.small_data import small_data
    res = small_data(TrainConfig(steps=4000, threads=1), seeds=(0, 1, 2))
    print(res.markdown())

Length: over 400 lines because it is one study's protocol, read top to bottom: the error measures
it reports, the cross-validation that chooses the residual decoder's settings, the per-seed units
the harness runs and caches, and :func:`run`. Each piece serves this experiment alone; split, a
reader would follow one table through several files.
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
from deepprompt_ros.training.basis import cv_basis_hyperparameters, fold_assignment
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
    map_noise_std: list = dataclasses.field(default_factory=list)  # the MAP via-point noise used (rad), per seed
    cv: dict = dataclasses.field(default_factory=dict)  # cross-validation on the training demos (cv_grid), or {}
    residual_used: list = dataclasses.field(default_factory=list)  # residual scale of the deepprompt_map row, per seed
    # MAP MSE [trained residual, off] on the demos that judged the residual (validation demos, or the held-out
    # demos of the residual's cross-validation), per seed
    residual_val: list = dataclasses.field(default_factory=list)
    residual_val_diff_se: list = dataclasses.field(default_factory=list)  # [mean per-demo difference, its SE], per seed
    residual_folds: int = 0  # residual judged by K-fold CV on the training demos (0: on the validation demos)
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
               if c.get("decoder_basis") else "decoder: plain MLP")
        if self.cv:
            chosen = (f"chosen by {self.cv['folds']}-fold cross-validation on the {self.cv['n_demos']} training demos "
                      f"(linear part, {self.cv['draws']} via-point draws per demo): latent {self.cv['latent_dim']}, "
                      f"`basis_cov_reg` {self.cv['basis_cov_reg']} in "
                      f"{self.cv.get('basis_cov_reg_units', 'normalized')} units, noise {self.cv['noise_std']} rad")
            map_txt = f"noise s = {self.cv['noise_std']} rad, {chosen}"
        else:
            map_txt = f"noise factor f = {self.map_noise_factor} (chosen on the validation demos)"
        if self.residual_val:
            diffs = [[float(f"{v:.2e}") for v in r] for r in self.residual_val_diff_se]
            rule = f"; per-demo difference and its standard error {diffs}" if diffs else ""
            where = (f"held-out demos of a {self.residual_folds}-fold cross-validation on the {self.n_train} training demos"
                     if self.residual_folds >= 2 else "validation demos")
            map_txt += (f"; MLP residual per seed: scale {self.residual_used} (the trained one only if its MAP MSE on the "
                        f"{where} is lower than with the residual off by more than one standard error — "
                        f"MSE [residual, off] {[[float(f'{v:.3e}') for v in r] for r in self.residual_val]}{rule})")
        return (f"# Small data: {self.n_train} demonstrations of `{self.task}` ({self.n_joints} joints) ({self.n_test} held-out demos, "
                f"{len(self.seeds)} seed(s))\n\nHeld-out reconstruction MSE (rad², mean ± standard error over "
                f"seeds; ProMP is deterministic). DeepProMP: {c['steps']} updates, objective "
                f"`{c['objective']}`, latent {c['latent_dim']}, {dec}. Refinement met 1e-6 rad on "
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
        lat = prim.condition(x[sel], y[sel])
        before.append(float(((prim.mean_trajectory(lat, x) - y) ** 2).mean()))
        res = prim.refine(lat, x[sel], y[sel], max_iterations=max_iterations)
        after.append(float(((prim.mean_trajectory(res.latent, x) - y) ** 2).mean()))
        ok.append(res.reachable)
    return float(np.mean(after)), float(np.mean(before)), float(np.mean(ok))


def map_mse(model: DeepProMPModel, test: DemoDataset, n_via: int, noise_factor: float, prior: str = "standard",
            n_points: int = 100, seed: int = 0, noise_std: float | None = None) -> float:
    """MSE after :meth:`DeepProMP.refine_map` from the posterior q(z | via-points); the via-points of
    :func:`refined_mse`. Via-point noise: ONE standard deviation for all joints (rad, as ProMP's
    via-point noise), ``noise_factor`` · σ_y · RMS of the joints' normalization stds (a per-joint
    σ_y · std would make the joints of small range stiff).
    ``noise_std`` (rad), if given, is used instead (``noise_factor`` is then ignored)."""
    return float(np.mean(map_errors(model, test, n_via, noise_factor, prior, n_points, seed, noise_std)))


def map_errors(model: DeepProMPModel, test: DemoDataset, n_via: int, noise_factor: float, prior: str = "standard",
               n_points: int = 100, seed: int = 0, noise_std: float | None = None) -> np.ndarray:
    """The per-demo MSEs (rad², one per demo of ``test``) whose mean is :func:`map_mse`."""
    prim = model.primitive
    x = np.linspace(0.0, 1.0, n_points)
    noise = float(noise_std) if noise_std is not None else \
        noise_factor * prim.cfg.sigma_y * float(np.sqrt(np.mean(np.asarray(prim.norm.y_std, dtype=np.float64) ** 2)))
    errs = []
    for i, demo in enumerate(test.demos):
        y = demo.resampled(n_points)
        sel = np.sort(np.random.default_rng([seed, i]).choice(n_points, int(n_via), replace=False))
        res = prim.refine_map(prim.condition(x[sel], y[sel]), x[sel], y[sel], prior=prior, noise_std=noise)
        errs.append(float(((prim.mean_trajectory(res.latent, x) - y) ** 2).mean()))
    return np.asarray(errs)


def keep_residual(with_residual: np.ndarray, without: np.ndarray) -> tuple[bool, float, float]:
    """The one-standard-error rule (Hastie, Tibshirani & Friedman, *The Elements of Statistical
    Learning*, 2nd ed., §7.10): keep the MLP residual only if its validation error is lower than the
    simpler model's (residual off) by more than one standard error of the difference.

    ``with_residual``, ``without`` : (draws, n_demos) validation MSEs of the same via-point sets. The
    standard error is over demos (their mean over draws; the draws of one demo are not independent),
    over draws when there is a single demo. Returns (keep, mean difference, its standard error)."""
    a = np.atleast_2d(np.asarray(with_residual, dtype=np.float64))
    b = np.atleast_2d(np.asarray(without, dtype=np.float64))
    if a.shape != b.shape or a.size == 0:
        raise ValueError(f"keep_residual needs two equal, non-empty (draws, demos) arrays, got {a.shape} and {b.shape}")
    diff = (a - b).mean(0) if a.shape[1] >= 2 else (a - b)[:, 0]
    if diff.size < 2:
        return False, float(diff.mean()), float("inf")
    se = float(diff.std(ddof=1) / np.sqrt(diff.size))
    return bool(diff.mean() + se < 0.0), float(diff.mean()), se


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
               map_noise_factors: Sequence[float] = (0.25, 0.5, 1.0, 2.0), cv_grid: dict | None = None,
               residual_select: bool = False, val_draws: int = 8, residual_folds: int = 0,
               cache: UnitCache | None = None,
               jobs: int = 1) -> SmallDataResult:
    """Train DeepProMP with ``train_config`` (its seed replaced by each of ``seeds``) and ProMP on the
    same demonstrations; measure held-out MSE with ``n_via`` via-points, with and without refinement.

    Parameters
    ----------
    train_config : TrainConfig for DeepProMP (steps, objective, latent size, …)
    data : (train, test) datasets; default :func:`default_data` (``n_train``, ``n_test``, ``task``)
    map_prior, map_noise_factors : MAP refinement (row ``deepprompt_map``): its prior and the noise
        factors f tried on the validation demos of each seed's training split (the best is used on the test demos)
    cv_grid : if given (keys ``latent_dims``, ``cov_regs``, ``noise_stds``, optional ``folds``, ``draws``;
        :func:`deepprompt_ros.training.basis.cv_basis_hyperparameters`), the latent size, ``basis_cov_reg`` and the MAP
        via-point noise (rad) are chosen by cross-validation of the decoder's linear part on the
        training demos ``train`` (all of them; never the test demos), once for all seeds, and replace
        ``train_config``'s values and ``map_noise_factors``
    residual_select : (residual decoders) per seed, the ``deepprompt_map`` row uses the trained MLP residual
        only if it lowers the MAP MSE on the seed's validation demos (``val_draws`` via-point sets per demo)
        by more than one standard error (:func:`keep_residual`), else none (scale 0); with ``residual_folds``
        K >= 2 judged instead by K-fold cross-validation on the training demos (:func:`residual_cv_errors`).
        Row ``deepprompt_map_linear`` is always the residual-off MAP on the test demos.
    cache, jobs : the cross-validation and each seed are units (:func:`cv_unit`, :func:`seed_unit`): those
        in ``cache`` are read, the others computed (``jobs`` worker processes for the seeds) and stored;
        ``units`` of the result is the :class:`UnitReport`
    """
    train_ds, test_ds = data if data is not None else default_data(n_train, n_test, task)
    n_points = train_config.n_points
    mse = {m: [] for m in METHODS}
    check, reach, fit_s, factors, noises, res_used, res_val, res_se = [], [], [], [], [], [], [], []
    cv = {}
    report = UnitReport()
    if cv_grid is not None:
        if not train_config.decoder_basis:
            raise ValueError("cv_grid needs a decoder with a linear basis (decoder_basis > 0)")
        args = (n_points, train_config.decoder_basis, train_config.basis_width, n_via, dict(cv_grid))
        unit = Unit("cv", {**unit_context(train_ds, test_ds), "cv": args}, args)
        (cv,), report = run_units([unit], cv_unit, {"train": train_ds}, cache, 1, SOURCES, log=lambda s: None)
        train_config = dataclasses.replace(train_config, latent_dim=cv["latent_dim"], basis_cov_reg=cv["basis_cov_reg"],
                                           basis_cov_reg_units=cv["basis_cov_reg_units"])
        log(f"  cross-validation ({cv['folds']} folds, {cv['wall_time_s']:.1f} s): latent {cv['latent_dim']}, "
            f"basis_cov_reg {cv['basis_cov_reg']} ({train_config.basis_cov_reg_units} units), "
            f"MAP noise {cv['noise_std']} rad (CV MSE {cv['cv_mse']:.3e})"
            + ("  (reused)" if report.reused else ""))
    promp = ProMPModel().fit(train_ds, train_config)
    p_via = reconstruction_mse(promp, test_ds, "via_point", n_via=n_via, n_points=n_points)
    p_start = _start_only(promp, test_ds, n_points)
    params = dict(n_via=n_via, map_prior=map_prior, map_noise_factors=tuple(map_noise_factors), cv=cv,
                  residual_select=residual_select, val_draws=val_draws, residual_folds=int(residual_folds))
    units = seed_units(train_ds, test_ds, train_config, seeds, params, n_points)

    def show(u: Unit, r: dict, reused: bool, wall_s: float) -> None:
        log(f"  seed {u.args[0]}: ProMP {p_via:.2e}  DeepProMP {r['deepprompt']:.2e}  refined {r['deepprompt_refined']:.2e}  "
            f"MAP {r['deepprompt_map']:.2e} (noise {r['noise']:.2e} rad)  "
            f"start-only ProMP {p_start:.2e} DeepProMP {r['deepprompt_start']:.2e}  (fit {r['fit_s']:.1f} s)"
            + ("  (reused)" if reused else ""))

    shared = {"train": train_ds, "test": test_ds}
    results, seeds_report = run_units(units, seed_unit, shared, cache, jobs, SOURCES, show, log)
    report = report.add(seeds_report)
    for r in results:
        fit_s.append(r["fit_s"])
        factors.append(r["factor"])
        noises.append(r["noise"])
        check.append(r["check"])
        reach.append(r["reach"])
        if "residual_used" in r:
            res_used.append(r["residual_used"])
        if "residual_val" in r:
            res_val.append(r["residual_val"])
        if "residual_val_diff_se" in r:
            res_se.append(r["residual_val_diff_se"])
        mse["promp"].append(p_via)
        mse["promp_start"].append(p_start)
        for m in ("deepprompt", "deepprompt_refined", "deepprompt_map", "deepprompt_map_linear", "deepprompt_start"):
            if m in r:
                mse[m].append(r[m])
    if not mse["deepprompt_map_linear"]:
        del mse["deepprompt_map_linear"]
    return SmallDataResult(train_ds.source, len(train_ds.joint_names), len(train_ds), len(test_ds), n_via, tuple(int(s) for s in seeds), mse,
                           check, reach, fit_s, dataclasses.asdict(train_config), factors, map_prior, noises, cv, res_used, res_val,
                           res_se, int(residual_folds) if residual_select else 0, units=report.to_json())


# The files whose code determines a unit's result (their digest is part of every unit's key).
SOURCES = ("experiments/small_data.py", "experiments/common.py", "deepprompt_ros/**/*.py")


def unit_context(train_ds: DemoDataset, test_ds: DemoDataset) -> dict:
    """The parts every unit of this experiment shares: the data digest, the digest of :data:`SOURCES`
    and the torch / numpy versions."""
    return {"experiment": "small_data",
            "data": {"sizes": [len(train_ds), len(test_ds)], "digest": common.dataset_digest([train_ds, test_ds])},
            **common.code_parts(SOURCES)}


def cv_unit(shared: dict, n_points: int, decoder_basis: int, basis_width: float, n_via: int, cv_grid: dict) -> dict:
    """The cross-validation unit: :func:`deepprompt_ros.training.basis.cv_basis_hyperparameters` on
    ``shared["train"]``, with its wall time (``wall_time_s``)."""
    t0 = time.perf_counter()
    cv = cv_basis_hyperparameters(shared["train"], n_points, decoder_basis, basis_width, n_via=n_via, **cv_grid)
    cv["wall_time_s"] = time.perf_counter() - t0
    return cv


def seed_units(train_ds: DemoDataset, test_ds: DemoDataset, train_config: TrainConfig, seeds: Sequence[int],
               params: dict, n_points: int) -> list[Unit]:
    """One unit per seed (:func:`seed_unit`); its parts: :func:`unit_context`, the training config with
    the seed, ``params`` (the cross-validation result without its wall time) and ``n_points``."""
    cv = {k: v for k, v in params["cv"].items() if k != "wall_time_s"}
    fixed = {**unit_context(train_ds, test_ds), "params": {**params, "cv": cv}, "n_points": n_points}
    tag = "residual" if train_config.decoder_basis else "plain"
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
    cv, residual_select, val_draws = params["cv"], params["residual_select"], params["val_draws"]
    r = {}
    t0 = time.perf_counter()
    model = DeepProMPModel().fit(train_ds, cfg)
    r["fit_s"] = time.perf_counter() - t0
    r["deepprompt"] = reconstruction_mse(model, test_ds, "via_point", n_via=n_via, n_points=n_points)
    r["deepprompt_refined"], r["check"], r["reach"] = refined_mse(model, test_ds, n_via, n_points)
    _, val_ds = train_ds.split(cfg.n_val or max(1, len(train_ds) // 10), seed=cfg.seed)  # DeepProMPModel.fit's split
    if cv:
        f, noise = float("nan"), cv["noise_std"]
    else:
        f, noise = min(map_noise_factors, key=lambda f: map_mse(model, val_ds, n_via, f, map_prior, n_points, seed=12345)), None
    r["factor"] = float(f)
    chosen = model
    if cfg.decoder_basis:
        linear = _residual_off(model)
        r["deepprompt_map_linear"] = map_mse(linear, test_ds, n_via, f, map_prior, n_points, noise_std=noise)
        if residual_select:
            folds = int(params.get("residual_folds", 0))
            if folds >= 2:
                val = residual_cv_errors(train_ds, cfg, folds, n_via, f, map_prior, n_points, noise, val_draws)
            else:
                val = [_draw_errors(m, val_ds, n_via, f, map_prior, n_points, noise, val_draws) for m in (model, linear)]
            keep, diff, se = keep_residual(*val)
            r["residual_val"] = [float(v.mean()) for v in val]
            r["residual_val_diff_se"] = [diff, se]
            chosen = model if keep else linear
        r["residual_used"] = float(chosen.primitive.cfg.residual_scale)
    r["deepprompt_map"] = map_mse(chosen, test_ds, n_via, f, map_prior, n_points, noise_std=noise)
    prim = model.primitive
    r["noise"] = float(noise) if noise is not None else float(
        f * prim.cfg.sigma_y * np.sqrt(np.mean(np.asarray(prim.norm.y_std, dtype=np.float64) ** 2)))
    r["deepprompt_start"] = _start_only(model, test_ds, n_points)
    return r


def residual_cv_errors(train_ds: DemoDataset, cfg: TrainConfig, folds: int, n_via: int, noise_factor: float,
                       prior: str, n_points: int, noise_std: float | None, draws: int) -> list[np.ndarray]:
    """K-fold cross-validation of the MLP residual on the training demos: per fold (a seeded
    permutation, ``cfg.seed``), DeepProMP is trained with ``cfg`` on the other folds exactly as the
    final model (its own validation split picks the checkpoint) and each held-out demo is MAP-refined
    through ``draws`` sets of ``n_via`` via-points with the trained residual and with it off.

    The demos that judge the residual are then never those that chose its checkpoint (on the final
    model's 3 validation demos the residual measured 0.2–6 % better on every seed, on the test demos it
    was worse on 5 of 6 seeds, by up to 9 %: EXPERIMENTS.md section 4).
    Returns [with residual, without], each (draws, n_demos) MSEs in rad² (:func:`keep_residual`'s input)."""
    n = len(train_ds)
    if not 2 <= folds <= n // 2:
        raise ValueError(f"residual cross-validation needs 2 <= folds <= {n // 2} for {n} demonstrations, got {folds}")
    fold_of = fold_assignment(n, folds, cfg.seed)
    out = [[], []]
    for k in range(folds):
        fit_on = DemoDataset(tuple(d for d, f in zip(train_ds.demos, fold_of) if f != k), train_ds.source + f":fold{k}")
        held = DemoDataset(tuple(d for d, f in zip(train_ds.demos, fold_of) if f == k),
                           train_ds.source + f":heldout{k}")
        model = DeepProMPModel().fit(fit_on, cfg)
        for j, m in enumerate((model, _residual_off(model))):
            out[j].append(_draw_errors(m, held, n_via, noise_factor, prior, n_points, noise_std, draws))
    return [np.concatenate(o, axis=1) for o in out]


def _residual_off(model: DeepProMPModel) -> DeepProMPModel:
    """``model`` with its decoder's MLP residual switched off (scale 0): the linear part alone."""
    linear = DeepProMPModel()
    linear._set(model.primitive.with_residual_scale(0.0))
    return linear


def _draw_errors(model: DeepProMPModel, demos: DemoDataset, n_via: int, noise_factor: float, prior: str,
                 n_points: int, noise_std: float | None, draws: int) -> np.ndarray:
    """(draws, n_demos) :func:`map_errors` of ``demos``, draw i with via-point seed 12345 + i."""
    return np.stack([map_errors(model, demos, n_via, noise_factor, prior, n_points, seed=12345 + i,
                                noise_std=noise_std) for i in range(draws)])


def _start_only(model, test: DemoDataset, n_points: int) -> float:
    """MSE when conditioned on the first point (x = 0) only."""
    x = np.linspace(0.0, 1.0, n_points)
    errs = []
    for demo in test.demos:
        y = demo.resampled(n_points)
        errs.append(float(((model.mean_trajectory(model.condition(x[:1], y[:1]), x) - y) ** 2).mean()))
    return float(np.mean(errs))


# The small-data configuration (on top of the base training config): the decoder is a residual over
# a linear basis of 20 RBFs per joint whose linear part starts as the PPCA of the demonstrations with
# ProMP's covariance regularizer (5 % of the mean weight variance) and stays fixed; latent 64 (> the
# rank 26 of 27 demos' weight covariance, so the latent linear-Gaussian model holds the ProMP).
RESIDUAL_CONFIG = dict(decoder_basis=20, latent_dim=64, basis_init="pca", basis_cov_reg=0.05, basis_lr_scale=0.0,
                       residual_scale=0.1)
# run() replaces RESIDUAL_CONFIG's latent_dim, basis_cov_reg and basis_cov_reg_units, and the MAP noise, by
# leave-one-out cross-validation of the linear part on the training demos over this grid
# (deepprompt_ros.training.basis.cv_basis_hyperparameters; 140 = 20 RBFs x 7 joints, the full weight space),
# and keeps the trained MLP residual only where it beats "residual off" by more than one standard error
# (residual_select, keep_residual)
CV_GRID = dict(latent_dims=(32, 64, 140), cov_regs=(0.0, 0.01, 0.02, 0.05, 0.1, 0.2),
               noise_stds=(3e-4, 1e-3, 3e-3, 1e-2, 3e-2), folds=0, draws=4, cov_reg_units=("normalized", "raw"))
# ... judged by RESIDUAL_FOLDS-fold cross-validation of the residual on the training demos (residual_cv_errors)
RESIDUAL_FOLDS = 3


def run(scale: Scale, out: pathlib.Path, train_config: TrainConfig | None = None,
        log: Callable[[str], None] = print, cache: UnitCache | None = None, jobs: int = 1) -> dict:
    """Experiment 4 at ``scale``; writes ``small_data.{json,md}`` under ``out``: the base config with
    :data:`RESIDUAL_CONFIG`, its latent size / ``basis_cov_reg`` / MAP noise chosen by cross-validation
    on the training demos over :data:`CV_GRID` and the residual kept or dropped on validation (top level
    of the JSON), and the base config unchanged (``plain``, MAP noise factor chosen on the validation demos).
    ``cache`` / ``jobs``: see :func:`small_data`; the returned dict's ``units`` is the summed
    :class:`UnitReport` (not in the JSON)."""
    base = train_config or common.base_train_config()
    cfg = common.train_config(base, scale.small_steps, max(1, scale.small_steps // 8), 0)
    kw = dict(n_train=scale.small_n_train, n_test=scale.small_n_test, seeds=range(scale.small_seeds),
              task=common.small_data_task(scale), log=log, cache=cache, jobs=jobs)
    data = default_data(kw["n_train"], kw["n_test"], kw["task"])
    log(" residual decoder (RESIDUAL_CONFIG, latent / basis_cov_reg / MAP noise by cross-validation on CV_GRID):")
    res = small_data(dataclasses.replace(cfg, **RESIDUAL_CONFIG), data=data, cv_grid=CV_GRID, residual_select=True,
                     residual_folds=RESIDUAL_FOLDS, **kw)
    log(" plain decoder (the base config):")
    plain = small_data(cfg, data=data, **kw)
    md = (res.markdown() + "\n## Reference: the plain decoder (base config, unchanged)\n\n"
          + plain.markdown().split("\n", 2)[2])
    files = common.write_outputs(out, "small_data", {**res.to_json(), "plain": plain.to_json()}, md)
    units = UnitReport(**res.units).add(UnitReport(**plain.units)).to_json()
    return {**res.to_json(), "plain": plain.to_json(), "files": [str(f) for f in files], "units": units}
