"""The resume file of a training run (``OUT.resume.pt`` beside the checkpoint ``OUT.safetensors``):
everything an interrupted run needs to continue exactly where it stopped.

It holds one entry per training proper (:func:`deepprompt_ros.training.loop.train` fits once, or
twice when ``auto_select`` falls back to one mode), each with the network's and the optimizer's
state, the update reached, the state of every process's random generators, the best validation so
far (its weights and error) and the validation history; and what the entry was trained on: the
configuration of the fit (its ``steps``, ``threads``, ``device`` and ``checkpoint_every`` aside),
a digest of the resampled, normalized training and validation demonstrations, and the number of
processes. A run continued from the file with the same seed reaches the same weights as a run that
was never interrupted (with more ``steps`` than the file's run had: when that run's ``steps`` is a
multiple of ``val_every``, so both validated at the same updates). Process 0 writes the file
(atomically: a kill while writing leaves the previous one) and reads it; the other processes get
their part through the process group. ``torch.save`` / ``torch.load`` (``weights_only``: tensors
and plain containers only) is its format, an internal one: the model file stays the safetensors
checkpoint.
"""
from __future__ import annotations

import copy
import dataclasses
import hashlib
import os
import pathlib

import torch

from deepprompt_ros.training.config import TrainConfig
from deepprompt_ros.training.distributed import Runtime
from deepprompt_ros.training.tensors import TensorData

__all__ = ["RUN_KEYS", "resume_path", "data_digest", "fit_key", "ResumeFile"]

#: configuration keys that change how a run runs, not what it computes
RUN_KEYS = ("steps", "threads", "device", "checkpoint_every")
FORMAT = 1


def resume_path(out_path) -> pathlib.Path:
    """``models/reach.safetensors`` -> ``models/reach.resume.pt``."""
    return pathlib.Path(out_path).with_suffix(".resume.pt")


def data_digest(*datasets: TensorData) -> str:
    """SHA-256 of the demonstrations as trained on: joint positions, contexts and their masks
    (images by their shape)."""
    h = hashlib.sha256()
    for d in datasets:
        tensors = [d.y, d.x, *(d.ctx[k] for k in sorted(d.ctx)), *(d.ctx_mask[k] for k in sorted(d.ctx_mask))]
        for t in tensors:
            h.update(str(tuple(t.shape)).encode())
            h.update(t.detach().cpu().contiguous().numpy().tobytes())
        h.update(str(None if d.images is None else tuple(d.images.shape)).encode())
    return h.hexdigest()


def fit_key(cfg: TrainConfig, digest: str, world_size: int) -> dict:
    """What a fit's entry must match to be continued."""
    config = {k: v for k, v in dataclasses.asdict(cfg).items() if k not in RUN_KEYS}
    return {"config": config, "data": digest, "world_size": world_size}


def _differences(saved: dict, now: dict) -> list[str]:
    out = []
    if saved["world_size"] != now["world_size"]:
        out.append(f"it was written by {saved['world_size']} process(es), this run has {now['world_size']}")
    if saved["data"] != now["data"]:
        out.append("its demonstrations (training and validation split, resampled and normalized) differ from this "
                   "run's")
    keys = sorted(set(saved["config"]) | set(now["config"]))
    changed = [f"{k} {saved['config'].get(k)!r} -> {now['config'].get(k)!r}" for k in keys
               if saved["config"].get(k) != now["config"].get(k)]
    if changed:
        out.append("configuration keys differ: " + ", ".join(changed))
    return out


class ResumeFile:
    """The resume file at ``path`` for the run ``run``; with ``load`` its entries are read (process 0)
    and shared with every process, refused when the file is missing or unreadable."""

    def __init__(self, path, run: Runtime, load: bool):
        self.path = pathlib.Path(path)
        self.run = run
        self.fits: list[dict] = []
        if load:
            payload, error = None, None
            if run.is_main:
                payload, error = self._read()
            payload, error = run.broadcast((payload, error))
            if error:
                raise ValueError(error)
            self.fits = payload["fits"]

    def _read(self):
        if not self.path.is_file():
            return None, (f"--resume: no resume file '{self.path}': expected the file an earlier run with the same "
                          "--out wrote (OUT.resume.pt), or a run without --resume")
        try:
            payload = torch.load(self.path, map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - any unreadable file is refused with its reason
            return None, f"--resume: '{self.path}' is not a readable resume file ({type(exc).__name__}: {exc})"
        if not isinstance(payload, dict) or payload.get("format") != FORMAT or "fits" not in payload:
            return None, f"--resume: '{self.path}' is not a resume file of format {FORMAT}"
        return payload, None

    def restore(self, fit_no: int, key: dict) -> dict | None:
        """The entry of fit ``fit_no`` when the file has one (``None``: start it afresh); refused when it was
        trained on something else than ``key``. Continuing a fit drops the entries after it (they
        followed from its earlier end)."""
        if fit_no >= len(self.fits):
            return None
        entry = self.fits[fit_no]
        diff = _differences(entry["key"], key)
        if diff:
            raise ValueError(f"--resume: '{self.path}' does not match this run: {'; '.join(diff)}. Expected the "
                             "configuration, data and number of processes of the run that wrote it (steps may "
                             "be larger)")
        del self.fits[fit_no + 1:]
        return entry

    def save(self, fit_no: int, entry: dict, generators: list) -> None:
        """Record a copy of fit ``fit_no``'s ``entry`` (process 0's states) with every process's ``generators``
        states and write the file (a collective: every process calls it at the same update)."""
        states = self.run.gather([g.get_state() for g in generators])
        if not self.run.is_main:
            return
        # a copy: the entry's tensors are the live network's and optimizer's, which change after it is recorded
        # (the best weights loaded at the fit's end) while a later fit's save writes this entry again
        entry = copy.deepcopy(dict(entry, generators=states))
        del self.fits[fit_no:]
        self.fits.append(entry)
        tmp = self.path.with_name(self.path.name + ".tmp")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        torch.save({"format": FORMAT, "fits": self.fits}, tmp)
        os.replace(tmp, self.path)  # atomic: a kill while saving leaves the previous file
