"""DeepProMP behind the common interface (:class:`deepprompt_ros.baselines.interface.MovementPrimitiveModel`):
an adapter over :func:`deepprompt_ros.training.loop.train` and
:class:`deepprompt_ros.primitive.deep_promp.DeepProMP` whose files are ordinary DeepProMP checkpoints."""
from __future__ import annotations

from typing import Callable

from deepprompt_ros.baselines.interface import (InputSpec, MovementPrimitiveModel, provenance,
                                                split_for_validation)
from deepprompt_ros.model.checkpoint import load_checkpoint, save_checkpoint
from deepprompt_ros.primitive.deep_promp import DeepProMP
from deepprompt_ros.primitive.latent import LatentGaussian
from deepprompt_ros.training.loop import train

__all__ = ["DeepProMPModel"]


class DeepProMPModel(MovementPrimitiveModel):
    """DeepProMP (:func:`deepprompt_ros.training.loop.train` +
    :class:`deepprompt_ros.primitive.deep_promp.DeepProMP`) behind the common interface.

    The conditioned object is a :class:`deepprompt_ros.primitive.latent.LatentGaussian`; files are
    ordinary DeepProMP checkpoints (:func:`deepprompt_ros.model.checkpoint.save_checkpoint`), so the
    primitive server can load them too.
    """

    kind = "deepprompt"

    def __init__(self, log: Callable[[str], None] | None = None):
        super().__init__()
        self.log = log
        self.primitive: DeepProMP | None = None

    def fit(self, train_ds, config, val_ds=None):
        train_ds, val_ds = split_for_validation(train_ds, config, val_ds)
        info = {}
        net, norm, hist = train(train_ds, config, out_path=None, log=self.log or (lambda s: None), val_ds=val_ds,
                                info=info)
        self.history = hist
        meta = {**info, "provenance": provenance(train_ds, val_ds),
                "metrics": {"best_val_mse_rad2": min(h["val"]["mean"] for h in hist)}, "model_kind": self.kind}
        self._set(DeepProMP(net, norm, train_ds.joint_names, name=self.kind, metadata=meta))
        return self

    def _set(self, prim: DeepProMP):
        self.primitive = prim
        self.spec = InputSpec(self.kind, prim.joint_names, prim.phase_type, tuple(prim.cfg.context_dims),
                              prim.image_shape)

    def condition(self, via_x=None, via_y=None, contexts=None, images=None) -> LatentGaussian:
        """As the primitive server's default Condition:
        :meth:`~deepprompt_ros.primitive.deep_promp.DeepProMP.condition_planner`."""
        inp = self.check_inputs(via_x, via_y, contexts, images)
        return self.primitive.condition_planner(inp.via_x, inp.via_y, contexts=inp.contexts or None,
                                                images=inp.images).latent

    def _latent(self, cond) -> LatentGaussian:
        if not isinstance(cond, LatentGaussian) or cond.mean.shape != (self.primitive.latent_dim,):
            raise ValueError("expected the conditioned object returned by this DeepProMPModel's condition()")
        return cond

    def mean_trajectory(self, cond, x):
        return self.primitive.mean_trajectory(self._latent(cond), self.spec.check_phases(x))

    def sample(self, cond, x, n, rng=None):
        return self.primitive.sample(self._latent(cond), self.spec.check_phases(x), self._check_n(n), rng)

    def save(self, path):
        self._require_fitted()
        p = self.primitive
        return save_checkpoint(path, p.net, p.norm, p.joint_names, {**p.metadata, "model_kind": self.kind})

    @classmethod
    def load(cls, path):
        out = cls()
        ck = load_checkpoint(path)  # CheckpointError is a ValueError
        out._set(DeepProMP.from_checkpoint(ck, name=cls.kind))
        return out
