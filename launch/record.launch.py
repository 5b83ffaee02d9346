"""Kinesthetic recording in simulation: sim_bridge in kinesthetic mode (guide the arm with
guide_target) and demo_recorder (start_recording / stop_recording services).

    ros2 launch deepprompt_ros record.launch.py [robot:=gen3_lite] [output_directory:=~/demos]

The nodes, their parameter files and parameters come from deepprompt_ros.bringup (launch
'record'); this file only declares the arguments and turns the description into Node actions.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from deepprompt_ros import bringup

LAUNCH = "record"


def _nodes(context, *args, **kwargs):
    values = {a.name: LaunchConfiguration(a.name).perform(context) for a in bringup.arguments(LAUNCH)}
    return [Node(**node.launch_kwargs()) for node in bringup.nodes(LAUNCH, values)]


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([DeclareLaunchArgument(**kw) for kw in bringup.launch_argument_kwargs(LAUNCH)]
                             + [OpaqueFunction(function=_nodes)])
