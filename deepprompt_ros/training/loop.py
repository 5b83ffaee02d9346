"""Training a DeepProMP (paper Sec. III-B): read :func:`train` top to bottom — batch → loss →
backward → eval → checkpoint. The loss and the validation are in
:mod:`deepprompt_ros.training.objectives`, the configuration in
:mod:`deepprompt_ros.training.config`; the command line is :mod:`deepprompt_ros.training.cli`.
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
from deepprompt_ros.training.objectives import loss_fn, validation_mse
from deepprompt_ros.training.tensors import fit_normalization, to_tensors

__all__ = ["train"]


def train(ds: DemoDataset, cfg: TrainConfig, out_path=None, log=print, val_ds: DemoDataset | None = None):
    """Train on ``ds`` (a validation split is held out unless ``val_ds`` is given).

    Returns
    -------
    net : DeepProMPNet (best validation weights), norm : Normalization, history : list of dict
    """
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    if val_ds is None:
        n_val = cfg.n_val or max(1, len(ds) // 10)
        train_ds, val_ds = ds.split(n_val, seed=cfg.seed)
    else:
        train_ds = ds
    norm = fit_normalization(train_ds, cfg.n_points)
    data = to_tensors(train_ds, norm, cfg.n_points)
    val = to_tensors(val_ds, norm, cfg.n_points)
    mcfg = ModelConfig(n_joints=len(ds.joint_names), phase_type=ds.phase_type, latent_dim=cfg.latent_dim,
                       hidden=cfg.hidden, context_dims=tuple(ds.context_dims.items()), image_shape=ds.image_shape,
                       sigma_y=cfg.sigma_y, var_floor=cfg.var_floor, phase_harmonics=cfg.phase_harmonics,
                       decoder_basis=cfg.decoder_basis, basis_width=cfg.basis_width,
                       residual_scale=cfg.residual_scale, variance_head=cfg.variance_head)
    net = DeepProMPNet(mcfg)
    if cfg.decoder_basis and cfg.basis_init == "pca":
        init_basis_pca(net, data, cfg.basis_cov_reg,
                       joint_std=np.asarray(norm.y_std) if cfg.basis_cov_reg_units == "raw" else None)
    if cfg.decoder_basis:  # the linear part learns at lr · basis_lr_scale (0: kept as initialized)
        rest = [p for n, p in net.named_parameters() if not n.startswith("basis.")]
        groups = [{"params": rest}]
        if cfg.basis_lr_scale > 0:
            groups.append({"params": list(net.basis.parameters()), "lr": cfg.lr * cfg.basis_lr_scale})
        else:
            net.basis.requires_grad_(False)
        opt = torch.optim.Adam(groups, lr=cfg.lr)
    else:
        opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    gen = torch.Generator().manual_seed(cfg.seed)
    history, best, best_state = [], math.inf, None
    t0 = time.perf_counter()
    n_train = data.y.shape[0]
    for step in range(1, cfg.steps + 1):
        idx = torch.randint(0, n_train, (cfg.batch_size,), generator=gen)
        beta = cfg.beta * min(1.0, step / max(1, cfg.kl_anneal_steps))  # KL annealing
        loss, nll, kl, cons = loss_fn(net, cfg, data, idx, gen, beta)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step % cfg.val_every == 0 or step == cfg.steps:
            v = validation_mse(net, cfg, val, norm)
            elapsed = time.perf_counter() - t0
            rec = {"step": step, "loss": loss.item(), "nll": nll, "kl": kl, "consistency": cons, "beta": beta, "val": v,
                   "samples_per_s": step * cfg.batch_size / elapsed}
            history.append(rec)
            mark = ""
            if v["mean"] < best:
                best, best_state, mark = v["mean"], {k: t.clone() for k, t in net.state_dict().items()}, " *best"
            log(f"step {step:6d}/{cfg.steps}  loss {loss.item():10.3f}  nll {nll:9.3f}  kl {kl:8.3f}  "
                f"val_mse {v['mean']:.3e} rad²  {rec['samples_per_s']:.0f} traj/s{mark}")
    net.load_state_dict(best_state)
    net.eval()
    if out_path is not None:
        meta = {
            "train_config": dataclasses.asdict(cfg),
            "provenance": {"dataset": ds.source, "n_train": len(train_ds), "n_val": len(val_ds),
                           "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                           "deepprompt_ros": __version__, "torch": torch.__version__},
            "metrics": {"best_val_mse_rad2": best, "wall_time_s": time.perf_counter() - t0},
        }
        save_checkpoint(out_path, net, norm, ds.joint_names, meta)
    return net, norm, history
