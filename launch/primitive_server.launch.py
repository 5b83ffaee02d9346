"""primitive_server alone, for a real arm: the arm's driver publishes joint_states and runs the
JointTrajectory controller the server streams to.

    ros2 launch deepprompt_ros primitive_server.launch.py [params_file:=/path/to/server.yaml]
        [robot:=gen3_lite] [controller:=joint_trajectory_controller] [primitives_file:=/path/to/primitives.yaml]
        [namespace:=arm1]

The nodes, their parameter files and parameters come from deepprompt_ros.bringup (launch
'primitive_server'); deepprompt_ros.ros.launch_description turns it into launch actions.
"""
from deepprompt_ros.ros.launch_description import launch_description


def generate_launch_description():
    return launch_description("primitive_server")
