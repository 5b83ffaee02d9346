"""ROS-free core of deepprompt_ros.

Glossary (paper notation):
  x  phase, normalized time in [0, 1] (rhythmic: fed to the network as [sin 2πx, cos 2πx])
  y  joint positions, shape (d,)
  a  via-point (x, y);  c  context (low-dimensional vector or camera images)
  z  latent variable, shape (k,), q(z | A, C) built by Bayesian aggregation
  ω  importance weight of a via-point / context (0 removes it)
  τ  time map t -> x (temporal modulation)
"""
__version__ = "0.1.0"
