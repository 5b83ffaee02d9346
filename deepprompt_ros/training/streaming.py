"""Training on a sharded dataset on disk (:class:`~deepprompt_ros.data.sharded.ShardedDataset`) with
bounded memory (:func:`train_sharded`, which ``train --data`` runs on a folder with ``index.json``): the
steps of :func:`deepprompt_ros.training.loop.train` with the demonstrations read when they are needed.

- the normalization in one streaming pass over the training demos (:func:`streaming_normalization`:
  per-joint and per-context mean and variance merged demo by demo, Chan, Golub & LeVeque, "Algorithms
  for computing the sample variance", 1979, the pairwise update);
- each update's batch read from the shards' memory maps and padded to the dataset's largest counts
  (:class:`ShardBatches`), by ``data_workers`` worker processes of a ``torch.utils.data.DataLoader``;
  the same loss (:func:`~deepprompt_ros.training.objectives.loss_fn` on the batch);
- the validation on at most ``val_max_demos`` held-out demos, read in chunks of :data:`VAL_CHUNK`
  (:func:`chunked_validation_mse`, the MSE of :func:`~deepprompt_ros.training.objectives.validation_mse`);
- ``auto_select``'s cross-validation and the PCA initialization of the linear part on at most
  ``select_max_demos`` training demos (a seeded subset), the residual judged on the validation
  subset; both subsets recorded in the selection's metadata (``bounded``). With K > 1 modes the
  decoder's modes (their offsets and shares) are the subset's.

Under torchrun (:mod:`deepprompt_ros.training.distributed`, the CPU) each process reads its share of
every batch, process 0 selects, validates and writes; a sharded training writes no resume file.

With at most ``select_max_demos`` training and ``val_max_demos`` held-out demos and ``data_workers``
0, the model is the one the same demos give in memory (the split, the draws and the initialization
are the same; test/test_sharded_training.py measures the difference).
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import Sequence

import numpy as np
import torch

from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.data.demonstration import DatasetError, Demonstration
from deepprompt_ros.data.sharded import ShardedDataset
from deepprompt_ros.model.aggregation import bayesian_aggregate
from deepprompt_ros.model.checkpoint import Normalization
from deepprompt_ros.model.network import DeepProMPNet
from deepprompt_ros.training.basis import init_basis_pca
from deepprompt_ros.training.config import TrainConfig
from deepprompt_ros.training.distributed import SINGLE, Runtime, wrap
from deepprompt_ros.training.loop import (judge_with_fallback, new_network, new_optimizer, record_validation,
                                          write_model)
from deepprompt_ros.training.objectives import encode_all, loss_fn
from deepprompt_ros.training.selection import select_linear_part
from deepprompt_ros.training.tensors import TensorData, demos_to_tensors, to_tensors

__all__ = ["train_sharded", "streaming_normalization", "ShardBatches", "chunked_validation_mse", "bounded_subset",
           "VAL_CHUNK"]

#: Held-out demos encoded at once by the validation.
VAL_CHUNK = 32


def bounded_subset(ids: np.ndarray, cap: int, seed: int) -> np.ndarray:
    """``ids`` when there are at most ``cap`` of them, else ``cap`` of them drawn without replacement
    (seed ``[seed, cap]``); sorted."""
    ids = np.asarray(ids, dtype=np.int64)
    if len(ids) <= cap:
        return ids
    return np.sort(np.random.default_rng([seed, cap]).choice(ids, cap, replace=False))


def streaming_normalization(ds: ShardedDataset, ids: Sequence[int], n_points: int) -> Normalization:
    """:func:`~deepprompt_ros.training.tensors.fit_normalization` of the demos ``ids`` of ``ds`` in one
    pass, one shard in memory at a time: per joint the mean and standard deviation (>= 1e-3) of the
    demos resampled at ``n_points`` phases, per context modality those of its vectors."""
    stats = {}  # name -> (count, mean, M2): the sum of squared deviations from the mean

    def merge(name: str, v: np.ndarray):  # v (n, c): Chan et al.'s pairwise update
        n_b, mean_b = v.shape[0], v.mean(0)
        m2_b = ((v - mean_b) ** 2).sum(0)
        if name not in stats:
            stats[name] = (n_b, mean_b, m2_b)
            return
        n_a, mean_a, m2_a = stats[name]
        n = n_a + n_b
        delta = mean_b - mean_a
        stats[name] = (n, mean_a + delta * n_b / n, m2_a + m2_b + delta ** 2 * n_a * n_b / n)

    for _, demo in ds.iter_shards(ids, images=False):
        merge("\0y", demo.resampled(n_points))
        for name in ds.context_dims:
            merge(name, np.asarray(demo.contexts[name], dtype=np.float64))

    def mean_std(name):
        n, mean, m2 = stats[name]
        return mean, np.maximum(np.sqrt(m2 / n), 1e-3)

    y_mean, y_std = mean_std("\0y")
    ctx = {name: mean_std(name) for name in ds.context_dims}
    return Normalization(y_mean, y_std, {k: v[0] for k, v in ctx.items()}, {k: v[1] for k, v in ctx.items()})


class ShardBatches(torch.utils.data.Dataset):
    """Batches of a sharded dataset as :class:`~deepprompt_ros.training.tensors.TensorData`: item
    ``positions`` (a 1-D tensor of positions in ``ids``) is (positions, the batch of those demos,
    normalized with ``norm``, resampled at ``n_points`` phases, contexts and images padded to the
    dataset's largest counts: the tensors :func:`~deepprompt_ros.training.tensors.to_tensors` gives)."""

    def __init__(self, ds: ShardedDataset, ids: np.ndarray, norm: Normalization, n_points: int):
        self.ds, self.ids, self.norm, self.n_points = ds, np.asarray(ids, dtype=np.int64), norm, n_points

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, positions) -> tuple[torch.Tensor, TensorData]:
        positions = torch.as_tensor(positions)
        return positions, self.tensors(self.ds.read(self.ids[positions.numpy()]))

    def tensors(self, demos: list[Demonstration]) -> TensorData:
        """``demos`` as the tensors of :func:`~deepprompt_ros.training.tensors.to_tensors` (padded to the
        dataset's largest counts)."""
        ds = self.ds
        return demos_to_tensors(demos, self.norm, self.n_points, ds.context_dims, ds.image_shape, ds.max_contexts,
                                ds.max_images)


class _BatchDraws(torch.utils.data.Sampler):
    """``steps`` batches of ``batch_size`` positions in [0, n) drawn with replacement from a generator
    seeded ``seed`` (the order the workers' batches come back in), each cut to this process's share
    (``share``: :meth:`~deepprompt_ros.training.distributed.Runtime.share`)."""

    def __init__(self, n: int, batch_size: int, steps: int, seed: int, share=lambda idx: idx):
        self.n, self.batch_size, self.steps, self.seed, self.share = n, batch_size, steps, seed, share

    def __len__(self) -> int:
        return self.steps

    def __iter__(self):
        gen = torch.Generator().manual_seed(self.seed)
        for _ in range(self.steps):
            yield self.share(torch.randint(0, self.n, (self.batch_size,), generator=gen))


@torch.no_grad()
def chunked_validation_mse(net: DeepProMPNet, cfg: TrainConfig, batches: ShardBatches, norm: Normalization) -> dict:
    """:func:`~deepprompt_ros.training.objectives.validation_mse` of the demos of ``batches`` (its
    conditionings: ``val_via_points`` seeded random via-points, the contexts and images, both), read
    and encoded :data:`VAL_CHUNK` demos at a time; the squared errors summed in float64."""
    net.eval()
    n, t = len(batches), batches.n_points
    rank = torch.rand(n, t, generator=torch.Generator().manual_seed(12345)).argsort(1).argsort(1)
    sums: dict[str, float] = {}
    count = 0
    scale = torch.tensor(norm.y_std, dtype=torch.float32)
    for start in range(0, n, VAL_CHUNK):
        positions = torch.arange(start, min(n, start + VAL_CHUNK))
        _, data = batches[positions]
        b = len(positions)
        mu, var, kinds = encode_all(net, data, torch.arange(b))
        via = (rank[positions] < cfg.val_via_points).float()
        weights = {"via": [], "context": [], "both": []}
        for kind, sl in kinds:
            width = sl.stop - sl.start
            if kind == "via":
                weights["via"].append(via), weights["both"].append(via)
                weights["context"].append(torch.zeros(b, width))
            else:
                mask = data.image_mask.amax(1, keepdim=True) if kind == "image" else data.ctx_mask[kind]
                weights["via"].append(torch.zeros(b, width)), weights["context"].append(mask)
                weights["both"].append(mask)
        for name, parts in weights.items():
            if name != "via" and len(kinds) == 1:
                continue
            mu_z, _ = bayesian_aggregate(mu, var, torch.cat(parts, 1))
            err = (net.decode(mu_z, data.x) - data.y) * scale
            sums[name] = sums.get(name, 0.0) + float((err.double() ** 2).sum())
        count += int(data.y.numel())
    out = {name: s / count for name, s in sums.items()}
    out["mean"] = float(np.mean(list(out.values())))
    net.train()
    return out


def train_sharded(ds: ShardedDataset, cfg: TrainConfig, out_path=None, log=print, info: dict | None = None,
                  run: Runtime = SINGLE):
    """:func:`deepprompt_ros.training.loop.train` on a sharded dataset with bounded memory (see the
    module's docstring). The validation split is that of
    :meth:`~deepprompt_ros.data.demo_dataset.DemoDataset.split` (``n_val``, seed ``cfg.seed``).
    ``run``: this process's place in a data-parallel run on the CPU, as in ``train`` (each process reads
    its share of every batch; the selection and the residual's judgement on process 0, shared).

    Returns
    -------
    net : DeepProMPNet (best validation weights), norm : Normalization, history : list of dict
    """
    torch.set_num_threads(cfg.threads)
    run.check(cfg)
    if run.device.type != "cpu":
        raise ValueError(f"a sharded dataset trains on the CPU (this run: {run.device}): expected device cpu")
    t0 = time.perf_counter()
    n = len(ds)
    n_val = cfg.n_val or max(1, n // 10)
    if not 0 < n_val < n:
        raise DatasetError(f"validation split of {n_val} needs 0 < n_val < {n} demonstrations")
    perm = np.random.default_rng(cfg.seed).permutation(n)
    train_ids, held_ids = np.sort(perm[n_val:]), np.sort(perm[:n_val])
    select_ids = bounded_subset(train_ids, cfg.select_max_demos, cfg.seed)
    val_ids = bounded_subset(held_ids, cfg.val_max_demos, cfg.seed)
    selection = {"bounded": {"train_demos": len(train_ids), "held_out_demos": len(held_ids),
                             "select_demos": len(select_ids), "val_demos": len(val_ids), "seed": cfg.seed,
                             "select_max_demos": cfg.select_max_demos, "val_max_demos": cfg.val_max_demos}}
    images_for_refit = cfg.auto_select and cfg.residual_folds >= 2

    def select_ds() -> DemoDataset:  # the training demos auto_select and the PCA initialization read
        return DemoDataset(tuple(ds.read(select_ids, images=images_for_refit)), f"{ds.source}:select")

    if cfg.auto_select:
        cfg, selection["linear_part"] = run.broadcast(
            select_linear_part(select_ds(), cfg, len(ds.joint_names)) if run.is_main else None)
    fitted = _fit(ds, train_ids, val_ids, select_ids, cfg, log, run)
    if cfg.auto_select:  # the residual's cross-validation, in memory on folds of the selection's demos
        val_ds = DemoDataset(tuple(ds.read(val_ids)), f"{ds.source}:val") if run.is_main else None
        fit_ds = select_ds() if images_for_refit else None
        cfg, fitted = judge_with_fallback(cfg, fitted, selection, log,
                                          lambda c: _fit(ds, train_ids, val_ids, select_ids, c, log, run),
                                          run, ds.joint_names, val_ds, fit_ds)
        del val_ds, fit_ds
    net, norm, history, best = fitted
    if info is not None:
        info.update(train_config=dataclasses.asdict(cfg), selection=selection)
    if out_path is not None and run.is_main:
        write_model(out_path, net, norm, ds, cfg, selection, run, (len(train_ids), len(held_ids)), best, t0)
    return net, norm, history


def _fit(ds: ShardedDataset, train_ids: np.ndarray, val_ids: np.ndarray, select_ids: np.ndarray, cfg: TrainConfig,
         log, run: Runtime = SINGLE):
    """:func:`deepprompt_ros.training.loop._fit` reading the demos from ``ds``: the normalization of
    ``train_ids`` streamed, the PCA initialization on ``select_ids``, ``cfg.steps`` updates on
    batches of ``train_ids``, the validation on ``val_ids``. Returns (net with the best validation
    weights, normalization, history, best validation MSE)."""
    torch.manual_seed(cfg.seed)
    norm = streaming_normalization(ds, train_ids, cfg.n_points)
    net = new_network(ds, cfg)
    if cfg.decoder_basis and cfg.basis_init == "pca":
        sub = to_tensors(DemoDataset(tuple(ds.read(select_ids, images=False)), ds.source), norm, cfg.n_points)
        init_basis_pca(net, sub, cfg.basis_cov_reg,
                       joint_std=np.asarray(norm.y_std) if cfg.basis_cov_reg_units == "raw" else None,
                       n_modes=cfg.linear_modes, seed=cfg.seed)
        del sub
    opt = new_optimizer(net, cfg)
    gen, draws = run.generators(cfg.seed)  # the batch's demos; the inputs given and z (one generator in one process)
    model = wrap(net, loss_fn, run)  # DDP averages the processes' gradients
    batches = ShardBatches(ds, train_ids, norm, cfg.n_points)
    val = ShardBatches(ds, val_ids, norm, cfg.n_points)
    n_train = len(train_ids)
    loader = None
    if cfg.data_workers > 0:
        loader = iter(torch.utils.data.DataLoader(
            batches, batch_size=None, sampler=_BatchDraws(n_train, cfg.batch_size, cfg.steps, cfg.seed, run.share),
            num_workers=cfg.data_workers, worker_init_fn=_worker_threads))
    history, best, best_state = [], math.inf, None
    t0 = time.perf_counter()
    local = torch.arange(cfg.batch_size // run.world_size)
    for step in range(1, cfg.steps + 1):
        if loader is None:  # drawn as loop._fit draws them
            idx, data = batches[run.share(torch.randint(0, n_train, (cfg.batch_size,), generator=gen))]
        else:
            try:
                idx, data = next(loader)
            except DatasetError as exc:  # re-raised from a worker with its traceback: the message is at its end
                raise DatasetError(str(exc).rstrip().rpartition("DatasetError: ")[2]) from None
        beta = cfg.beta * min(1.0, step / max(1, cfg.kl_anneal_steps))  # KL annealing
        loss, nll, kl, cons = model(cfg, data, local, draws, beta)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if run.is_main and (step % cfg.val_every == 0 or step == cfg.steps):
            v = chunked_validation_mse(net, cfg, val, norm)
            best, best_state = record_validation(step, (loss.item(), nll, kl, cons, beta), v, cfg, t0, net, history,
                                                 best, best_state, log)
    del loader  # ends the worker processes
    if run.is_main:
        net.load_state_dict(best_state)
    net.eval()
    return net, norm, history, best


def _worker_threads(_worker_id: int):
    """A worker process assembles batches with one torch thread (the training keeps its own)."""
    torch.set_num_threads(1)
