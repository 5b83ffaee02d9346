"""The ROS graph of sim_bridge and demo_recorder as a user sees it (``ros2 node list`` / ``ros2 node
info``), in both modes (fast path, plain rclpy), each started with a node-name and a namespace remap
(what a launch file's ``name=`` / ``namespace=`` does): no two nodes share a name, each process is
one node, and each node lists its own topics and services. Read from another process's node; a
short recording through the remapped names shows the subscriptions are the ones in use. Real
processes, real DDS (LOCALHOST discovery, random domain)."""

import pytest
from deepprompt_msgs.srv import StartRecording, StopRecording

from deepprompt_ros.ros.testing import NodeProcess, RosTestClient, isolated_ros_env

NS, SIM, RECORDER = "/left", "arm_sim", "arm_recorder"
SIM_PUBLISHES = {"/left/joint_states": "sensor_msgs/msg/JointState", "/clock": "rosgraph_msgs/msg/Clock",
                 "/left/robot_description": "std_msgs/msg/String", "/left/camera/image_raw": "sensor_msgs/msg/Image",
                 "/left/objects/cube/pose": "geometry_msgs/msg/PoseStamped"}
SIM_SUBSCRIBES = {"/left/joint_command": "sensor_msgs/msg/JointState",
                  "/left/guide_target": "geometry_msgs/msg/PointStamped"}
SIM_SERVICES = {"/left/spawn_object": "deepprompt_msgs/srv/SpawnObject",
                "/left/set_kinesthetic": "std_srvs/srv/SetBool", "/left/reset": "std_srvs/srv/Trigger"}
RECORDER_SUBSCRIBES = {"/left/joint_states": "sensor_msgs/msg/JointState",
                       "/left/objects/cube/pose": "geometry_msgs/msg/PoseStamped"}
RECORDER_SERVICES = {"/left/start_recording": "deepprompt_msgs/srv/StartRecording",
                     "/left/stop_recording": "deepprompt_msgs/srv/StopRecording"}


def _by_node(client, node: str):
    """(publishers, subscriptions, services) of node ``node`` in NS: {name: [type, ...]} each."""
    n = client.node
    return (dict(n.get_publisher_names_and_types_by_node(node, NS)),
            dict(n.get_subscriber_names_and_types_by_node(node, NS)),
            dict(n.get_service_names_and_types_by_node(node, NS)))


def _lists(entities: dict, expected: dict) -> bool:
    return all(entities.get(name) == [t] for name, t in expected.items())


@pytest.mark.parametrize("fast_path", [True, False], ids=["fast_path", "plain_rclpy"])
def test_remapped_nodes_have_unique_names_and_list_their_own_topics_and_services(tmp_path, fast_path):
    env = isolated_ros_env(tmp_path / "log")
    mode = ["-p", f"fast_path:={str(fast_path).lower()}"]
    sim_args = mode + ["-p", "rate_hz:=200.0", "-p", "camera.width:=16", "-p", "camera.height:=16",
                       "-p", "camera.rate_hz:=1.0", "-p", "object_names:=[cube]",
                       "-r", f"__node:={SIM}", "-r", f"__ns:={NS}"]
    rec_args = mode + ["-p", f"output_directory:={tmp_path / 'demos'}", "-p", "record_bag:=false",
                       "-p", "context_topics:=[object=objects/cube/pose]",
                       "-r", f"__node:={RECORDER}", "-r", f"__ns:={NS}"]
    with NodeProcess.start_module("deepprompt_ros.ros.sim_bridge", env, ros_args=sim_args, log_dir=tmp_path) as sim, \
            NodeProcess.start_module("deepprompt_ros.ros.demo_recorder", env, ros_args=rec_args,
                                     log_dir=tmp_path) as recorder, \
            RosTestClient(env, "graph_reader") as client:
        def complete():
            if not (sim.running() and recorder.running()):
                return True  # fails below, with the output
            names = client.node.get_node_names_and_namespaces()
            if not {(SIM, NS), (RECORDER, NS)} <= set(names):
                return False
            pubs, subs, srvs = _by_node(client, SIM)
            _, rec_subs, rec_srvs = _by_node(client, RECORDER)
            return (_lists(pubs, SIM_PUBLISHES) and _lists(subs, SIM_SUBSCRIBES) and _lists(srvs, SIM_SERVICES)
                    and _lists(rec_subs, RECORDER_SUBSCRIBES) and _lists(rec_srvs, RECORDER_SERVICES))

        def outputs():
            return sim.output_tail() + "\n" + recorder.output_tail()

        # the recorder subscribes the cube's pose once it has discovered its publisher (0.5 s timer)
        assert client.wait_for(complete, 90), (client.node.get_node_names_and_namespaces(), outputs())
        assert sim.running() and recorder.running(), outputs()
        client.spin_for(1.0)  # anything else the two processes create has been discovered by now
        names = client.node.get_node_names_and_namespaces()
        assert len(set(names)) == len(names), f"two nodes share a name: {names}"
        ours = sorted(n for n in names if n != ("graph_reader", "/"))
        assert ours == [(RECORDER, NS), (SIM, NS)], ours  # one node per process, as remapped

        pubs, subs, srvs = _by_node(client, SIM)
        rec_pubs, rec_subs, rec_srvs = _by_node(client, RECORDER)
        for name, t in SIM_PUBLISHES.items():
            assert pubs.get(name) == [t], (name, pubs)
        for name, t in SIM_SUBSCRIBES.items():
            assert subs.get(name) == [t], (name, subs)
        parameters = "rcl_interfaces/srv/GetParameters"
        for name, t in {**SIM_SERVICES, f"{NS}/{SIM}/get_parameters": parameters}.items():
            assert srvs.get(name) == [t], (name, srvs)
        for name, t in RECORDER_SUBSCRIBES.items():
            assert rec_subs.get(name) == [t], (name, rec_subs)
        for name, t in {**RECORDER_SERVICES, f"{NS}/{RECORDER}/get_parameters": parameters}.items():
            assert rec_srvs.get(name) == [t], (name, rec_srvs)
        # each node's topics and services are its own, none listed on the other
        assert not set(SIM_SERVICES) & set(rec_srvs) and not set(RECORDER_SERVICES) & set(srvs)
        assert not set(SIM_PUBLISHES) & set(rec_pubs)

        # the remapped recorder records the remapped sim's joint states through those subscriptions
        assert client.wait_for_recorder(NS, 30.0), outputs()
        res = client.call(StartRecording, f"{NS}/start_recording", StartRecording.Request(demo_name="graph"), 30.0)
        assert res.success, res.message + outputs()
        client.spin_for(0.5)
        res = client.call(StopRecording, f"{NS}/stop_recording", StopRecording.Request(), 30.0)
        assert res.success and res.n_samples > 10, res.message + outputs()
        assert (tmp_path / "demos" / "graph.npz").is_file()
    for proc in (sim, recorder):
        assert proc.returncode == 0 and "Traceback" not in proc.output(), proc.output_tail()
