"""The simulated demo: sim_bridge (the simulated arm) and primitive_server with the shipped
primitives, ready for service calls; the same nodes and parameters as `make run`.

    ros2 launch deepprompt_ros demo.launch.py [robot:=wam] [real_time_factor:=0.5] [stale_timeout:=1.0]

The nodes, their parameter files and parameters come from deepprompt_ros.bringup (launch
'demo'); this file only declares the arguments and turns the description into Node actions.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from deepprompt_ros import bringup

LAUNCH = "demo"


def _nodes(context, *args, **kwargs):
    values = {a.name: LaunchConfiguration(a.name).perform(context) for a in bringup.arguments(LAUNCH)}
    return [Node(**node.launch_kwargs()) for node in bringup.nodes(LAUNCH, values)]


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([DeclareLaunchArgument(**kw) for kw in bringup.launch_argument_kwargs(LAUNCH)]
                             + [OpaqueFunction(function=_nodes)])
