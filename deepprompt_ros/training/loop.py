"""Training a DeepProMP (paper Sec. III-B): read :func:`train` top to bottom — model selection →
batch → loss → backward → eval → residual kept or dropped → checkpoint. The loss and the validation
are in :mod:`deepprompt_ros.training.objectives`, the configuration in
:mod:`deepprompt_ros.training.config`, the model selection (``auto_select``) in
:mod:`deepprompt_ros.training.selection`; the command line is :mod:`deepprompt_ros.training.cli`.
"""
from __future__ import annotations

import dataclasses
import datetime
import math
import time

import numpy as np
import torch

from deepprompt_ros import __version__
from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.model.checkpoint import save_checkpoint
from deepprompt_ros.model.network import DeepProMPNet, ModelConfig
from deepprompt_ros.training.basis import init_basis_pca
from deepprompt_ros.training.config import TrainConfig
from deepprompt_ros.training.distributed import SINGLE, Runtime, judge_on_main, wrap
from deepprompt_ros.training.objectives import loss_fn, validation_mse
from deepprompt_ros.training.resume import ResumeFile, data_digest, fit_key, resume_path
from deepprompt_ros.training.selection import (choose_context_paths, choose_mode_noise, compare_modes, judge_residual,
                                               nonlinear_dims, select_linear_part)
from deepprompt_ros.training.tensors import fit_normalization, to_tensors

__all__ = ["train", "new_network", "new_optimizer", "record_validation", "write_model", "selection_line",
           "judge_with_fallback", "in_memory_refit"]


def train(ds: DemoDataset, cfg: TrainConfig, out_path=None, log=print, val_ds: DemoDataset | None = None,
          info: dict | None = None, run: Runtime = SINGLE, resume: bool = False):
    """Train on ``ds`` (a validation split is held out unless ``val_ds`` is given). A sharded dataset
    on disk trains with bounded memory by :func:`deepprompt_ros.training.streaming.train_sharded`.

    With ``cfg.auto_select`` the linear part and the modes of the demos are chosen on the training
    split before training (:func:`~deepprompt_ros.training.selection.select_linear_part`) and the MLP
    residual kept or dropped on the validation split after it by the energy score of conditioned
    samples (:func:`~deepprompt_ros.training.selection.judge_residual`). With K > 1 modes the
    training with K = 1 (the PPCA of all demos) runs too, its residual judged, and the modes are served
    only when their residual was kept and they beat it on the validation split
    (:func:`~deepprompt_ros.training.selection.compare_modes`). Then the path of the low-dimensional
    contexts (:func:`~deepprompt_ros.training.selection.choose_context_paths`). Every choice is logged
    and recorded in the checkpoint's metadata (``selection``, and ``train_config`` holds the
    configuration actually trained).

    ``info``, when given, receives the checkpoint's metadata entries ``train_config`` and ``selection``.

    With ``out_path`` the run writes its resume file beside it every ``checkpoint_every`` updates
    (:mod:`deepprompt_ros.training.resume`); ``resume`` continues from that file. ``run``: this
    process's place in a data-parallel run (:mod:`deepprompt_ros.training.distributed`; every process
    calls :func:`train`): the model selection and the residual's judgement are made on process 0 and
    shared, process 0 alone validates and writes; the others return their last weights and an empty
    history.

    Returns
    -------
    net : DeepProMPNet (best validation weights), norm : Normalization, history : list of dict
    """
    torch.set_num_threads(cfg.threads)
    t0 = time.perf_counter()
    if val_ds is None:
        n_val = cfg.n_val or max(1, len(ds) // 10)
        train_ds, val_ds = ds.split(n_val, seed=cfg.seed)
    else:
        train_ds = ds
    run.check(cfg)
    ckpt = ResumeFile(resume_path(out_path), run, load=resume) if out_path is not None else None
    selection = {}
    if cfg.auto_select:  # numpy on process 0, its choice shared: every process trains the same configuration
        cfg, selection["linear_part"] = run.broadcast(
            select_linear_part(train_ds, cfg, len(ds.joint_names)) if run.is_main else None)
    fitted = _fit(train_ds, val_ds, cfg, log, run, ckpt, fit_no=0)
    if cfg.auto_select:
        cfg, fitted = judge_with_fallback(cfg, fitted, selection, log,
                                          lambda c: _fit(train_ds, val_ds, c, log, run, ckpt, fit_no=1),
                                          run, ds.joint_names, val_ds, train_ds)
    net, norm, history, best = fitted
    if cfg.auto_select and run.is_main:
        selection["context"] = choose_context_paths(net, norm, ds.joint_names, cfg, train_ds, val_ds)
        log(context_line(selection["context"]))
    if info is not None:
        info.update(train_config=dataclasses.asdict(cfg), selection=selection)
    if out_path is not None and run.is_main:
        write_model(out_path, net, norm, ds, cfg, selection, run, (len(train_ds), len(val_ds)), best, t0)
    return net, norm, history


def in_memory_refit(cfg: TrainConfig):
    """The training of the residual's cross-validation: a fold's demos trained in memory exactly as
    ``cfg`` says, the linear part as chosen (no selection again). Returns (network, normalization)."""
    def refit(fold_ds):
        fold_net, fold_norm, _ = train(fold_ds, dataclasses.replace(cfg, auto_select=False), log=lambda s: None)
        return fold_net, fold_norm
    return refit


def judge_with_fallback(cfg: TrainConfig, fitted: tuple, selection: dict, log, fit_again, run: Runtime, joint_names,
                        val_ds: DemoDataset | None, refit_ds: DemoDataset | None) -> tuple:
    """``auto_select`` after the training: the residual of ``fitted`` = (net, norm, history, best) judged
    on the validation demos ``val_ds`` (:func:`~deepprompt_ros.training.selection.judge_residual`, its
    cross-validation on ``refit_ds`` by :func:`in_memory_refit`). Beside a linear part of
    ``cfg.linear_modes`` > 1 modes (which the decoder holds, ``ModelConfig.decoder_modes``) the training
    runs again with one (``fit_again(cfg)`` -> fitted), its residual is judged, and the modes are kept
    only if :func:`~deepprompt_ros.training.selection.compare_modes` prefers them, each with its judged
    residual and its path of the low-dimensional contexts. The modes are kept without that training
    where the selection's cross-validation found their executed means better
    (:func:`~deepprompt_ros.training.basis.cv_modes`, ``better``) or ``cfg.judge_modes`` is false. The judgements are made on
    process 0 of ``run`` and shared (``val_ds`` may be None elsewhere). The records go into
    ``selection``, the choices into one log line. Returns (the configuration trained, with its residual
    scale; the fitted network, normalization, history and best validation MSE)."""
    def judge(n, nm, c):
        return judge_on_main(run, n, lambda: judge_residual(n, nm, joint_names, val_ds, c, refit_ds,
                                                            in_memory_refit(c)))

    def compare(a, b, c):
        def paths(n, nm):  # each model with its own path of the low-dim contexts (in-memory training)
            return None if refit_ds is None else choose_context_paths(n, nm, joint_names, c, refit_ds, val_ds)
        return run.broadcast(compare_modes(a, b, joint_names, val_ds, c, paths(*a), paths(*b)) if run.is_main
                             else None)

    net, norm, history, best = fitted
    net, selection["residual"] = judge(net, norm, cfg)
    modes_cv = selection.get("linear_part", {}).get("modes", {}).get("cross_validation") or {}
    if cfg.linear_modes > 1 and (not cfg.judge_modes or modes_cv.get("better")):
        net, noise = run.broadcast(choose_mode_noise(net, norm, joint_names, val_ds, cfg) if run.is_main else None)
        cfg = dataclasses.replace(cfg, via_noise=noise["via_noise"], mode_noise=noise["mode_noise"])
        why = ("judge_modes false" if not cfg.judge_modes else
               "the cross-validation's executed means better with the modes")
        selection["modes_fallback"] = {"linear_modes": cfg.linear_modes, "kept_modes": True, "noise": noise,
                                       "reason": f"{why}: kept without the training with one mode"}
    elif cfg.linear_modes > 1:
        several, modes_cfg, modes_fitted = selection.pop("residual"), cfg, (net, norm, history, best)
        log(f"residual {'kept' if several['kept'] else 'dropped'} beside the linear part of {cfg.linear_modes} "
            "modes: training with one mode to compare")
        cfg = dataclasses.replace(cfg, linear_modes=1, latent_dim=cfg.latent_linear + nonlinear_dims(cfg, 1))
        noise_net, noise = run.broadcast(choose_mode_noise(modes_fitted[0], norm, joint_names, val_ds, modes_cfg)
                                         if run.is_main else None)
        modes_cfg, modes_fitted = (dataclasses.replace(modes_cfg, via_noise=noise["via_noise"],
                                                       mode_noise=noise["mode_noise"]),
                                   (noise_net, *modes_fitted[1:]))
        net, norm, history, best = fit_again(cfg)
        net, selection["residual"] = judge(net, norm, cfg)
        keep, record = compare((modes_fitted[0], modes_fitted[1]), (net, norm), modes_cfg)
        selection["modes_fallback"] = {"linear_modes": modes_cfg.linear_modes, "residual": several,
                                       "noise": noise, **record}
        if keep:
            selection["one_mode"] = {"residual": selection.pop("residual")}
            selection["residual"] = several
            cfg, (net, norm, history, best) = modes_cfg, modes_fitted
    cfg = dataclasses.replace(cfg, residual_scale=net.cfg.residual_scale)
    log(selection_line(selection))
    return cfg, (net, norm, history, best)


def write_model(out_path, net: DeepProMPNet, norm, ds, cfg: TrainConfig, selection: dict, run: Runtime,
                sizes: tuple[int, int], best: float, t0: float) -> None:
    """The checkpoint of a finished training with its metadata: the configuration trained, the
    selection's record, the provenance (data set, ``sizes`` = (training, validation) demos, versions,
    device and processes) and the metrics (best validation MSE, wall time since ``t0``)."""
    meta = {
        "train_config": dataclasses.asdict(cfg),
        "selection": selection,
        "provenance": {"dataset": ds.source, "n_train": sizes[0], "n_val": sizes[1],
                       "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                       "deepprompt_ros": __version__, "torch": torch.__version__,
                       "device": str(run.device), "backend": run.backend, "world_size": run.world_size},
        "metrics": {"best_val_mse_rad2": best, "wall_time_s": time.perf_counter() - t0},
    }
    save_checkpoint(out_path, net, norm, ds.joint_names, meta)


def _fit(train_ds: DemoDataset, val_ds: DemoDataset, cfg: TrainConfig, log, run: Runtime = SINGLE,
         ckpt: ResumeFile | None = None, fit_no: int = 0):
    """The training proper of ``cfg`` (its choices made): initialization (seed ``cfg.seed``; the PCA
    of the linear part within ``cfg.linear_modes`` modes), ``cfg.steps`` updates, the validation every
    ``cfg.val_every``; with ``ckpt``, continued from its entry ``fit_no`` and recorded in it every
    ``cfg.checkpoint_every`` updates. Returns (net with the best validation weights, normalization,
    history, best validation MSE; on processes other than 0 the last weights, an empty history and inf)."""
    torch.manual_seed(cfg.seed)
    norm = fit_normalization(train_ds, cfg.n_points)
    data = to_tensors(train_ds, norm, cfg.n_points)
    val = to_tensors(val_ds, norm, cfg.n_points)
    net = new_network(train_ds, cfg)
    if cfg.decoder_basis and cfg.basis_init == "pca":
        init_basis_pca(net, data, cfg.basis_cov_reg,
                       joint_std=np.asarray(norm.y_std) if cfg.basis_cov_reg_units == "raw" else None,
                       n_modes=cfg.linear_modes, seed=cfg.seed)
    opt = new_optimizer(net, cfg)
    data, val = run.place(net, data, val)  # to the run's device (no copy on the CPU)
    gen, draws = run.generators(cfg.seed)  # the batch's demos; the inputs given and z (one generator in one process)
    history, best, best_state, done = [], math.inf, None, 0
    key = fit_key(cfg, data_digest(data, val), run.world_size) if ckpt else None
    entry = ckpt.restore(fit_no, key) if ckpt else None
    if entry is not None:  # continue after the update the resume file reached
        if entry["step"] > cfg.steps:
            raise ValueError(f"--resume: '{ckpt.path}' reached update {entry['step']}, beyond this run's steps = "
                             f"{cfg.steps}: expected steps >= {entry['step']}")
        net.load_state_dict(entry["net"])
        opt.load_state_dict(entry["optimizer"])
        for g, state in zip((gen, draws), entry["generators"][run.rank]):
            g.set_state(state)
        done, history, best, best_state = entry["step"], entry["history"], entry["best"], entry["best_state"]
        log(f"resumed from {ckpt.path} at update {done}")
    model = wrap(net, loss_fn, run)  # DDP averages the processes' gradients
    every = cfg.checkpoint_every or cfg.val_every
    t0 = time.perf_counter() - (entry["elapsed_s"] if entry else 0.0)
    n_train = data.y.shape[0]
    for step in range(done + 1, cfg.steps + 1):
        idx = run.share(torch.randint(0, n_train, (cfg.batch_size,), generator=gen, device=gen.device))  # (B / procs,)
        beta = cfg.beta * min(1.0, step / max(1, cfg.kl_anneal_steps))  # KL annealing
        loss, nll, kl, cons = model(cfg, data, idx, draws, beta)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if run.is_main and (step % cfg.val_every == 0 or step == cfg.steps):
            with run.device:  # the tensors the validation creates on the run's device
                v = validation_mse(net, cfg, val, norm)
            best, best_state = record_validation(step, (loss.item(), nll, kl, cons, beta), v, cfg, t0, net, history,
                                                 best, best_state, log)
        if ckpt and (step % every == 0 or step == cfg.steps):
            ckpt.save(fit_no, {"key": key, "step": step, "net": net.state_dict(), "optimizer": opt.state_dict(),
                               "history": history, "best": best, "best_state": best_state,
                               "elapsed_s": time.perf_counter() - t0}, [gen, draws])
    net.cpu()
    if run.is_main:
        net.load_state_dict(best_state)
    net.eval()
    return net, norm, history, best


def record_validation(step: int, losses: tuple, v: dict, cfg: TrainConfig, t0: float, net: DeepProMPNet,
                      history: list, best: float, best_state, log):
    """One validation of the training loop: its record appended to ``history`` (``losses`` = loss, nll,
    kl, consistency, β of the update; ``v`` the validation MSE; samples/s since ``t0``), the weights kept
    when they are the best so far, one log line. Returns (best, best_state)."""
    loss, nll, kl, cons, beta = losses
    rec = {"step": step, "loss": loss, "nll": nll, "kl": kl, "consistency": cons, "beta": beta, "val": v,
           "samples_per_s": step * cfg.batch_size / (time.perf_counter() - t0)}
    history.append(rec)
    mark = ""
    if v["mean"] < best:
        best, best_state, mark = v["mean"], {k: t.clone() for k, t in net.state_dict().items()}, " *best"
    log(f"step {step:6d}/{cfg.steps}  loss {loss:10.3f}  nll {nll:9.3f}  kl {kl:8.3f}  "
        f"val_mse {v['mean']:.3e} rad²  {rec['samples_per_s']:.0f} traj/s{mark}")
    return best, best_state


def new_network(ds, cfg: TrainConfig) -> DeepProMPNet:
    """A freshly initialized network (torch's global generator) for the data layout of ``ds`` (its
    ``joint_names``, ``phase_type``, ``context_dims`` and ``image_shape``) and the architecture of ``cfg``."""
    mcfg = ModelConfig(n_joints=len(ds.joint_names), phase_type=ds.phase_type, latent_dim=cfg.latent_dim,
                       hidden=cfg.hidden, context_dims=tuple(ds.context_dims.items()),
                       image_shape=ds.image_shape, sigma_y=cfg.sigma_y, var_floor=cfg.var_floor,
                       phase_harmonics=cfg.phase_harmonics, decoder_basis=cfg.decoder_basis,
                       basis_width=cfg.basis_width, residual_scale=cfg.residual_scale,
                       variance_head=cfg.variance_head, latent_linear=cfg.latent_linear, via_noise=cfg.via_noise,
                       mode_noise=cfg.mode_noise, decoder_modes=cfg.linear_modes if cfg.linear_modes > 1 else 0)
    return DeepProMPNet(mcfg)


def new_optimizer(net: DeepProMPNet, cfg: TrainConfig) -> torch.optim.Optimizer:
    """Adam over the network's parameters; the linear part learns at lr · basis_lr_scale (0: kept as
    initialized)."""
    if not cfg.decoder_basis:
        return torch.optim.Adam(net.parameters(), lr=cfg.lr)
    rest = [p for n, p in net.named_parameters() if not n.startswith("basis.")]
    groups = [{"params": rest}]
    if cfg.basis_lr_scale > 0:
        groups.append({"params": list(net.basis.parameters()), "lr": cfg.lr * cfg.basis_lr_scale})
    else:
        net.basis.requires_grad_(False)
    return torch.optim.Adam(groups, lr=cfg.lr)


def selection_line(selection: dict) -> str:
    """The one log line of ``auto_select``'s choices (``selection`` as :func:`train` records it)."""
    lin, res = selection["linear_part"], selection["residual"]
    cv = lin.get("cross_validation")
    how = f"CV MSE {cv['cv_mse']:.3e} rad², " if cv else ""
    r = (f"residual {'kept' if res['kept'] else 'dropped'} (energy score's relative difference "
         f"{res['relative_difference']:+.3f} ± {res['standard_error']:.3f}, the via-point means' "
         f"{res['via_mean_relative_difference']:+.3f} ± {res['via_mean_standard_error']:.3f} on the {res['n_val']} "
         f"{res['judged_on']})" if "relative_difference" in res else f"residual: {res['reason']}")
    fallback = selection.get("modes_fallback")
    modes_cv = lin.get("modes", {}).get("cross_validation")
    if modes_cv and not modes_cv["admitted"]:
        worst = max((i for i, w in enumerate(modes_cv["worse"]) if w), key=lambda i: modes_cv["relative_difference"][i])
        modes = (f"{lin['modes']['n_modes']} modes of the basis weights not admitted (their executed mean from "
                 f"{modes_cv['conditionings'][worst]}: MSE {modes_cv['relative_difference'][worst]:+.1%} ± "
                 f"{modes_cv['standard_error'][worst]:.1%}, cross-validated): linear_modes 1")
    elif not fallback:
        modes = f"linear_modes {lin['linear_modes']}"
    elif fallback["kept_modes"] and "reason" in fallback:
        modes = f"linear_modes {lin['linear_modes']} ({fallback['reason']})"
    elif fallback["kept_modes"]:
        modes = (f"linear_modes {lin['linear_modes']} kept over one mode (energy score's relative difference "
                 f"{fallback['relative_difference']:+.3f} ± {fallback['standard_error']:.3f}; via_noise "
                 f"{fallback['noise']['via_noise']:g}, mode_noise {fallback['noise']['mode_noise']:g})")
    else:
        why = fallback.get("reason") or (f"not better than one mode: energy score's relative difference "
                                         f"{fallback['relative_difference']:+.3f} ± {fallback['standard_error']:.3f}, "
                                         f"the via-point means' {fallback['via_mean_relative_difference']:+.3f}"
                                         + ("" if fallback.get("means_not_worse", True) else
                                            ", a conditioning's executed mean worse"))
        modes = f"linear_modes {lin['linear_modes']} ({why}): linear_modes 1"
    return (f"selected on the training demos: decoder_basis {lin['decoder_basis']}, latent_linear "
            f"{lin['latent_linear']} (latent_dim {lin['latent_dim']}), basis_cov_reg {lin['basis_cov_reg']:g} "
            f"({lin['basis_cov_reg_units']}), via_noise {lin['via_noise']:g} ({how}{lin['method']}), {modes}; {r}")


def context_line(record: dict) -> str:
    """The log line of :func:`~deepprompt_ros.training.selection.choose_context_paths`' choice."""
    if "reason" in record:
        return f"contexts: encoders only ({record['reason']})"
    rel = ", ".join(f"{k} {v:.3g}" for k, v in record["relative"].items())
    ev = record.get("encoders_vs_linear")
    paired = (f"; encoders minus linear {ev['difference']:+.3g} ± {ev['standard_error']:.3g}" if ev else "")
    return f"contexts: {record['chosen']} (validation MSE relative to the encoders': {rel}{paired})"
