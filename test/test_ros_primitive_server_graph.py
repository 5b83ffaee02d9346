"""The ROS graph of primitive_server as a user sees it (``ros2 node list`` / ``ros2 node info``), in
both modes (fast path, plain rclpy), started with a node-name and namespace remap (what a launch
file's ``name=`` / ``namespace=`` does): no two nodes share a name, the server node itself lists
its five services and the Execute action, and its control process is one node ``<name>_control``
holding the command stream and the joint_states subscription. Read from another process's node.
Real processes, real DDS (LOCALHOST discovery, random domain)."""

import numpy as np
import pytest
import torch
import yaml

from deepprompt_ros.model.checkpoint import Normalization, save_checkpoint
from deepprompt_ros.model.network import DeepProMPNet, ModelConfig
from deepprompt_ros.robots.spec import load_robot
from deepprompt_ros.ros.testing import NodeProcess, RosTestClient, isolated_ros_env

SPEC = load_robot("gen3_lite")
NAME, NS = "left_server", "/left"
SERVICES = {"condition": "deepprompt_msgs/srv/Condition", "blend": "deepprompt_msgs/srv/Blend",
            "sample": "deepprompt_msgs/srv/Sample", "list_primitives": "deepprompt_msgs/srv/ListPrimitives",
            "set_phase_rate": "deepprompt_msgs/srv/SetPhaseRate"}


@pytest.fixture(scope="module")
def primitives(tmp_path_factory):
    """A servable (untrained) 6-joint Gen3 lite primitive: the graph does not depend on what it learned."""
    tmp = tmp_path_factory.mktemp("graph")
    torch.manual_seed(0)
    net = DeepProMPNet(ModelConfig(n_joints=6, latent_dim=4, hidden=8))
    model = save_checkpoint(tmp / "reach.safetensors", net, Normalization(np.zeros(6), np.ones(6)),
                            list(SPEC.joint_names))
    prims = tmp / "primitives.yaml"
    prims.write_text(yaml.safe_dump({"primitives": [{"name": "reach", "model": str(model)}]}))
    return prims


def _graph(client):
    node = client.node
    names = node.get_node_names_and_namespaces()
    services = dict(node.get_service_names_and_types_by_node(NAME, NS)) if (NAME, NS) in names else {}
    return names, services


@pytest.mark.parametrize("fast_path,loop_process", [(True, True), (False, True), (True, False), (False, False)],
                         ids=["fast_path", "plain_rclpy", "fast_path_in_process", "plain_rclpy_in_process"])
def test_remapped_server_has_unique_node_names_and_lists_its_own_services(tmp_path, primitives, fast_path,
                                                                          loop_process):
    env = isolated_ros_env(tmp_path / "log")
    with NodeProcess.start_module("deepprompt_ros.ros.primitive_server", env, ros_args=[
            "-p", f"primitives_file:={primitives}", "-p", f"fast_path:={str(fast_path).lower()}",
            "-p", f"loop_process:={str(loop_process).lower()}", "-r", f"__node:={NAME}", "-r", f"__ns:={NS}"]) \
            as server, RosTestClient(env, "graph_reader") as client:
        def complete():
            names, services = _graph(client)
            return (all(f"{NS}/{NAME}/{s}" in services for s in SERVICES)
                    and (not loop_process or (f"{NAME}_control", NS) in names))

        assert client.wait_for(lambda: "serving 1 primitive(s)" in server.output(), 90), server.output_tail()
        assert client.wait_for(complete, 30), (_graph(client), server.output_tail())
        client.spin_for(1.0)  # anything else the server process creates has been discovered by now
        names, services = _graph(client)
        ours = sorted(n for n in names if n != ("graph_reader", "/"))
        assert len(set(names)) == len(names), f"two nodes share a name: {names}"
        assert ours == sorted([(NAME, NS)] + ([(f"{NAME}_control", NS)] if loop_process else [])), ours
        for s, t in SERVICES.items():
            assert services[f"{NS}/{NAME}/{s}"] == [t]
        assert f"{NS}/{NAME}/execute/_action/send_goal" in services  # the Execute action's own services
        # the command stream and the robot state: on the control process's node (or the server's in-process)
        loop_node = (f"{NAME}_control" if loop_process else NAME, NS)
        pubs = dict(client.node.get_publisher_names_and_types_by_node(*loop_node))
        subs = dict(client.node.get_subscriber_names_and_types_by_node(*loop_node))
        assert pubs.get(f"{NS}/joint_command") == ["sensor_msgs/msg/JointState"], pubs
        assert pubs.get(f"{NS}/joint_trajectory_controller/joint_trajectory") == [
            "trajectory_msgs/msg/JointTrajectory"], pubs
        assert subs.get(f"{NS}/joint_states") == ["sensor_msgs/msg/JointState"], subs
    assert "Traceback" not in server.output(), server.output_tail()
