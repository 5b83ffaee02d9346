"""Reading and writing safetensors files: raw tensors plus a JSON header of string metadata,
never pickle. Every model file of the package (DeepProMP checkpoints, the baselines) goes
through here, so a file that is missing, pickled or corrupt is refused the same way before any
of it is interpreted.

The refusal messages name what the caller expected (``expected``, ``written``, ``refused``) and
are raised as ``error`` (``ValueError`` or a subclass such as
:class:`deepprompt_ros.model.checkpoint.CheckpointError`).
"""
from __future__ import annotations

import pathlib
from typing import Mapping

import torch

__all__ = ["MAX_HEADER", "check_header", "read_safetensors", "write_safetensors"]

MAX_HEADER = 100 * 1024 * 1024  # a safetensors JSON header larger than this is not one of ours


def check_header(path, *, expected: str = "a .safetensors model file",
                 written: str = "a model written by deepprompt_ros", refused: str = "pickled files",
                 error: type[ValueError] = ValueError) -> pathlib.Path:
    """Refuse a missing file, or one whose first 8 bytes are not a plausible safetensors header
    size (e.g. a pickle), before any library parses it.

    Parameters
    ----------
    expected : str
        What the missing file should have been ("... does not exist; expected <expected>").
    written : str
        What a valid file is ("... is not a safetensors file (...); expected <written>").
    refused : str
        The kind of file that is refused ("<refused> are refused: they can run code").
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise error(f"model file '{path}' does not exist; expected {expected}")
    with open(path, "rb") as f:
        head = f.read(8)
    if len(head) < 8 or int.from_bytes(head, "little") > min(MAX_HEADER, path.stat().st_size):
        raise error(f"model file '{path}' is not a safetensors file ({refused} are refused: they can run code); "
                    f"expected {written}")
    return path


def read_safetensors(path, tensors: bool = True, *, error: type[ValueError] = ValueError,
                     **wording) -> tuple[dict[str, str], dict[str, torch.Tensor]]:
    """(metadata, tensors) of a safetensors file (``tensors=False``: the metadata only, tensors
    ``{}``); a missing, non-safetensors or corrupt file raises ``error``. ``wording``: the
    ``expected`` / ``written`` / ``refused`` texts of :func:`check_header`."""
    from safetensors import safe_open

    path = check_header(path, error=error, **wording)
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = dict(f.metadata() or {})
            out = {k: f.get_tensor(k) for k in f.keys()} if tensors else {}
    except Exception as exc:  # safetensors raises its own error types for corrupt headers
        raise error(f"model file '{path}' is corrupt or not a safetensors file: {exc}") from exc
    return meta, out


def write_safetensors(path, tensors: Mapping[str, torch.Tensor], metadata: Mapping[str, str]) -> pathlib.Path:
    """Write ``tensors`` (moved to contiguous CPU memory) and the string ``metadata`` to ``path``
    atomically (a ``.part`` file renamed over the target); creates the parent folder."""
    from safetensors.torch import save_file

    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    save_file({k: v.detach().cpu().contiguous() for k, v in tensors.items()}, str(tmp), metadata=dict(metadata))
    tmp.replace(path)
    return path
