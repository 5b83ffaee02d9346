"""Kinesthetic recording in simulation: sim_bridge in kinesthetic mode (guide the arm with
guide_target), demo_recorder (start_recording / stop_recording services) and robot_state_publisher
(TF for RViz).

    ros2 launch deepprompt_ros record.launch.py [robot:=gen3_lite] [output_directory:=~/demos] [namespace:=arm1]

The nodes, their parameter files and parameters come from deepprompt_ros.bringup (launch
'record'); deepprompt_ros.ros.launch_description turns it into launch actions.
"""
from deepprompt_ros.ros.launch_description import launch_description


def generate_launch_description():
    return launch_description("record")
