"""ROS-free core of deepprompt_ros.

Glossary (paper notation):
  x  phase, normalized time in [0, 1] (rhythmic: fed to the network as [sin 2πx, cos 2πx])
  y  joint positions, shape (d,)
  a  via-point (x, y);  c  context (low-dimensional vector or camera images)
  z  latent variable, shape (k,); q(z | A, C) is built by Bayesian aggregation
  ω  importance weight of a via-point / context (0 removes it)
  τ  time map t -> x (temporal modulation)

Names below are imported lazily (torch, pinocchio and pybullet load only when used).
"""
from importlib import import_module

__version__ = "0.1.0"

_EXPORTS = {
    # model, training and operations
    "ModelConfig": "model", "DeepProMPNet": "model", "bayesian_aggregate": "model",
    "TrainConfig": "train",
    "DeepProMP": "primitive", "LatentGaussian": "primitive", "RefinementResult": "primitive",
    "load_checkpoint": "checkpoint", "save_checkpoint": "checkpoint", "CheckpointError": "checkpoint",
    "LinearTimeMap": "temporal", "MonotoneTimeMap": "temporal", "RhythmicTimeMap": "temporal",
    # data
    "Demonstration": "dataset", "DemoDataset": "dataset", "DatasetError": "dataset",
    "demo_from_arrays": "dataset", "load_dataset": "dataset", "load_demo": "dataset", "save_demo": "dataset",
    "load_csv": "dataset", "bimodal_sine": "dataset", "builtin_dataset": "dataset",
    # baseline
    "ProMP": "promp",
    # robots, simulation and streaming
    "RobotSpec": "robots", "load_robot": "robots", "RobotKinematics": "robots", "Simulation": "sim",
    "PhaseClock": "streaming", "RuckigStreamer": "streaming", "JointLimits": "streaming",
    "check_limits": "streaming",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        return getattr(import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
