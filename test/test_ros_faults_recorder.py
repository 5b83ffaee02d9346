"""demo_recorder stopped in the middle of a recording, as a real process over real DDS (LOCALHOST
discovery, random domain); the joint states (250 Hz) and an object pose (the context) are published
by this test.

* SIGKILL and SIGINT mid-recording: the demonstrations finished before are intact and load
  (:func:`deepprompt_ros.data.demo_dataset.load_dataset`, their bags read back), the interrupted one
  is nowhere presented as a demonstration (no ``.npz``, no final bag; its raw messages stay in a
  hidden ``.part`` folder), and a new recorder on the same folders records again, the interrupted
  name included. SIGINT ends the recorder cleanly (exit code 0) and its log says what was left.
* A half-written demonstration left by a crash during the write (``<name>.npz.part``) is not loaded
  as a demonstration and does not keep that name from being recorded.
"""
from __future__ import annotations

import pathlib
import signal
import threading
import time

import numpy as np
import pytest
from deepprompt_msgs.msg import ResultCode
from deepprompt_msgs.srv import StartRecording, StopRecording
from geometry_msgs.msg import PoseStamped
from mcap.reader import make_reader
from sensor_msgs.msg import JointState

from deepprompt_ros.data.demo_dataset import load_dataset
from deepprompt_ros.data.io import load_demo
from deepprompt_ros.robots.spec import load_robot
from deepprompt_ros.ros import conversions as conv
from deepprompt_ros.ros.testing import NodeProcess, RosTestClient

SPEC = load_robot("gen3_lite")
RATE_HZ = 250.0
CUBE = [0.35, -0.1, 0.02]


class Robot:
    """joint_states (a slow sine on every joint, header stamped now) at RATE_HZ and the cube's pose at
    30 Hz, published from a thread of the test's node."""

    def __init__(self, client: RosTestClient):
        self.js = client.node.create_publisher(JointState, "joint_states", 100)
        self.pose = client.node.create_publisher(PoseStamped, "objects/cube/pose", 10)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        k = 0
        t0 = time.monotonic()
        while not self._stop.wait(1.0 / RATE_HZ):
            t = time.monotonic() - t0
            q = np.asarray(SPEC.home) + 0.1 * np.sin(t + np.arange(len(SPEC.joint_names)))
            self.js.publish(conv.arrays_to_joint_state(SPEC.joint_names, q, stamp_ns=time.time_ns()))
            if k % int(RATE_HZ / 30) == 0:
                self.pose.publish(conv.pose_stamped(CUBE, stamp_ns=time.time_ns(), frame_id="world"))
            k += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)


@pytest.fixture(scope="module")
def client(ros_env):
    with RosTestClient(ros_env) as c:
        c.robot = Robot(c)
        yield c
        c.robot.close()


def start_recorder(env, client, out: pathlib.Path, name: str) -> NodeProcess:
    """A demo_recorder in namespace ``/<name>`` (its services are its own: a killed recorder's stay
    in the DDS discovery data for a while, and a request to them is lost)."""
    proc = NodeProcess.start_module("deepprompt_ros.ros.demo_recorder", env, name=name, ros_args=[
        "-r", f"__ns:=/{name}"], params={"output_directory": str(out), "joint_states_topic": "/joint_states",
                                         "context_topics": ["object=/objects/cube/pose"]})
    proc.ns = f"/{name}"
    if not client.wait_for_recorder(proc.ns, 30.0):
        proc.stop()
        raise AssertionError("the recorder's services did not answer within 30 s" + proc.output_tail())
    return proc


def start(client, proc, name, timeout=30.0):
    """start_recording ``name``, again while the recorder has not yet seen the joint states or the
    context's publisher (both are discovered after it starts)."""
    srv = f"{proc.ns}/start_recording"
    assert client.wait_for_service(StartRecording, srv, 30.0), proc.output_tail()
    end = time.monotonic() + timeout
    while True:
        res = client.call(StartRecording, srv, StartRecording.Request(demo_name=name))
        if res.success or time.monotonic() > end or res.code.value not in (
                ResultCode.ROBOT_STATE_STALE, ResultCode.INVALID_REQUEST) or "exists" in res.message:
            assert res.success, res.message + proc.output_tail()
            return res
        client.spin_for(0.2)


def stop(client, proc):
    res = client.call(StopRecording, f"{proc.ns}/stop_recording", StopRecording.Request())
    assert res.success, res.message + proc.output_tail()
    return res


def record(client, proc, name, seconds=0.5):
    start(client, proc, name)
    client.spin_for(seconds)
    return stop(client, proc)


def assert_intact(out: pathlib.Path, finished: dict) -> None:
    """The dataset of ``out`` is exactly the ``finished`` demonstrations ({name: StopRecording
    response}), each with all its samples, its context and its readable bag."""
    dataset = load_dataset(out)
    assert sorted(d.name for d in dataset.demos) == sorted(finished)
    assert sorted(p.stem for p in out.glob("*.npz")) == sorted(finished)
    for demo in dataset.demos:
        res = finished[demo.name]
        assert len(demo.t) == res.n_samples > 20 and np.all(np.diff(demo.t) > 0)
        assert demo.joint_names == SPEC.joint_names
        np.testing.assert_allclose(demo.contexts["object"], [CUBE])
        bag = pathlib.Path(res.bag_path)
        assert bag.parent == out / "bags" / demo.name
        with open(bag, "rb") as f:
            summary = make_reader(f).get_summary()
        assert summary is not None and summary.statistics.message_count >= res.n_samples
    visible = {p.name for p in (out / "bags").iterdir() if not p.name.startswith(".")}
    assert visible == set(finished), visible


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT], ids=["SIGKILL", "SIGINT"])
def test_recorder_stopped_mid_recording_keeps_finished_demos_and_records_again(ros_env, client, tmp_path, sig):
    out = tmp_path / "demos"
    finished = {}
    rec = start_recorder(ros_env, client, out, f"{sig.name.lower()}_1")
    try:
        finished["first"] = record(client, rec, "first")
        start(client, rec, "second")
        client.spin_for(0.5)
        if sig == signal.SIGKILL:
            assert rec.kill() == -signal.SIGKILL
        else:
            assert rec.stop(sigint_timeout=10.0) == 0, rec.output_tail()  # a clean exit, not killed
            log = rec.output()
            assert "recording 'second' was not stopped; nothing added to the dataset" in log, log[-2000:]
            assert "Traceback" not in log
    finally:
        rec.stop()
    assert_intact(out, finished)
    part = [p for p in (out / "bags").iterdir() if p.name.startswith(".second.")]
    assert len(part) == 1 and part[0].name.endswith(".part"), part  # the raw messages, hidden
    assert not list(out.glob("*.part"))

    rec = start_recorder(ros_env, client, out, f"{sig.name.lower()}_2")  # the next start, on the same folders
    try:
        finished["second"] = record(client, rec, "second")  # the interrupted name is free
        finished["third"] = record(client, rec, "third")
    finally:
        rec.stop()
    assert_intact(out, finished)


def test_a_half_written_demo_is_not_a_demo_and_its_name_can_be_recorded(ros_env, client, tmp_path):
    out = tmp_path / "demos"
    out.mkdir()
    rec = start_recorder(ros_env, client, out, "half_written")
    try:
        finished = {"first": record(client, rec, "first")}
        # what a crash during the write of 'second' leaves: a truncated temporary file
        data = (out / "first.npz").read_bytes()
        (out / "second.npz.part").write_bytes(data[: len(data) // 2])
        assert_intact(out, finished)
        finished["second"] = record(client, rec, "second")
    finally:
        rec.stop()
    assert_intact(out, finished)
    assert load_demo(out / "second.npz").name == "second"
