"""Two simulated arms side by side, each with the demo's nodes (sim_bridge, primitive_server with the
robot's shipped primitives, robot_state_publisher) under its own namespace: one planner conditions and
executes on both (/left_arm/primitive_server/..., /right_arm/primitive_server/...). Only the first
arm's sim_bridge publishes /clock.

    ros2 launch deepprompt_ros dual_arm.launch.py [left_robot:=gen3_lite] [right_robot:=wam]
        [left_namespace:=left_arm] [right_namespace:=right_arm] [real_time_factor:=1.0] [stale_timeout:=1.0]

The nodes, their parameter files and parameters come from deepprompt_ros.bringup (launch
'dual_arm'); deepprompt_ros.ros.launch_description turns it into launch actions.
"""
from deepprompt_ros.ros.launch_description import launch_description


def generate_launch_description():
    return launch_description("dual_arm")
