"""deepprompt_ros — Deep Probabilistic Movement Primitives served to ROS 2 controllers.

Glossary (paper notation):
  x  phase, normalized time in [0, 1] (rhythmic: fed to the network as [sin 2πx, cos 2πx])
  y  joint positions, shape (d,)
  a  via-point (x, y);  c  context (low-dimensional vector or camera images)
  z  latent variable, shape (k,); q(z | A, C) is built by Bayesian aggregation
  ω  importance weight of a via-point / context (0 removes it)
  τ  time map t -> x (temporal modulation)

Subpackages, by concept, from the bottom layer up: each imports only subpackages listed before it
(one exception: ``data.builtin``, the registry of the built-in data sets, sits above ``sim.tasks``,
whose generators it lists; test/test_package_structure.py keeps the order):
  common      the one parameter scheme, the joint-list formatter, result codes
  data        demonstration format, I/O, synthetic families, built-in datasets (data.builtin)
  robots      robot specs from URDF, kinematics, inverse kinematics, geometry
  sim         the PyBullet simulation and the task-data generators (sim.tasks)
  model       the network, Bayesian aggregation, phase features, checkpoints
  primitive   DeepProMP operations: condition, decode, sample, blend, refine, time maps
  evaluation  reconstruction metrics used by the experiments (and ProMP's validation)
  training    training configuration, objectives, the loop, basis initialization
  baselines   ProMP, CNMP, VAE-CNMP and their Indep variants behind one interface
  execution   joint limits, phase clock, reference, Ruckig streamer, the ROS-free stream loop
  server      server configuration, primitives file, handles, request types, service logic
  recording   kinesthetic recording: demo buffer, images, MCAP bag writer
  bringup     the one description of the nodes the launch files and `make run` start
  ros         the only modules that import rclpy: the nodes, message conversions, ros.fastpath

Names below are imported lazily (torch, pinocchio and pybullet load only when used).
"""
from importlib import import_module

__version__ = "0.1.0"

_EXPORTS = {
    # model, training and operations
    "ModelConfig": "model.network", "DeepProMPNet": "model.network", "bayesian_aggregate": "model.aggregation",
    "TrainConfig": "training.config",
    "DeepProMP": "primitive.deep_promp", "LatentGaussian": "primitive.latent",
    "RefinementResult": "primitive.refinement",
    "load_checkpoint": "model.checkpoint", "save_checkpoint": "model.checkpoint",
    "CheckpointError": "model.checkpoint",
    "LinearTimeMap": "primitive.time_maps", "MonotoneTimeMap": "primitive.time_maps",
    "RhythmicTimeMap": "primitive.time_maps",
    # data
    "Demonstration": "data.demonstration", "DatasetError": "data.demonstration",
    "demo_from_arrays": "data.demonstration", "DemoDataset": "data.demo_dataset",
    "load_dataset": "data.demo_dataset", "load_demo": "data.io", "save_demo": "data.io", "load_csv": "data.io",
    "bimodal_sine": "data.synthetic", "builtin_dataset": "data.builtin",
    "ShardedDataset": "data.sharded", "write_shards": "data.sharded", "convert_folder": "data.sharded",
    # baseline
    "ProMP": "baselines.promp",
    # robots, simulation and streaming
    "RobotSpec": "robots.spec", "load_robot": "robots.spec", "RobotKinematics": "robots.kinematics",
    "Simulation": "sim.simulation",
    "PhaseClock": "execution.phase_clock", "RuckigStreamer": "execution.ruckig_streamer",
    "JointLimits": "execution.limits", "check_limits": "execution.limits",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        return getattr(import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
