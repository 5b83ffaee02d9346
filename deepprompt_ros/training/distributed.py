"""Data-parallel training on PyTorch's distributed runtime: the process group that ``torchrun``
(``python -m torch.distributed.run``) sets up, :class:`~torch.nn.parallel.DistributedDataParallel`
around the loss, and the device of a run.

A run launched by ``torchrun`` has the environment variables ``RANK``, ``WORLD_SIZE``,
``LOCAL_RANK``, ``MASTER_ADDR`` and ``MASTER_PORT`` (documented with ``torch.distributed.run``);
:func:`runtime_from_env` reads them and :func:`init` joins the process group (gloo on the CPU,
NCCL on CUDA devices) with the ``env://`` rendezvous those variables describe. Every process draws
the same total batch of ``batch_size`` demonstrations from one generator seeded alike on every
process and trains on its share (``batch_size / WORLD_SIZE``, :meth:`Runtime.share`); DDP averages the
gradients, so an update is that of the whole batch's mean loss. The inputs each demonstration is
given and its latent samples come from each process's own generator (:meth:`Runtime.generators`), so
one process and several reach the same validation error within the run-to-run noise, not the same
weights. Process 0 (rank 0) validates, keeps the best weights and writes the checkpoints; the others
stop at the end of the training.
"""
from __future__ import annotations

import dataclasses
import os
from typing import Any

import numpy as np
import torch
import torch.distributed as dist

from deepprompt_ros.model.network import DeepProMPNet

__all__ = ["DEVICES", "Runtime", "SINGLE", "resolve_device", "runtime_from_env", "init", "finish", "shutdown",
           "LossModule", "wrap", "judge_on_main"]

#: values of ``TrainConfig.device``
DEVICES = ("auto", "cpu", "cuda")
#: the variables torchrun sets in every process it starts
_TORCHRUN_ENV = ("RANK", "WORLD_SIZE", "LOCAL_RANK")
#: and those of the env:// rendezvous
_RENDEZVOUS_ENV = ("MASTER_ADDR", "MASTER_PORT")


@dataclasses.dataclass(frozen=True)
class Runtime:
    """Where one training process runs: its rank among ``world_size`` processes, its device and the
    process group's backend (``None``: a single process, no process group)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: torch.device = torch.device("cpu")
    backend: str | None = None

    @property
    def is_main(self) -> bool:
        """Process 0: it validates and writes the checkpoints."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.backend is not None

    def check(self, cfg) -> None:
        """Refuse a training configuration (``TrainConfig``) this run cannot train: a total batch the processes
        cannot share evenly; with several processes, the residual's cross-validation (``residual_folds``),
        whose trainings would run on process 0 alone while the others wait on it."""
        errors = []
        if cfg.batch_size % self.world_size:
            errors.append(f"batch_size = {cfg.batch_size} is not divisible by the {self.world_size} processes of this "
                          f"run (WORLD_SIZE): expected a multiple of {self.world_size} (each process trains on "
                          "batch_size / WORLD_SIZE demonstrations per update)")
        if self.world_size > 1 and cfg.auto_select and cfg.residual_folds:
            errors.append(f"residual_folds = {cfg.residual_folds} with {self.world_size} processes: its "
                          f"{cfg.residual_folds} trainings of the residual's cross-validation would run on process 0 "
                          "alone; expected residual_folds 0 under torchrun (or train in one process)")
        if errors:
            raise ValueError("; ".join(errors))

    def share(self, idx: torch.Tensor) -> torch.Tensor:
        """This process's part of the total batch ``idx`` (B,): (B / world_size,), the whole of it in one process."""
        per = idx.shape[0] // self.world_size
        return idx[self.rank * per:(self.rank + 1) * per]

    def place(self, net: DeepProMPNet, *tensors):
        """``net`` moved to this process's device (in place) and each of ``tensors`` (tensors, or dataclasses
        / named tuples of tensors, ``None`` passed through) as a copy on it."""
        net.to(self.device)
        return tuple(_to(t, self.device) for t in tensors)

    def generators(self, seed: int) -> tuple[torch.Generator, torch.Generator]:
        """(batch generator, draw generator). The batch generator draws the total batch's demos and is
        seeded alike on every process; the draw generator draws the inputs given and the latent samples
        of this process's share. In one process they are one generator (seed ``seed``); with several,
        each process's draws come from its own seed derived from (``seed``, rank)."""
        batch = torch.Generator(self.device).manual_seed(seed)
        if self.world_size == 1:
            return batch, batch
        own = int(np.random.SeedSequence([seed, self.rank]).generate_state(1, dtype=np.uint64)[0] >> 1)
        return batch, torch.Generator(self.device).manual_seed(own)

    def label(self) -> str:
        """What the run used, for the log and the checkpoint's provenance."""
        if not self.distributed:
            return f"device {self.device}, one process"
        return f"device {self.device}, backend {self.backend}, {self.world_size} processes (torchrun)"

    # -- collectives (identity in one process)
    def broadcast(self, obj: Any) -> Any:
        """Process 0's ``obj`` on every process (picklable objects)."""
        if not self.distributed:
            return obj
        box = [obj if self.is_main else None]
        dist.broadcast_object_list(box, src=0)
        return box[0]

    def gather(self, obj: Any) -> list | None:
        """Every process's ``obj`` in rank order on process 0 (``None`` on the others)."""
        if not self.distributed:
            return [obj]
        out = [None] * self.world_size if self.is_main else None
        dist.gather_object(obj, out, dst=0)
        return out


def _to(obj, device: torch.device):
    if obj is None or isinstance(obj, (int, float, str)):
        return obj
    if isinstance(obj, torch.Tensor):
        return obj.to(device)
    if isinstance(obj, dict):
        return {k: _to(v, device) for k, v in obj.items()}
    if dataclasses.is_dataclass(obj):
        return dataclasses.replace(obj, **{f.name: _to(getattr(obj, f.name), device) for f in dataclasses.fields(obj)})
    if isinstance(obj, tuple) and hasattr(obj, "_fields"):  # a NamedTuple
        return type(obj)(*(_to(v, device) for v in obj))
    raise TypeError(f"cannot move {type(obj).__name__} to {device}")


def judge_on_main(run: Runtime, net, judge):
    """``judge()`` -> (network, record) made on process 0 alone (the residual's judgement); the record
    shared with every process, the others keeping their ``net``."""
    kept, record = judge() if run.is_main else (net, None)
    return kept, run.broadcast(record)


#: the runtime of a plain (not torchrun) process on the CPU
SINGLE = Runtime()


def resolve_device(name: str, local_rank: int = 0) -> torch.device:
    """The device ``TrainConfig.device`` names: ``auto`` is the process's GPU when CUDA is available
    (GPU ``local_rank`` modulo their count), the CPU otherwise."""
    if name not in DEVICES:
        raise ValueError(f"device = {name!r}: expected one of {', '.join(DEVICES)}")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("device = 'cuda' but CUDA is not available to this PyTorch (torch.cuda.is_available() is "
                         f"False; torch {torch.__version__}): expected device cpu or auto")
    if name == "cpu" or not torch.cuda.is_available():
        return torch.device("cpu")
    return torch.device("cuda", local_rank % torch.cuda.device_count())


def runtime_from_env(device: str, env=None) -> Runtime:
    """The runtime of this process: launched by torchrun (``RANK``, ``WORLD_SIZE`` and ``LOCAL_RANK`` set)
    a member of a process group, gloo on the CPU and NCCL on CUDA; otherwise :data:`SINGLE` on ``device``.
    The process group is not joined yet (:func:`init`)."""
    env = os.environ if env is None else env
    present = [k for k in _TORCHRUN_ENV if k in env]
    if not present:
        return Runtime(device=resolve_device(device))
    if len(present) < len(_TORCHRUN_ENV):
        missing = sorted(set(_TORCHRUN_ENV) - set(present))
        raise ValueError(f"environment has {', '.join(present)} but not {', '.join(missing)}: expected all of "
                         f"{', '.join(_TORCHRUN_ENV)} (launch with torchrun) or none of them (one process)")
    try:
        rank, world, local = (int(env[k]) for k in _TORCHRUN_ENV)
    except ValueError:
        values = [env[k] for k in _TORCHRUN_ENV]
        raise ValueError(f"RANK, WORLD_SIZE, LOCAL_RANK = {values}: expected integers") from None
    if not 0 <= rank < world:
        raise ValueError(f"RANK = {rank}, WORLD_SIZE = {world}: expected 0 <= RANK < WORLD_SIZE")
    rendezvous = [k for k in _RENDEZVOUS_ENV if not env.get(k)]
    if rendezvous:
        raise ValueError(f"environment has {', '.join(_TORCHRUN_ENV)} but not {', '.join(rendezvous)}: expected the "
                         "address and port of process 0 too (torchrun sets them), or none of RANK, WORLD_SIZE, "
                         "LOCAL_RANK (one process)")
    dev = resolve_device(device, local)
    return Runtime(rank, world, local, dev, "nccl" if dev.type == "cuda" else "gloo")


def init(run: Runtime) -> None:
    """Join the process group of ``run`` (``env://``: MASTER_ADDR, MASTER_PORT, RANK, WORLD_SIZE)."""
    if not run.distributed:
        return
    if run.device.type == "cuda":
        torch.cuda.set_device(run.device)
    dist.init_process_group(backend=run.backend, rank=run.rank, world_size=run.world_size)


def finish(run: Runtime) -> None:
    """Wait until every process has ended its training (a barrier): no process leaves the group, and
    no node's agent closes the rendezvous store, while another still talks to it."""
    if run.distributed and dist.is_initialized():
        dist.barrier()


def shutdown(run: Runtime) -> None:
    """Leave the process group (every process, after the last collective)."""
    if run.distributed and dist.is_initialized():
        dist.destroy_process_group()


class LossModule(torch.nn.Module):
    """The training loss of ``net`` as a module's ``forward``, the call that
    :class:`~torch.nn.parallel.DistributedDataParallel` synchronizes the gradients of (DDP hooks the
    backward of what its ``forward`` computed; the loss calls the network's encoders and decoder
    rather than one ``forward``). The tensors the loss creates are made on ``device``."""

    def __init__(self, net: DeepProMPNet, loss, device: torch.device):
        super().__init__()
        self.net = net
        self._loss = loss
        self._device = device

    def forward(self, *args):
        with self._device:  # the tensors the loss creates, on the network's device
            return self._loss(self.net, *args)


def wrap(net: DeepProMPNet, loss, run: Runtime) -> torch.nn.Module:
    """``loss(net, ...)`` as a module: under DDP when ``run`` is distributed (process 0's weights
    are broadcast to the others here), plain otherwise."""
    module = LossModule(net, loss, run.device)
    if not run.distributed:
        return module
    ids = [run.device.index] if run.device.type == "cuda" else None
    return torch.nn.parallel.DistributedDataParallel(module, device_ids=ids)
