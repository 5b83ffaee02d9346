"""primitive_server alone, for a real arm: the arm's driver publishes joint_states and runs the
JointTrajectory controller the server streams to.

    ros2 launch deepprompt_ros primitive_server.launch.py [params_file:=/path/to/server.yaml]
        [robot:=gen3_lite] [controller:=joint_trajectory_controller] [primitives_file:=/path/to/primitives.yaml]

The nodes, their parameter files and parameters come from deepprompt_ros.bringup (launch
'primitive_server'); this file only declares the arguments and turns the description into Node actions.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from deepprompt_ros import bringup

LAUNCH = "primitive_server"


def _nodes(context, *args, **kwargs):
    values = {a.name: LaunchConfiguration(a.name).perform(context) for a in bringup.arguments(LAUNCH)}
    return [Node(**node.launch_kwargs()) for node in bringup.nodes(LAUNCH, values)]


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([DeclareLaunchArgument(**kw) for kw in bringup.launch_argument_kwargs(LAUNCH)]
                             + [OpaqueFunction(function=_nodes)])
