"""Several robots, one planner, over real DDS (LOCALHOST discovery, random domain), every node a real
process: the nodes of the ``dual_arm`` launch (deepprompt_ros.bringup), a simulated Gen3 lite with its
primitive_server under ``/left_arm`` and a simulated WAM with its own under ``/right_arm``, and this
test's client as the one planner.

1. The graph: every topic, service and the Execute action of each arm is under its namespace and
   published by that arm's nodes only; nothing is published outside the two namespaces but ROS's own
   /rosout and /parameter_events and /clock, which the left arm's sim_bridge alone publishes.
2. The planner conditions each server on a via-point off its prior mean and executes both goals at
   once: both succeed, their executions overlap, each arm's measured joint_states pass through its
   via-point, each namespace's command stream carries its own robot's joints only, and no command or
   joint state appears on an un-namespaced topic.
"""
import dataclasses
import math
import sys
import time

import numpy as np
import pytest
from deepprompt_msgs.action import Execute
from deepprompt_msgs.msg import ResultCode
from deepprompt_msgs.srv import Condition
from rclpy.action import ActionClient

from deepprompt_ros import bringup
from deepprompt_ros.execution.plan import ExecutionReference
from deepprompt_ros.robots.spec import load_robot
from deepprompt_ros.ros import conversions as conv
from deepprompt_ros.ros.testing import JointStateTap, NodeProcess, RosTestClient, isolated_ros_env
from deepprompt_ros.server.config import ServerConfig, robot_limits


@dataclasses.dataclass(frozen=True)
class Arm:
    """One arm of the launch and what the test asks of it."""

    namespace: str
    robot: str
    primitive: str
    periodic: bool
    #: offset (rad) of the via-point from the prior mean at VIA_PHASE, on the two joints the prior
    #: varies most there: about one prior standard deviation (reach 0.06-0.16 rad, shake ~0.026 rad)
    via_offset: float

    @property
    def spec(self):
        return load_robot(self.robot)

    def name(self, relative: str) -> str:
        return f"/{self.namespace}/{relative}"


ARMS = (Arm("left_arm", "gen3_lite", "reach", False, 0.03), Arm("right_arm", "wam", "shake", True, 0.025))
VIA_PHASE = 0.5
#: goal duration / the shortest the velocity limits allow for the conditioned mean (the server's preview).
#: The simulations follow the newest command when they fall behind the wall clock (a busy machine pauses
#: them), cutting across the path by up to the distance the arm moved meanwhile: at 1.3 x (the other
#: tests' ordinary goals) runs on a loaded 2-core machine missed the via-points by 15-70 mrad with the
#: simulations at 0.5-0.7 x real time; at 2 x, with the simulations at SIM_RATE_HZ, within 3 mrad.
MARGIN = 2.0
#: Physics steps per simulated second of both simulations (their robots' control rates are 1000 and 500 Hz):
#: two Python simulations at those rates beside two servers fell to 0.5-0.7 x real time on a busy 2-core
#: machine. The servers still stream at the robots' control rates; the simulations follow the newest command.
SIM_RATE_HZ = 250.0
#: How close (max over joints, rad) each measured arm must pass to its via-point: as in
#: test_ros_end_to_end (the refined mean meets it within 1e-6 rad; Ruckig and PyBullet's position loop
#: follow the stream with a lag along the path, little across it).
VIA_TOLERANCE = 0.01
#: the global topics of every ROS 2 node (its log and its parameter events)
ROS_GLOBAL = {"/rosout", "/parameter_events"}
GRID = ServerConfig().execution_grid_points


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    return isolated_ros_env(tmp_path_factory.mktemp("multi_robot") / "log")


@pytest.fixture(scope="module")
def nodes(env):
    """The dual_arm launch's nodes (robot_state_publisher, not installable here, left out; cameras
    off and physics at SIM_RATE_HZ), each its own process."""
    described = bringup.nodes("dual_arm", {"left_robot": ARMS[0].robot, "right_robot": ARMS[1].robot,
                                           "left_namespace": ARMS[0].namespace,
                                           "right_namespace": ARMS[1].namespace})
    procs = {}
    try:
        for node in described:
            if node.optional:
                continue
            if node.executable == "sim_bridge":
                node = dataclasses.replace(node, parameters={
                    **node.parameters, "camera.enabled": False, "rate_hz": SIM_RATE_HZ})
            procs[(node.namespace, node.executable)] = NodeProcess(
                node.command(sys.executable), {**env, **dict(node.environment)},
                f"{env['ROS_LOG_DIR']}/{node.namespace}_{node.executable}.log")
        yield procs
    finally:
        NodeProcess.stop_all(procs.values())


def _outputs(procs) -> str:
    return "\n".join(p.output_tail(1500) for p in procs.values())


@pytest.fixture(scope="module")
def planner(env, nodes):
    """The test's client, with an Execute action client per server, once both serve and receive their
    robot's joint_states."""
    with RosTestClient(env, "planner") as client:
        client.actions = {a.namespace: ActionClient(client.node, Execute, a.name("primitive_server/execute"))
                          for a in ARMS}
        for arm in ARMS:
            server = nodes[(arm.namespace, "primitive_server")]
            assert client.wait_for(client.actions[arm.namespace].server_is_ready, 90.0), _outputs(nodes)
            assert client.wait_for(lambda: "receiving joint_states" in server.output(), 60.0), _outputs(nodes)
            assert client.wait_for_publisher(arm.name("joint_command"), 30.0), _outputs(nodes)
        yield client
        for ac in client.actions.values():
            ac.destroy()


def _node_of(info) -> tuple[str, str]:
    return info.node_namespace, info.node_name


def test_each_arm_has_its_own_names_and_nothing_else_is_published(planner, nodes):
    node = planner.node
    planner.spin_for(1.0)  # what the processes create has been discovered by now
    ours = {(f"/{a.namespace}", n) for a in ARMS for n in ("sim_bridge", "primitive_server",
                                                            "primitive_server_control")}
    names = set(node.get_node_names_and_namespaces())
    assert {(name, ns) for ns, name in ours} <= names, names
    published = {}
    for topic, _ in node.get_topic_names_and_types():
        pubs = {_node_of(i) for i in node.get_publishers_info_by_topic(topic)} - {("/", "planner")}
        if pubs:
            published[topic] = pubs
    for arm in ARMS:
        ns = f"/{arm.namespace}"
        # each of its names is published by its own nodes only
        for topic, pubs in published.items():
            if topic.startswith(ns + "/"):
                assert {p[0] for p in pubs} == {ns}, (topic, pubs)
        assert published[arm.name("joint_states")] == {(ns, "sim_bridge")}
        assert published[arm.name("joint_command")] == {(ns, "primitive_server_control")}
        assert published[arm.name("joint_trajectory_controller/joint_trajectory")] == {
            (ns, "primitive_server_control")}
        assert published[arm.name("primitive_server/execute/_action/feedback")] == {(ns, "primitive_server")}
        services = dict(node.get_service_names_and_types_by_node("primitive_server", ns))
        assert {arm.name(f"primitive_server/{s}") for s in ("condition", "blend", "sample", "list_primitives",
                                                            "set_phase_rate", "execute/_action/send_goal")} \
            <= set(services), services
        assert all(s.startswith(ns + "/") for s in services), services
        for srv in ("spawn_object", "set_kinesthetic", "reset"):
            assert arm.name(srv) in dict(node.get_service_names_and_types_by_node("sim_bridge", ns))
    outside = {t: p for t, p in published.items() if not any(t.startswith(f"/{a.namespace}/") for a in ARMS)}
    assert set(outside) == ROS_GLOBAL | {"/clock"}, outside
    assert outside["/clock"] == {(f"/{ARMS[0].namespace}", "sim_bridge")}  # one clock: the first arm's


def _condition(planner, arm, **kw):
    r = planner.call(Condition, arm.name("primitive_server/condition"),
                     Condition.Request(primitive=arm.primitive, **kw), timeout=30.0)
    assert r.success, r.message
    return r


def _plan(planner, arm):
    """Condition ``arm``'s primitive on a via-point off its prior mean; the via-point, the conditioned
    mean on the execution grid, the goal's duration (MARGIN x the shortest its preview allows) and
    how far the prior mean passes from the via-point."""
    prior = conv.preview_from_msg(_condition(planner, arm, preview_points=GRID).preview)
    k = int(round(VIA_PHASE * (GRID - 1)))
    joints = np.sort(np.argsort(prior.std[k])[-2:])  # the joints the primitive varies most there
    via = prior.mean[k].copy()
    via[joints] += np.array([arm.via_offset, -arm.via_offset])
    arm.spec.validate_positions(via)
    r = _condition(planner, arm, via_points=conv.via_points_to_msgs([VIA_PHASE], [via]), refine=True,
                   preview_points=GRID)
    assert r.reachable and r.refine_max_error <= 1e-6, (r.reachable, r.refine_max_error, r.message)
    preview = conv.preview_from_msg(r.preview)
    limits = robot_limits(arm.spec, ServerConfig())
    v_max = dict(zip(limits.names, limits.max_velocity))
    shortest = ExecutionReference(preview.mean, arm.periodic, ServerConfig().derivative_step).shortest_duration(
        [v_max[name] for name in preview.joint_names])
    prior_gap = np.abs(prior.mean - via).max(axis=1).min()
    return r.handle, via, preview.mean, MARGIN * shortest, prior_gap


def _closest_approach(q, mean, via):
    """Closest approach (max over joints) of the measured configurations ``q`` to ``via``, among those
    whose nearest point on the conditioned mean path is within 0.25 of the via phase."""
    n = mean.shape[0]
    near = np.abs(q[:, None, :] - mean[None, ::10, :]).max(axis=2).argmin(axis=1) * 10 / (n - 1)
    window = np.abs(near - VIA_PHASE) <= 0.25
    return float(np.where(window, np.abs(q - via).max(axis=1), np.inf).min())


def test_one_planner_executes_on_both_arms_at_once(planner, nodes):
    plans = {arm.namespace: _plan(planner, arm) for arm in ARMS}
    left, right = ARMS
    # the rhythmic WAM runs as many cycles as it takes to cover the reach's whole execution
    cycles = {left.namespace: 1,
              right.namespace: math.ceil(plans[left.namespace][3] / plans[right.namespace][3])}
    taps = {(arm.namespace, what): JointStateTap(planner, arm.name(what)) for arm in ARMS
            for what in ("joint_states", "joint_command")}
    global_taps = {what: JointStateTap(planner, f"/{what}") for what in ("joint_states", "joint_command")}
    every_tap = [*taps.values(), *global_taps.values()]

    def take():
        for tap in every_tap:
            tap.take()

    feedback = {arm.namespace: [] for arm in ARMS}
    try:
        # each arm's taps have matched its publishers (what comes before is not received)
        assert planner.wait_for(lambda: take() or all(t.matched() for t in taps.values()), 30.0), _outputs(nodes)
        planner.wait_for(lambda: take() or False, 0.3)
        for tap in every_tap:
            tap.raw.clear()
        results, t_done = {}, {}
        t0 = time.perf_counter()
        for arm in ARMS:  # one goal after the other, without waiting: both execute at once
            handle, _, _, duration, _ = plans[arm.namespace]
            results[arm.namespace] = planner.actions[arm.namespace].send_goal_async(
                Execute.Goal(handle=handle, duration=duration, cycles=cycles[arm.namespace]),
                feedback_callback=lambda m, ns=arm.namespace: feedback[ns].append((time.perf_counter(), m.feedback)))
        assert planner.wait_for(lambda: take() or all(f.done() for f in results.values()), 10.0)
        assert all(f.result().accepted for f in results.values())
        results = {ns: f.result().get_result_async() for ns, f in results.items()}

        def finished():
            take()
            for ns, f in results.items():
                if f.done() and ns not in t_done:
                    t_done[ns] = time.perf_counter()
            return len(t_done) == len(results)

        longest = max(plans[a.namespace][3] * cycles[a.namespace] for a in ARMS)
        assert planner.wait_for(finished, 3 * longest + 30.0), _outputs(nodes)
        planner.wait_for(lambda: take() or False, 0.3)  # the arms settle on their last commands
        take()
    finally:
        for tap in every_tap:
            tap.close()

    report, errors, gaps = [], {}, {}
    for arm in ARMS:
        ns = arm.namespace
        res = results[ns].result().result
        assert res.success and res.code.value == ResultCode.SUCCESS, res.message + _outputs(nodes)
        assert res.cycles_completed == cycles[ns]
        names = list(arm.spec.joint_names)
        # its command stream and joint states: its own robot's joints only (a message naming other
        # joints would fail the reordering), commands at its robot's control rate
        for what in ("joint_command", "joint_states"):
            tap = taps[(ns, what)]
            assert tap.raw, f"no {arm.name(what)}"
            stamps, q, _ = tap.arrays(names)
            assert q.shape[1] == len(names) and np.all(np.diff(stamps) > 0)
        stamps, _, _ = taps[(ns, "joint_command")].arrays(names)
        assert np.median(np.diff(stamps)) == pytest.approx(1e9 / arm.spec.control_rate_hz, rel=1e-3)
        stamps, q, _ = taps[(ns, "joint_states")].arrays(names)
        handle, via, mean, duration, prior_gap = plans[ns]
        err = _closest_approach(q, mean, via)
        moving = [t for t, f in feedback[ns] if f.phase > 0.0 or f.cycle > 0]
        report.append(f"{arm.name('')} {arm.robot} {arm.primitive}: {cycles[ns]} x {duration:.2f} s, moving "
                      f"{moving[0] - t0:.2f}-{t_done[ns] - t0:.2f} s; via-point {err * 1e3:.2f} mrad (prior mean "
                      f"{prior_gap * 1e3:.1f} mrad away), {len(taps[(ns, 'joint_command')].raw)} commands, "
                      f"max tracking error {res.max_tracking_error * 1e3:.1f} mrad; {(stamps[-1] - stamps[0]) * 1e-9:.2f} "
                      f"simulated s over {t_done[ns] - t0:.2f} wall s")
        errors[ns], gaps[ns] = err, prior_gap
    print("\n".join(report))
    assert all(g > 2 * VIA_TOLERANCE for g in gaps.values()), report  # the via-points are off the prior means
    assert all(e <= VIA_TOLERANCE for e in errors.values()), report
    # the two executions overlapped: each was moving before the other finished
    first_moving = {ns: next(t for t, f in fb if f.phase > 0.0 or f.cycle > 0) for ns, fb in feedback.items()}
    assert all(first_moving[a.namespace] < min(t_done.values()) for a in ARMS), (first_moving, t_done)
    # feedback only from the arm's own goal: its phase rises within a cycle, its cycles count up
    for ns, fb in feedback.items():
        progress = [f.cycle + f.phase for _, f in fb]
        assert np.all(np.diff(progress) >= -1e-9) and max(f.cycle for _, f in fb) >= cycles[ns] - 1, (ns, progress)
    # nothing outside the namespaces
    assert [len(t.raw) for t in global_taps.values()] == [0, 0]
