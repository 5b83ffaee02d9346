"""The training configuration of a DeepProMP (:class:`TrainConfig`), one parameter per YAML key.

Every field is declared once with :func:`deepprompt_ros.common.params.param` (type, default,
description, range or choices, unit): the same scheme as the nodes' ROS parameters, so
``docs/parameters.md`` documents it from the same declaration. The architecture fields are
declared in :class:`deepprompt_ros.model.network.ModelConfig` and taken over with
:func:`~deepprompt_ros.common.params.param_from`. Files: ``config/train_*.yaml``.
"""
from __future__ import annotations

import dataclasses
import pathlib
from typing import Mapping

from deepprompt_ros.common.params import ConfigError, from_mapping, param, param_from, validate
from deepprompt_ros.model.network import ModelConfig, decoder_basis_error, decoder_modes_error, latent_linear_errors
from deepprompt_ros.training.distributed import DEVICES

__all__ = ["TrainConfig", "OBJECTIVES", "CONSISTENCY_ENCODER", "BASIS_INITS", "BASIS_COV_REG_UNITS"]

OBJECTIVES = ("paper", "np")
CONSISTENCY_ENCODER = ("none", "coverage", "all")
BASIS_INITS = ("random", "pca")
BASIS_COV_REG_UNITS = ("normalized", "raw")
#: basis functions per joint the automatic selection tries (training/basis.cv_basis_hyperparameters)
AUTO_DECODER_BASIS = (10, 15, 20, 30)


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Training hyper-parameters (YAML keys of the same names; unknown keys are refused).

    The objectives (``objective``) and the sub-sampling of inputs are described in
    :mod:`deepprompt_ros.training.objectives`; the linear-basis initialization and its
    cross-validation in :mod:`deepprompt_ros.training.basis`, the model selection of ``auto_select``
    in :mod:`deepprompt_ros.training.selection`. "normalized" units are joint positions and contexts
    standardized with the training set's statistics.
    """

    # -- architecture (stored in the checkpoint's ModelConfig, declared there)
    latent_dim: int = param_from(ModelConfig, "latent_dim")
    hidden: int = param_from(ModelConfig, "hidden")
    sigma_y: float = param_from(ModelConfig, "sigma_y")
    var_floor: float = param_from(ModelConfig, "var_floor")
    variance_head: str = param_from(ModelConfig, "variance_head")
    phase_harmonics: int = param_from(ModelConfig, "phase_harmonics")
    decoder_basis: int = param_from(ModelConfig, "decoder_basis")
    basis_width: float = param_from(ModelConfig, "basis_width")
    residual_scale: float = param_from(ModelConfig, "residual_scale")
    latent_linear: int = param_from(ModelConfig, "latent_linear")
    via_noise: float = param_from(ModelConfig, "via_noise")
    mode_noise: float = param_from(ModelConfig, "mode_noise")
    # -- model selection on the training demonstrations
    auto_select: bool = param(True, "choose the decoder from the training demos (never held-out ones): "
                                    "decoder_basis, latent_linear, basis_cov_reg, basis_cov_reg_units and "
                                    "via_noise by cross-validation of the linear part, linear_modes by the modes "
                                    "of the demos' basis weights unless the same cross-validation finds their "
                                    "executed means worse than one Gaussian's (by more than two standard errors "
                                    "and 2 %), latent_dim = latent_linear + latent_nonlinear "
                                    "(with several modes the first z_nl dimension chooses the mode), the linear part "
                                    "initialized as their PPCA and kept fixed (basis_init pca, "
                                    "basis_lr_scale 0), then the MLP residual kept (residual_scale) or dropped (0) "
                                    "on the validation demos (with linear_modes > 1 the modes' via-point noise and mode_noise are "
                                    "chosen on the validation demos; unless the cross-validation found their "
                                    "executed means better by more than two standard errors and 2 %, the training with linear_modes 1 runs too "
                                    "and the modes are kept only if better there), and "
                                    "the low-dim contexts conditioned through their joint linear Gaussian model "
                                    "of z_lin, or through the encoders alone where they reconstruct the "
                                    "validation demos better by more than one standard error (in-memory "
                                    "training; a sharded dataset keeps the encoders); the file's values of "
                                    "those keys are not used. "
                                    "false: every key as given")
    latent_nonlinear: int = param(8, "with auto_select: k_n, the latent dimensions z_nl that only the MLP "
                                     "reads; with linear_modes K > 1 the first of them also chooses the mode",
                                  min=1)
    judge_modes: bool = param(True, "with auto_select and K > 1 modes admitted: true = unless the "
                                    "cross-validation found their executed means better, the training with "
                                    "linear_modes 1 runs too and the modes are kept only if better there; false = "
                                    "the modes the cross-validation admits are kept (no training with one mode)")
    cv_folds: int = param(5, "with auto_select: folds of the cross-validation (at most one per training "
                             "demonstration)", min=2)
    residual_folds: int = param(0, "with auto_select: 0 = judge the MLP residual on the validation demos; K >= 2 "
                                   "= on the held-out demos of a K-fold cross-validation of the whole training on "
                                   "the training demos (K more trainings; in one process: refused under torchrun)",
                          min=0)
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
    linear_modes: int = param(1, "K, the modes of the training demos' basis weights (training/basis.weight_modes) "
                                 "the decoder treats apart: 1 = the linear part is the PPCA of all demos; K > 1 = "
                                 "the PPCA of each demo's weights minus its mode's mean (A spans the variation "
                                 "inside a mode) and the modes' offsets and shares in the decoder (ModelConfig."
                                 "decoder_modes: the first z_nl dimension chooses the mode); needs basis_init pca "
                                 "and 1 <= latent_linear < latent_dim", min=1)
    # -- objective
    objective: str = param("paper", "'np': Neural-Process form, z from all inputs and β KL(q(z | all) ‖ q(z | "
                                 "subset)); 'paper': the paper's rewritten ELBO, z from the subset and β Σ_i "
                                 "KL(q(z | a_i) ‖ p0)", choices=OBJECTIVES)
    beta: float = param(1.0, "β, the weight of the KL term once annealed", min=0.0)
    kl_anneal_steps: int = param(1000, "updates over which β rises linearly from 0 to beta", min=0, unit="updates")
    # -- optimization
    lr: float = param(1e-3, "Adam learning rate", gt=0.0)
    batch_size: int = param(16, "demonstrations per update", min=1)
    steps: int = param(4000, "number of updates", min=1, unit="updates")
    n_points: int = param(100, "phases at which every demonstration is resampled for training", min=2)
    # -- which inputs each update gives (sub-sampling)
    max_via_points: int = param(10, "most via-points in a training subset (<= n_points)", min=0)
    p_via_points: float = param(0.7, "probability of drawing via-points for a trajectory not given nothing "
                                     "(draws that give nothing are repeated, so the share with via-points is "
                                     "higher)", min=0.0, max=1.0)
    p_context: float = param(0.5, "probability of drawing each context modality (and the images) for a "
                                  "trajectory not given nothing (repeated like p_via_points)", min=0.0, max=1.0)
    p_empty: float = param(0.1, "share of the trajectories given nothing (the prior); every other one is given "
                                "at least one input", min=0.0, max=1.0)
    p_low_info: float = param(0.0, "fraction of the via-point subsets drawn only from the phases where the "
                                   "batch's demonstrations agree most (points that cannot tell them apart)",
                              min=0.0, max=1.0)
    low_info_fraction: float = param(0.2, "fraction of the phases (smallest across-demo spread) that p_low_info "
                                          "draws from", gt=0.0, max=1.0)
    # -- sample consistency and the prior
    consistency_weight: float = param(0.0, "weight of the sample-consistency (Chamfer) term between samples of "
                                           "q(z | subset) and the batch's demonstrations consistent with the "
                                           "subset (0 = off)", min=0.0)
    prior_kl_weight: float = param(0.0, "weight of KL(q(z | all) ‖ N(0, I)) added to the 'np' objective (0 = off)",
                                   min=0.0)
    consistency_tol: float = param(0.15, "a demonstration is consistent with a subset when it is within this of "
                                         "every given value", gt=0.0, unit="normalized")
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
    threads: int = param(2, "torch CPU threads (per process)", min=1)
    device: str = param("auto", "where the training runs: 'auto' (a GPU when CUDA is available, the CPU "
                                "otherwise), 'cpu' or 'cuda'; under torchrun process LOCAL_RANK takes GPU "
                                "LOCAL_RANK, and the process group is NCCL on GPUs, gloo on the CPU",
                        choices=DEVICES)
    checkpoint_every: int = param(0, "updates between writes of the resume file OUT.resume.pt beside the "
                                     "checkpoint (train --resume continues from it); 0 = val_every", min=0,
                                  unit="updates")
    # -- sharded datasets on disk (deepprompt_ros.data.sharded; training/streaming.py)
    data_workers: int = param(0, "sharded dataset: worker processes that read and assemble the batches "
                                 "(torch DataLoader); 0 = read in the training process, the batches drawn as in "
                                 "memory (the same model as the folder format); > 0: the batches' demos drawn "
                                 "from their own generator (seed), the same model for any count of workers", min=0)
    select_max_demos: int = param(1000, "sharded dataset: most training demos (a seeded subset) that auto_select's "
                                        "cross-validation and the PCA initialization of the linear part read",
                                  min=3)
    val_max_demos: int = param(1000, "sharded dataset: most validation demos (a seeded subset of the held-out "
                                     "ones) the validation and the residual's judgement read", min=1)

    def __post_init__(self):
        # the type and range or choices of every field, then the rules a field's range cannot state
        # latent_linear's rule on decoder_basis × n_joints waits for the data (the model's config checks it)
        validate(self, rules=lambda c: [
            decoder_basis_error(c.decoder_basis),
            *latent_linear_errors(c.latent_linear, c.latent_dim, c.decoder_basis, n_joints=c.latent_linear),
            "" if c.linear_modes == 1 or c.auto_select or (c.decoder_basis and c.basis_init == "pca") else
            f"linear_modes = {c.linear_modes!r} needs the PCA initialization of a linear part: expected "
            "decoder_basis >= 2 and basis_init pca (or linear_modes 1)",
            "" if c.linear_modes == 1 or c.auto_select else decoder_modes_error(c.linear_modes, c.latent_linear,
                                                                                c.latent_dim).replace(
                "(or decoder_modes 0)", "(or linear_modes 1)").replace("decoder_modes", "linear_modes"),
            "" if c.residual_folds != 1 else
            "residual_folds = 1: expected 0 (the validation demos) or >= 2 folds",
            "" if not c.auto_select or c.n_points >= 2 * min(AUTO_DECODER_BASIS) else
            f"n_points = {c.n_points!r} with auto_select: the selection's smallest basis ({min(AUTO_DECODER_BASIS)} "
            f"functions per joint) needs n_points >= {2 * min(AUTO_DECODER_BASIS)}; expected a larger n_points, or "
            "auto_select: false with decoder_basis set by hand",
            "" if c.max_via_points <= c.n_points else
            f"max_via_points = {c.max_via_points!r}: expected at most n_points = {c.n_points}",
            "" if c.p_empty == 1.0 or c.p_via_points > 0 or c.p_context > 0 else
            f"p_via_points = 0 and p_context = 0 give every trajectory nothing: expected p_empty = 1 "
            f"(got {c.p_empty!r}) or a positive p_via_points or p_context"])

    @classmethod
    def from_yaml(cls, path) -> "TrainConfig":
        import yaml

        path = pathlib.Path(path)
        if not path.is_file():
            raise ConfigError(f"training config '{path}' does not exist; expected a YAML file")
        try:
            raw = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise ConfigError(f"training config '{path}' is not valid YAML: {exc}") from exc
        if not isinstance(raw, dict):
            raise ConfigError(f"training config '{path}' must be a mapping of keys to values")
        return cls.from_dict(raw, str(path))

    @classmethod
    def from_dict(cls, raw: Mapping, where: str = "config") -> "TrainConfig":
        """The configuration of the keys in ``raw`` (the others at their defaults); unknown keys and
        invalid values are all reported in one :class:`~deepprompt_ros.common.params.ConfigError`
        that starts with ``where``."""
        try:
            return from_mapping(cls, raw)
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}") from None
