"""deepprompt_ros — Deep Probabilistic Movement Primitives served to ROS 2 controllers.

The maths lives in :mod:`deepprompt_ros.core` (no ROS needed); nodes live in
:mod:`deepprompt_ros.ros`.
"""
__version__ = "0.1.0"
