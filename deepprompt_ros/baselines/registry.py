"""Every model class behind the common interface, and :func:`load_model`, which opens any of
their files by the kind stored in it."""
from __future__ import annotations

from deepprompt_ros.baselines.concat import CNMP, VAECNMP, CNMPIndep, VAECNMPIndep
from deepprompt_ros.baselines.deep_promp_model import DeepProMPModel
from deepprompt_ros.baselines.interface import BASELINE_FORMAT, MovementPrimitiveModel
from deepprompt_ros.baselines.promp_model import ProMPModel
from deepprompt_ros.model.checkpoint import FORMAT as DEEPPROMP_FORMAT
from deepprompt_ros.model.safetensors_file import read_safetensors

__all__ = ["MODEL_CLASSES", "load_model"]


MODEL_CLASSES: tuple[type[MovementPrimitiveModel], ...] = (
    DeepProMPModel, ProMPModel, CNMP, CNMPIndep, VAECNMP, VAECNMPIndep)
_BY_KIND = {c.kind: c for c in MODEL_CLASSES}


def load_model(path) -> MovementPrimitiveModel:
    """Open any model file written by one of :data:`MODEL_CLASSES` (dispatch on its metadata)."""
    meta, _ = read_safetensors(path, tensors=False)
    if meta.get("format") == DEEPPROMP_FORMAT:
        return DeepProMPModel.load(path)
    if meta.get("format") == BASELINE_FORMAT and meta.get("kind") in _BY_KIND:
        return _BY_KIND[meta["kind"]].load(path)
    raise ValueError(f"model file '{path}' has format '{meta.get('format')}' kind '{meta.get('kind')}'; expected "
                     f"'{DEEPPROMP_FORMAT}' or '{BASELINE_FORMAT}' with kind in {sorted(_BY_KIND)}")
