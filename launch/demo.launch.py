"""The simulated demo: sim_bridge (the simulated arm) and primitive_server with the robot's shipped
primitives, ready for service calls, and robot_state_publisher (TF for RViz); the same nodes and
parameters as `make run`.

    ros2 launch deepprompt_ros demo.launch.py [robot:=wam] [real_time_factor:=0.5] [stale_timeout:=1.0]
        [primitives_file:=/path/to/primitives.yaml] [namespace:=arm1]

The nodes, their parameter files and parameters come from deepprompt_ros.bringup (launch
'demo'); deepprompt_ros.ros.launch_description turns it into launch actions.
"""
from deepprompt_ros.ros.launch_description import launch_description


def generate_launch_description():
    return launch_description("demo")
