"""Reading and writing safetensors files: raw tensors plus a JSON header of string metadata,
never pickle. Every model file of the package (DeepProMP checkpoints, the baselines) goes
through here, so a file that is missing, pickled, truncated or corrupt is refused the same way
before any of it is interpreted.

The refusal messages name what the caller expected (``expected``, ``written``, ``refused``) and
are raised as ``error`` (``ValueError`` or a subclass such as
:class:`deepprompt_ros.model.checkpoint.CheckpointError`).

File layout (safetensors): 8 bytes little-endian header size n, n bytes of JSON header (starting
with ``{``), then the tensor data the header's offsets point into.
"""
from __future__ import annotations

import json
import pathlib
from typing import Any, Mapping

import torch

__all__ = ["MAX_HEADER", "check_header", "read_safetensors", "write_safetensors", "metadata_json"]

MAX_HEADER = 100 * 1024 * 1024  # a safetensors JSON header larger than this is not one of ours


def check_header(path, *, expected: str = "a .safetensors model file",
                 written: str = "a model written by deepprompt_ros", refused: str = "pickled files",
                 error: type[ValueError] = ValueError) -> pathlib.Path:
    """Refuse, before any library parses it, a path that is missing or not a regular file, a file
    that cannot be read, a pickle or ``torch.save`` archive, and a file whose 8-byte header size is
    implausible (over :data:`MAX_HEADER`, or more than the file holds: truncated) or whose header
    is not a JSON object (a pickle, protocol 2 and later, starts with the PROTO opcode 0x80 and its
    version; a ``torch.save`` file is a zip archive holding a pickle).

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
    if not path.exists():
        raise error(f"model file '{path}' does not exist; expected {expected}")
    if not path.is_file():
        kind = "a directory" if path.is_dir() else "not a regular file"
        raise error(f"model file '{path}' is {kind}; expected {expected}")
    try:
        with open(path, "rb") as f:
            head = f.read(9)
        size = path.stat().st_size
    except OSError as exc:
        raise error(f"model file '{path}' cannot be read ({exc.strerror or exc}); expected {expected}") from exc

    def not_safetensors(reason: str) -> ValueError:
        return error(f"model file '{path}' is not a safetensors file ({reason}; {refused} are refused: they can "
                     f"run code); expected {written}")

    if len(head) < 9:
        raise error(f"model file '{path}' is {size} bytes long, too short for a safetensors file; expected {written}")
    if head[8:9] != b"{":  # a safetensors header is a JSON object
        pickled = (head[0] == 0x80 and 2 <= head[1] <= 5) or head.startswith(b"PK\x03\x04")
        raise not_safetensors("it starts like a pickle or a torch.save archive" if pickled
                              else "its header is not a JSON object")
    n = int.from_bytes(head[:8], "little")
    if n > MAX_HEADER:
        raise not_safetensors(f"its first 8 bytes give a header of {n} bytes, over the limit of {MAX_HEADER}")
    if n > size - 8:
        raise error(f"model file '{path}' is truncated or not a safetensors file: its header size says {n} bytes "
                    f"but only {size - 8} bytes follow; expected {written}")
    return path


def read_safetensors(path, tensors: bool = True, *, error: type[ValueError] = ValueError,
                     **wording) -> tuple[dict[str, str], dict[str, torch.Tensor]]:
    """(metadata, tensors) of a safetensors file (``tensors=False``: the metadata only, tensors
    ``{}``); a missing, non-safetensors, truncated or corrupt file raises ``error``. ``wording``:
    the ``expected`` / ``written`` / ``refused`` texts of :func:`check_header`."""
    from safetensors import safe_open

    path = check_header(path, error=error, **wording)
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = dict(f.metadata() or {})
            out = {k: f.get_tensor(k) for k in f.keys()} if tensors else {}
    except Exception as exc:  # safetensors raises its own error types for corrupt headers
        raise error(f"model file '{path}' is corrupt or truncated (not a complete safetensors file): {exc}") from exc
    return meta, out


_MISSING = object()


def metadata_json(meta: Mapping[str, str], key: str, path, *, kind: type = dict, default: Any = _MISSING,
                  error: type[ValueError] = ValueError):
    """The JSON value of the metadata entry ``key`` of the model file ``path``, which must be a
    ``kind`` (``dict``: a JSON object, ``list``: an array). A missing entry gives ``default`` when
    one is given; otherwise a missing entry, invalid JSON or another JSON type raises ``error``
    naming the file and the entry."""
    if key not in meta:
        if default is not _MISSING:
            return default
        raise error(f"model file '{path}' lacks the metadata entry '{key}'; expected a file written by deepprompt_ros")
    try:
        value = json.loads(meta[key])
    except ValueError as exc:
        raise error(f"model file '{path}': metadata entry '{key}' is not valid JSON ({exc})") from exc
    if not isinstance(value, kind):
        want = {dict: "a JSON object", list: "a JSON array"}.get(kind, kind.__name__)
        raise error(f"model file '{path}': metadata entry '{key}' must be {want}; got {type(value).__name__} "
                    f"{str(value)[:60]}")
    return value


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
