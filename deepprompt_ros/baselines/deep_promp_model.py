"""DeepProMP behind the common interface (:class:`deepprompt_ros.baselines.interface.MovementPrimitiveModel`):
an adapter over :func:`deepprompt_ros.training.loop.train` and
:class:`deepprompt_ros.primitive.deep_promp.DeepProMP` whose files are ordinary DeepProMP checkpoints."""
from __future__ import annotations

from typing import Callable

import numpy as np

from deepprompt_ros.baselines.interface import (InputSpec, MovementPrimitiveModel, provenance,
                                                split_for_validation)
from deepprompt_ros.model.checkpoint import load_checkpoint, save_checkpoint
from deepprompt_ros.primitive.deep_promp import DeepProMP
from deepprompt_ros.primitive.latent import PLANNER_VIA_NOISE, LatentGaussian
from deepprompt_ros.training.loop import train

__all__ = ["DeepProMPModel", "planner_condition", "PLANNER_TOLERANCE"]

#: The via-point tolerance (rad) of :func:`planner_condition`, the primitive server's default
#: (``refine_tolerance``).
PLANNER_TOLERANCE = 1e-6


def planner_condition(prim: DeepProMP, via_x, via_y, contexts=None, images=None) -> LatentGaussian:
    """``prim`` conditioned as the primitive server's default Condition request does it (no
    refinement asked for): the aggregation of every input (paper Eq. 1 / 3) and, for a split latent,
    the exact conditioning of its linear block with the planner's via-point noise
    (:data:`deepprompt_ros.primitive.latent.PLANNER_VIA_NOISE`), conditioned again with a smaller one
    while a via-point is missed by more than :data:`PLANNER_TOLERANCE`
    (:meth:`DeepProMP.refine_linear`). via_x (n,), via_y (n, d), n may be 0."""
    has_via = np.asarray(via_x).size > 0
    vx, vy = (via_x, via_y) if has_via else (None, None)
    if not (has_via and prim.exact_conditioning):
        return prim.condition(vx, vy, contexts=contexts, images=images)
    lat = prim.condition(vx, vy, contexts=contexts, images=images, via_noise=PLANNER_VIA_NOISE)
    if lat.linear.via_error <= PLANNER_TOLERANCE:
        return lat
    return prim.refine_linear(lat, vx, vy, tol=PLANNER_TOLERANCE).latent


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
        """As the primitive server's default Condition: :meth:`planner_condition`."""
        inp = self.check_inputs(via_x, via_y, contexts, images)
        return planner_condition(self.primitive, inp.via_x, inp.via_y, inp.contexts or None, inp.images)

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
