"""primitive_server's control loop in a child process (loop_process: true, the default):
a crash of the child ends the running goal with INTERNAL_ERROR (no hang) and a new child takes
over; the child dies with the server (no orphan); every thread of the child runs SCHED_FIFO by
default where the kernel grants it, and where it refuses (checked here even as root, with the
server started without CAP_SYS_NICE and with RLIMIT_RTPRIO 0) the refusal is a warning, every thread
runs normal scheduling and goals execute; ``control_cpu`` pins it; the in-process mode (loop_process:
false) still executes, with the fast path and with plain rclpy. Real processes, real DDS (LOCALHOST discovery, random domain)."""
import contextlib
import os
import pathlib
import re
import shutil
import signal
import sys
import time

import pytest
import yaml

from deepprompt_msgs.action import Execute
from deepprompt_msgs.msg import ResultCode
from deepprompt_msgs.srv import Condition
from rclpy.action import ActionClient

from deepprompt_ros.ros.testing import NodeProcess, RosTestClient, isolated_ros_env, write_params_file

SRV = "/primitive_server"
CHILD = re.compile(r"control loop running in its own process \(pid (\d+)\)")


def alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError):
        return False


#: Runs the command of its arguments with the real-time priority refused even to root: RLIMIT_RTPRIO
#: 0, and CAP_SYS_NICE (which lets a process exceed that limit) dropped from the capability bounding
#: set, so the exec'd process and its children do not have it. Without CAP_SETPCAP (not root) the
#: drop is refused, and not needed: such a process has no CAP_SYS_NICE to lose.
NO_REALTIME = """
import ctypes, os, resource, sys
resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))
ctypes.CDLL(None, use_errno=True).prctl(24, 23, 0, 0, 0)  # PR_CAPBSET_DROP, CAP_SYS_NICE
os.execv(sys.argv[1], sys.argv[1:])
"""


def start(tmp, name, params, model, no_realtime=False):
    """sim_bridge + primitive_server serving ``model`` (copied into ``tmp``) as 'reach';
    ``no_realtime``: the server started through :data:`NO_REALTIME`."""
    reach = tmp / "reach.safetensors"
    if not reach.exists():
        shutil.copy(model, reach)
    prims = tmp / "primitives.yaml"
    prims.write_text(yaml.safe_dump({"primitives": [{"name": "reach", "model": str(reach)}]}))
    env = isolated_ros_env(tmp / f"log_{name}")
    sim = NodeProcess.start_module("deepprompt_ros.ros.sim_bridge", env, params={
        "camera.enabled": False, "publish_clock": False})
    server_params = {"primitives_file": str(prims), "stale_timeout": 1.0, **params}
    if no_realtime:
        params_file = write_params_file(tmp / f"server_{name}.yaml", server_params)
        server = NodeProcess([sys.executable, "-c", NO_REALTIME, sys.executable, "-m",
                              "deepprompt_ros.ros.primitive_server", "--ros-args", "--params-file", str(params_file)],
                             env, tmp / f"server_{name}.log")
    else:
        server = NodeProcess.start_module("deepprompt_ros.ros.primitive_server", env, params=server_params)
    return env, sim, server


def run_goal(client, ac, server, duration, feedback=None, before_result=None):
    r = client.call(Condition, f"{SRV}/condition", Condition.Request(primitive="reach"), timeout=20)
    assert r.success, r.message
    fut = ac.send_goal_async(Execute.Goal(handle=r.handle, duration=duration),
                             feedback_callback=(lambda m: feedback.append(m.feedback)) if feedback is not None else None)
    assert client.wait_for(fut.done, 10)
    gh = fut.result()
    assert gh.accepted
    res = gh.get_result_async()
    if before_result is not None:
        before_result(res)
    assert client.wait_for(res.done, 30), "no Execute result:\n" + server.output_tail()
    return res.result().result


def run_goal_once_state_arrives(client, ac, server, duration, timeout=10.0):
    """:func:`run_goal`, sent again while (and only while) it is refused because the server has not
    yet seen a joint state: the child logs "receiving joint_states" as soon as it receives them, and
    the server learns it from the child's next status message, which can come a little later.
    Any other result, or the refusal after ``timeout`` s, is returned."""
    end = time.monotonic() + timeout
    while True:
        res = run_goal(client, ac, server, duration)
        if not (res.code.value == ResultCode.ROBOT_STATE_STALE and "no joint_states received" in res.message
                and time.monotonic() < end):
            return res
        client.spin_for(0.2)


@pytest.fixture(scope="module")
def nodes(tmp_path_factory, tiny_reach_model):
    with serving(tmp_path_factory.mktemp("control_process"), "child", {}, tiny_reach_model) as (client, ac, server):
        yield dict(client=client, ac=ac, server=server)


def thread_policies(pid: int) -> dict[str, tuple[int, int]]:
    """{thread name: (scheduling policy, real-time priority)} of every thread of ``pid`` (/proc)."""
    out = {}
    for task in pathlib.Path(f"/proc/{pid}/task").iterdir():
        try:
            comm = (task / "comm").read_text().strip()
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except (FileNotFoundError, ProcessLookupError):
            continue  # the thread ended meanwhile
        out[f"{comm}/{task.name}"] = (int(fields[38]), int(fields[37]))  # stat fields 41 and 40
    return out


def sched_fifo_granted() -> bool:
    """Whether the kernel grants this process SCHED_FIFO (the servers these tests start inherit what
    it may do); its own scheduling is restored."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except PermissionError:
        return False
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    return True


def assert_refused_and_normal(server, policies) -> None:
    """The refusal of SCHED_FIFO 50 is a warning in the log and every thread of the control process
    runs normal scheduling."""
    assert "SCHED_FIFO priority 50 refused" in server.output(), server.output_tail()
    assert all(pol == os.SCHED_OTHER for pol, _ in policies.values()), policies


def test_every_thread_of_the_control_process_runs_sched_fifo_by_default(nodes):
    """realtime_priority 50 (the default): where the kernel grants it, the control thread AND every
    other thread of the child (status sender, link reader, JointTrajectory writer, the DDS threads) at
    SCHED_FIFO 50 — none of them can hold the interpreter lock while preempted by an ordinary process.
    Where it refuses (no CAP_SYS_NICE and a lower RLIMIT_RTPRIO), the refusal is a warning in the log,
    every thread runs normal scheduling and the goal executed all the same."""
    server = nodes["server"]
    assert run_goal(nodes["client"], nodes["ac"], server, 0.5).success  # every thread has been started
    pid = int(CHILD.findall(server.output())[-1])
    policies = thread_policies(pid)
    assert len(policies) >= 4, policies
    if sched_fifo_granted():
        assert all(v == (os.SCHED_FIFO, 50) for v in policies.values()), policies
        assert any(name.startswith("control_loop") for name in policies), policies
        assert "SCHED_FIFO priority 50 refused" not in server.output(), server.output_tail()
    else:
        assert_refused_and_normal(server, policies)


def test_a_refused_realtime_priority_is_a_warning_and_goals_execute(tmp_path, tiny_reach_model):
    """The refused path on any machine, root included: the server (and so its control process) is
    started without CAP_SYS_NICE and with RLIMIT_RTPRIO 0 (:data:`NO_REALTIME`). The refusal is logged,
    every thread of the child runs normal scheduling, and goals execute."""
    with serving(tmp_path, "no_realtime", {}, tiny_reach_model, no_realtime=True) as (client, ac, server):
        res = run_goal(client, ac, server, 1.0)
        assert res.success, res.message
        pid = int(CHILD.findall(server.output())[-1])
        status = pathlib.Path(f"/proc/{pid}/status").read_text()
        cap_eff = int(re.search(r"CapEff:\s*([0-9a-f]+)", status)[1], 16)
        assert not cap_eff & (1 << 23), status  # CAP_SYS_NICE: the premise of the refusal
        rtprio = re.search(r"Max realtime priority\s+(\d+)\s+(\d+)", pathlib.Path(f"/proc/{pid}/limits").read_text())
        assert rtprio and rtprio.groups() == ("0", "0"), rtprio
        assert_refused_and_normal(server, thread_policies(pid))
        assert run_goal(client, ac, server, 0.5).success  # and keeps executing


def test_child_crash_aborts_the_goal_and_a_new_child_takes_over(nodes):
    client, ac, server = nodes["client"], nodes["ac"], nodes["server"]
    assert client.wait_for(lambda: CHILD.search(server.output()), 30), server.output_tail()
    pid = int(CHILD.findall(server.output())[-1])
    assert alive(pid)
    fb = []

    def crash(res):
        assert client.wait_for(lambda: (fb and fb[-1].phase > 0.1) or res.done(), 20)
        assert not res.done(), res.result().result.message
        os.kill(pid, signal.SIGKILL)

    t0 = time.monotonic()
    res = run_goal(client, ac, server, 6.0, fb, crash)
    assert res.code.value == ResultCode.INTERNAL_ERROR and not res.success
    assert "exited unexpectedly" in res.message and str(pid) in res.message
    assert time.monotonic() - t0 < 6.0  # reported, not waited out
    assert client.wait_for(lambda: len(CHILD.findall(server.output())) >= 2, 30), server.output_tail()
    new = int(CHILD.findall(server.output())[-1])
    assert new != pid and alive(new) and "control process restarted" in server.output()
    # the new child streams: an execution succeeds
    assert client.wait_for(lambda: server.output().count("receiving joint_states") >= 2, 30), server.output_tail()
    res = run_goal_once_state_arrives(client, ac, server, 1.5)
    assert res.success, res.message


def test_child_dies_with_the_server(nodes):
    server = nodes["server"]
    pid = int(CHILD.findall(server.output())[-1])
    assert alive(pid)
    os.kill(server.pid, signal.SIGKILL)  # no chance to stop it
    end = time.monotonic() + 10
    while alive(pid) and time.monotonic() < end:
        time.sleep(0.05)
    assert not alive(pid), "control process outlived the server"


@contextlib.contextmanager
def serving(tmp_path, name, params, model, no_realtime=False):
    """sim_bridge + primitive_server with ``params`` serving ``model``, ready (action server up,
    joint_states received): yields (client, action client, server); stops both processes.
    ``no_realtime``: see :func:`start`."""
    env, sim, server = start(tmp_path, name, params, model, no_realtime)
    try:
        with RosTestClient(env) as client:
            ac = ActionClient(client.node, Execute, f"{SRV}/execute")
            assert client.wait_for(ac.server_is_ready, 60), server.output_tail()
            assert client.wait_for(lambda: "receiving joint_states" in server.output(), 60), server.output_tail()
            yield client, ac, server
            ac.destroy()
    finally:
        server.stop()
        sim.stop()


@pytest.mark.parametrize("fast_path", [True, False], ids=["fast_path", "plain_rclpy"])
def test_in_process_loop_still_executes(tmp_path, tiny_reach_model, fast_path):
    with serving(tmp_path, "inproc", {"loop_process": False, "fast_path": fast_path},
                 tiny_reach_model) as (client, ac, server):
        res = run_goal(client, ac, server, 1.5)
        assert res.success, res.message
        assert "in this process" in server.output() and not CHILD.search(server.output())


def test_control_cpu_pins_every_thread_and_a_missing_cpu_is_a_warning(tmp_path, tiny_reach_model):
    """control_cpu: N pins the control process (all its threads, DDS included) to CPU N; a CPU the
    machine does not have is a warning and the loop still executes on any CPU."""
    cpu = max(os.sched_getaffinity(0))
    for name, value in (("pinned", cpu), ("absent", 1023)):
        with serving(tmp_path, name, {"control_cpu": value}, tiny_reach_model) as (client, ac, server):
            res = run_goal(client, ac, server, 0.5)
            assert res.success, res.message
            pid = int(CHILD.findall(server.output())[-1])
            masks = {t.name: os.sched_getaffinity(int(t.name)) for t in pathlib.Path(f"/proc/{pid}/task").iterdir()}
            if name == "pinned":
                assert len(masks) >= 4 and all(m == {cpu} for m in masks.values()), masks
            else:
                assert "control_cpu 1023 refused" in server.output(), server.output_tail()
                assert all(m == os.sched_getaffinity(0) for m in masks.values()), masks
