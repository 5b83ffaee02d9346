"""The training configuration of a DeepProMP (:class:`TrainConfig`), one parameter per YAML key.

Every field is declared once with :func:`deepprompt_ros.common.params.param` (type, default,
description, range or choices, unit): the same scheme as the nodes' ROS parameters, so
``docs/parameters.md`` documents it from the same declaration. Files: ``config/train_*.yaml``.
"""
from __future__ import annotations

import dataclasses
import pathlib
from typing import Mapping

from deepprompt_ros.common.params import param, validate
from deepprompt_ros.model.network import VARIANCE_HEADS

__all__ = ["TrainConfig", "OBJECTIVES", "CONSISTENCY_ENCODER", "BASIS_INITS", "BASIS_COV_REG_UNITS"]

OBJECTIVES = ("paper", "np")
CONSISTENCY_ENCODER = ("none", "coverage", "all")
BASIS_INITS = ("random", "pca")
BASIS_COV_REG_UNITS = ("normalized", "raw")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Training hyper-parameters (YAML keys of the same names; unknown keys are refused).

    The objectives (``objective``) and the sub-sampling of inputs are described in
    :mod:`deepprompt_ros.training.objectives`; the linear-basis initialization in
    :mod:`deepprompt_ros.training.basis`. "normalized" units are joint positions and contexts
    standardized with the training set's statistics.
    """

    # -- architecture (stored in the checkpoint's ModelConfig)
    latent_dim: int = param(16, "k, the dimension of the latent z (16 or 32 in the paper)", min=1)
    hidden: int = param(128, "width of the 2 hidden ReLU layers of every encoder and of the decoder (128 in the "
                             "paper)", min=1)
    sigma_y: float = param(0.05, "fixed decoder standard deviation σ_y of the reconstruction likelihood (> 0)",
                           min=0.0, unit="normalized")
    var_floor: float = param(1e-4, "lower bound added to every encoder variance σ²_i of the latent (the prior's "
                                   "variance is 1); keeps the aggregation finite (> 0)", min=0.0)
    variance_head: str = param("softplus", "how the shared head's output r becomes σ²_i: softplus(r) + var_floor, "
                                           "or exp(min(r, 12)) + var_floor (a large σ²_i, an element that says "
                                           "almost nothing, is then a moderate r)", choices=VARIANCE_HEADS)
    phase_harmonics: int = param(0, "extra Fourier features of the phase fed to encoders and decoder: linear "
                                    "adds [sin πhx, cos πhx] for h = 1..H, rhythmic uses h = 1..max(1, H)", min=0)
    decoder_basis: int = param(0, "n_b: 0 = the paper's MLP decoder; >= 2 adds a linear part Φ(x)(b + A z) of n_b "
                                  "basis functions per joint under the MLP (residual decoder)", min=0)
    basis_width: float = param(1.0, "basis function width of the linear part relative to the centre spacing "
                                    "(ProMP's width, > 0)", min=0.0)
    residual_scale: float = param(1.0, "s, the factor on the MLP part of a residual decoder (0 = the linear part "
                                       "only)", min=0.0)
    # -- linear part of a residual decoder
    basis_init: str = param("random", "initial linear part: 'random' (small Gaussian weights) or 'pca' (the PPCA "
                                      "of the training demonstrations)", choices=BASIS_INITS)
    basis_lr_scale: float = param(1.0, "learning rate of the linear part relative to lr (0 keeps it as "
                                       "initialized)", min=0.0)
    basis_cov_reg: float = param(0.0, "λ of the PCA initialization relative to the mean weight variance: λI added "
                                      "to the weights' covariance gives the latent directions beyond the demos' "
                                      "span a small variance (0 = none)", min=0.0)
    basis_cov_reg_units: str = param("normalized", "units of basis_cov_reg's λI: 'normalized' joint units, or "
                                                   "'raw' (rad, ProMP's regularizer)", choices=BASIS_COV_REG_UNITS)
    # -- objective
    objective: str = param("np", "'np': Neural-Process form, z from all inputs and β KL(q(z | all) ‖ q(z | "
                                 "subset)); 'paper': the paper's rewritten ELBO, z from the subset and β Σ_i "
                                 "KL(q(z | a_i) ‖ p0)", choices=OBJECTIVES)
    beta: float = param(1.0, "β, the weight of the KL term once annealed", min=0.0)
    kl_anneal_steps: int = param(1000, "updates over which β rises linearly from 0 to beta", min=0, unit="updates")
    # -- optimization
    lr: float = param(1e-3, "Adam learning rate (> 0)", min=0.0)
    batch_size: int = param(16, "demonstrations per update", min=1)
    steps: int = param(4000, "number of updates", min=1, unit="updates")
    n_points: int = param(100, "phases at which every demonstration is resampled for training", min=2)
    # -- which inputs each update gives (sub-sampling)
    max_via_points: int = param(10, "most via-points in a training subset (<= n_points)", min=0)
    p_via_points: float = param(0.7, "probability that a trajectory's subset has via-points", min=0.0, max=1.0)
    p_context: float = param(0.5, "probability that each context modality (and the images) is given", min=0.0,
                             max=1.0)
    p_empty: float = param(0.1, "probability that a trajectory is given nothing (the prior)", min=0.0, max=1.0)
    p_low_info: float = param(0.0, "fraction of the via-point subsets drawn only from the phases where the "
                                   "batch's demonstrations agree most (points that cannot tell them apart)",
                              min=0.0, max=1.0)
    low_info_fraction: float = param(0.2, "fraction of the phases (smallest across-demo spread) that p_low_info "
                                          "draws from (> 0)", min=0.0, max=1.0)
    # -- sample consistency and the prior
    consistency_weight: float = param(0.0, "weight of the sample-consistency (Chamfer) term between samples of "
                                           "q(z | subset) and the batch's demonstrations consistent with the "
                                           "subset (0 = off)", min=0.0)
    prior_kl_weight: float = param(0.0, "weight of KL(q(z | all) ‖ N(0, I)) added to the 'np' objective (0 = off)",
                                   min=0.0)
    consistency_tol: float = param(0.15, "a demonstration is consistent with a subset when it is within this of "
                                         "every given value (> 0)", min=0.0, unit="normalized")
    consistency_samples: int = param(8, "M, samples of q(z | subset) per trajectory in the consistency term", min=1)
    consistency_encoder: str = param("none", "which part of the consistency term reaches the encoder through z: "
                                             "'none' (a decoder term), 'coverage', 'all'",
                                     choices=CONSISTENCY_ENCODER)
    # -- validation and run
    n_val: int = param(0, "demonstrations held out for validation; 0 = 10 % of them (at least 1)", min=0)
    val_every: int = param(250, "updates between validations; the weights of the best one are kept", min=1,
                           unit="updates")
    val_via_points: int = param(5, "via-points per held-out demonstration in the validation's via-point "
                                   "conditioning", min=0)
    seed: int = param(0, "seed of the validation split, the initialization and every random draw", min=0)
    threads: int = param(2, "torch CPU threads", min=1)

    def __post_init__(self):
        # exclusive bounds and rules between fields, which a parameter's range cannot state (and the
        # messages users know for steps and objective); then the declared type and range of every field
        checks = [
            (self.objective in OBJECTIVES, f"objective must be one of {OBJECTIVES}, got '{self.objective}'"),
            (self.batch_size >= 1 and self.steps >= 1, "batch_size and steps must be >= 1"),
            (self.sigma_y > 0 and self.var_floor > 0, "sigma_y and var_floor must be > 0"),
            (self.consistency_weight >= 0 and self.consistency_tol > 0,
             "consistency_weight must be >= 0 and consistency_tol > 0"),
            (self.lr > 0, f"lr must be > 0, got {self.lr}"),
            (0 <= self.max_via_points <= self.n_points, f"max_via_points must be in [0, n_points={self.n_points}]"),
            (0 < self.low_info_fraction <= 1, f"low_info_fraction must be in (0, 1], got {self.low_info_fraction}"),
            (self.decoder_basis == 0 or self.decoder_basis >= 2, "decoder_basis must be 0 or >= 2"),
            (self.basis_width > 0 and self.residual_scale >= 0, "basis_width must be > 0 and residual_scale >= 0"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ValueError(f"invalid training config: {msg}")
        validate(self)

    @classmethod
    def from_yaml(cls, path) -> "TrainConfig":
        import yaml

        path = pathlib.Path(path)
        if not path.is_file():
            raise ValueError(f"training config '{path}' does not exist; expected a YAML file")
        try:
            raw = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise ValueError(f"training config '{path}' is not valid YAML: {exc}") from exc
        if not isinstance(raw, dict):
            raise ValueError(f"training config '{path}' must be a mapping of keys to values")
        return cls.from_dict(raw, str(path))

    @classmethod
    def from_dict(cls, raw: Mapping, where: str = "config") -> "TrainConfig":
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(raw) - set(fields))
        if unknown:
            raise ValueError(f"{where}: unknown keys {unknown}; valid keys: {sorted(fields)}")
        kw = {}
        for k, v in raw.items():
            typ = type(getattr(cls(), k))
            if typ is float and isinstance(v, int) and not isinstance(v, bool):
                v = float(v)
            if not isinstance(v, typ) or (typ is int and isinstance(v, bool)):
                raise ValueError(f"{where}: '{k}' must be {typ.__name__}, got {v!r}")
            kw[k] = v
        return cls(**kw)
