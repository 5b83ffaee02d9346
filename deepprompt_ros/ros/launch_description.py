"""A launch of :mod:`deepprompt_ros.bringup` as a ROS 2 launch description (the Jazzy launch API).

Each file in ``launch/`` is three lines over :func:`launch_description`: the launch's arguments become
``DeclareLaunchArgument`` actions, and an ``OpaqueFunction`` turns the argument values into the
described ``launch_ros.actions.Node`` actions when the launch runs.
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

    def nodes(context, *args, **kwargs):
        values = {a.name: LaunchConfiguration(a.name).perform(context) for a in bringup.arguments(launch)}
        return [Node(**node.launch_kwargs()) for node in bringup.nodes(launch, values)]

    return LaunchDescription([DeclareLaunchArgument(**kw) for kw in bringup.launch_argument_kwargs(launch)]
                             + [OpaqueFunction(function=nodes)])
