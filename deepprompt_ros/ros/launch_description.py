"""A launch of :mod:`deepprompt_ros.bringup` as a ROS 2 launch description (the Jazzy launch API).

Each file in ``launch/`` is three lines over :func:`launch_description`: the launch's arguments become
``DeclareLaunchArgument`` actions, and an ``OpaqueFunction`` turns the argument values into the
described ``launch_ros.actions.Node`` actions when the launch runs. String parameter values go to
``launch_ros`` as ``ParameterValue(value, value_type=str)``: it reads a plain string as YAML, which
would turn ``'1'`` into a number and fail on a URDF (robot_state_publisher's robot_description).
"""
from __future__ import annotations

from deepprompt_ros import bringup

__all__ = ["launch_description"]


def launch_description(launch: str):
    """The ``LaunchDescription`` of the launch named ``launch`` (one of ``bringup.LAUNCHES``)."""
    # imported here, not at module level: the module stays importable where launch is not installed
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument, OpaqueFunction
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node
    from launch_ros.parameter_descriptions import ParameterValue

    def node_action(node: bringup.NodeDescription):
        kw = node.launch_kwargs()
        kw["parameters"] = [p if isinstance(p, str) else
                            {k: ParameterValue(v, value_type=str) if isinstance(v, str) else v for k, v in p.items()}
                            for p in kw["parameters"]]
        return Node(**kw)

    def nodes(context, *args, **kwargs):
        values = {a.name: LaunchConfiguration(a.name).perform(context) for a in bringup.arguments(launch)}
        return [node_action(node) for node in bringup.nodes(launch, values)]

    return LaunchDescription([DeclareLaunchArgument(**kw) for kw in bringup.launch_argument_kwargs(launch)]
                             + [OpaqueFunction(function=nodes)])
