"""deepprompt_msgs: generated types, constants, defaults, CDR round trips, docs.

Needs the interfaces built into the venv (``make setup``); no ROS graph.
"""
import math
import os
import re
import sys

import numpy as np
import pytest

from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image

from deepprompt_msgs.action import Execute
from deepprompt_msgs.msg import Context, PrimitiveInfo, ResultCode, TrajectoryPreview, ViaPoint
from deepprompt_msgs.srv import (Blend, Condition, ListPrimitives, Sample, SetPhaseRate,
                                 SpawnObject, StartRecording, StopRecording)

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MSG_DEFS = os.path.join(REPO, "msg_defs")
SHARE = os.path.join(sys.prefix, "share", "deepprompt_msgs")

SERVICES = [Condition, Blend, Sample, ListPrimitives, SetPhaseRate, StartRecording,
            StopRecording, SpawnObject]

EXPECTED_CODES = {
    "SUCCESS": 0, "INVALID_REQUEST": 1, "UNKNOWN_PRIMITIVE": 2, "UNKNOWN_HANDLE": 3,
    "INVALID_VIA_POINT": 4, "INVALID_CONTEXT": 5, "INVALID_IMAGE": 6,
    "REFINEMENT_UNREACHABLE": 7, "HANDLE_LIMIT": 8, "ROBOT_STATE_STALE": 9,
    "LIMIT_VIOLATION": 10, "CANCELED": 11, "PREEMPTED": 12, "NO_ACTIVE_EXECUTION": 13,
    "RECORDING_ACTIVE": 14, "NOT_RECORDING": 15, "INTERNAL_ERROR": 99,
}


def _roundtrip(msg):
    data = serialize_message(msg)
    # a CDR stream: the encapsulation header (representation CDR_BE 0x0000 or CDR_LE 0x0001, options)
    assert isinstance(data, bytes) and len(data) >= 4 and data[:2] in (b"\x00\x00", b"\x00\x01"), data[:4]
    return deserialize_message(data, type(msg))


def _interface_files():
    out = []
    for kind in ("msg", "srv", "action"):
        folder = os.path.join(MSG_DEFS, kind)
        out += [os.path.join(kind, f) for f in sorted(os.listdir(folder))]
    return out


def test_result_code_constants_are_the_documented_set():
    constants = {name: getattr(ResultCode, name) for name in EXPECTED_CODES}
    assert constants == EXPECTED_CODES
    # all values distinct, so a code identifies one outcome
    assert len(set(constants.values())) == len(constants)
    assert ResultCode().value == ResultCode.SUCCESS


@pytest.mark.parametrize("response", [s.Response for s in SERVICES] + [Execute.Result],
                         ids=lambda t: t.__name__)
def test_every_response_carries_success_code_and_message(response):
    r = response()
    assert r.success is False
    assert isinstance(r.code, ResultCode)
    assert r.message == ""
    r.success, r.code.value, r.message = False, ResultCode.UNKNOWN_HANDLE, "handle 'h7' expired"
    back = _roundtrip(r)
    assert (back.success, back.code.value, back.message) == (False, 3, "handle 'h7' expired")


def test_zero_initialised_weights_mean_weight_one():
    # the server reads omega = weight only when use_weight is true, so an unset
    # weight never silently removes a via-point or context
    for msg in (ViaPoint(), Context()):
        assert msg.use_weight is False
        assert msg.weight == 1.0
    vp = ViaPoint(use_weight=True, weight=0.0)
    assert _roundtrip(vp).use_weight is True and _roundtrip(vp).weight == 0.0


def test_string_constants():
    assert Context.IMAGE_MODALITY == "image"
    assert (PrimitiveInfo.PHASE_LINEAR, PrimitiveInfo.PHASE_RHYTHMIC) == ("linear", "rhythmic")
    assert (SpawnObject.Request.SHAPE_BOX, SpawnObject.Request.SHAPE_SPHERE,
            SpawnObject.Request.SHAPE_CYLINDER) == ("box", "sphere", "cylinder")


def test_condition_request_roundtrips_through_cdr():
    img = Image(height=2, width=3, encoding="rgb8", step=9, data=bytes(range(18)))
    req = Condition.Request(
        primitive="reach",
        via_points=[
            ViaPoint(phase=0.0, positions=[0.1, -0.2, 0.3]),
            ViaPoint(phase=0.75, positions=[1.0, 2.0, -3.0], joint_mask=[True, False, True],
                     use_weight=True, weight=2.5),
        ],
        contexts=[
            Context(modality="object_xy", values=[0.4, -0.1]),
            Context(modality=Context.IMAGE_MODALITY, images=[img, img], use_weight=True,
                    weight=0.5),
        ],
        refine=True, refine_max_iterations=200, refine_tolerance=1e-6, preview_points=100,
    )
    back = _roundtrip(req)
    assert back == req
    assert back.via_points[1].joint_mask == [True, False, True]
    assert back.via_points[1].positions.tolist() == [1.0, 2.0, -3.0]
    assert back.contexts[1].images[1].data.tobytes() == bytes(range(18))
    assert back.refine_tolerance == 1e-6 and back.refine_max_iterations == 200


def test_condition_response_preview_layout_roundtrips():
    n_points, names = 4, ["joint_1", "joint_2"]
    mean = [t * 10.0 + j for t in range(n_points) for j in range(len(names))]  # row-major T x d
    prev = TrajectoryPreview(joint_names=names, phases=[0.0, 1 / 3, 2 / 3, 1.0], mean=mean,
                             std=[0.01] * 8, n_points=n_points, n_joints=2)
    resp = Condition.Response(success=True, handle="h1", handle_expires_in=30.0, preview=prev,
                              refine_max_error=3e-9, refine_iterations=5, reachable=True)
    back = _roundtrip(resp).preview
    assert np.asarray(back.mean).reshape(back.n_points, back.n_joints)[2, 1] == 21.0
    assert len(back.std) == 8 and math.isclose(back.phases[1], 1 / 3)


def test_other_services_roundtrip():
    blend = Blend.Request(handle_a="a", handle_b="b", schedule_phases=[0.0, 0.4, 1.0],
                          schedule_weights=[1.0, 0.5, 0.0], preview_points=50, sample=True,
                          seed=-7)
    assert _roundtrip(blend) == blend
    sample = Sample.Response(joint_names=["j"], phases=[0.0, 1.0], samples=[1.0, 2.0, 3.0, 4.0],
                             n_samples=2, n_points=2, n_joints=1)
    assert _roundtrip(sample) == sample
    info = PrimitiveInfo(name="reach", joint_names=["joint_1"], position_lower=[-2.0],
                         position_upper=[2.0], phase_type=PrimitiveInfo.PHASE_RHYTHMIC,
                         context_modalities=["object_xy"], context_dims=[2],
                         accepts_images=True, image_height=64, image_width=64,
                         image_encoding="rgb8", latent_dim=16, description="demo")
    listed = _roundtrip(ListPrimitives.Response(success=True, primitives=[info, info]))
    assert listed.primitives[1] == info
    spawn = SpawnObject.Request(name="cube", shape="box", size=[0.05, 0.05, 0.05], mass=0.1,
                                rgba=[1.0, 0.0, 0.0, 1.0])
    spawn.pose.position.x = 0.4
    spawn.pose.orientation.w = 1.0
    assert _roundtrip(spawn) == spawn
    stop = StopRecording.Response(success=True, dataset_path="/d.npz", bag_path="/b.mcap",
                                  n_samples=1234)
    assert _roundtrip(stop) == stop
    assert _roundtrip(SetPhaseRate.Request(phase_rate=-0.25)).phase_rate == -0.25
    assert _roundtrip(StartRecording.Request(demo_name="d1", context_topics=["/a"])) \
        .context_topics == ["/a"]


def test_execute_action_parts_roundtrip():
    goal = Execute.Goal(handle="h1", duration=0.0, phase_rate=0.2, cycles=3, reverse=True)
    assert _roundtrip(goal) == goal
    fb = Execute.Feedback(phase=0.5, cycle=2, phase_rate=0.2, tracking_error=1e-3)
    assert _roundtrip(fb) == fb
    res = Execute.Result(success=False, max_tracking_error=0.02, final_phase=0.3,
                         cycles_completed=1)
    res.code.value = ResultCode.CANCELED
    back = _roundtrip(res)
    assert back.code.value == 11 and back.final_phase == 0.3
    # the action machinery types exist (goal request carries the goal)
    send = Execute.Impl.SendGoalService.Request(goal=goal)
    assert _roundtrip(send).goal == goal


_DECL = re.compile(r"^[A-Za-z_][\w/]*(\[\d*\])?\s+[A-Za-z_]\w*(\s*=.*|\s+\S.*)?$")


@pytest.mark.parametrize("relpath", _interface_files())
def test_every_field_is_documented(relpath):
    """Each block of declarations in a .msg/.srv/.action follows a comment, so
    ``ros2 interface show`` explains every field."""
    with open(os.path.join(MSG_DEFS, relpath), encoding="utf-8") as f:
        lines = [ln.rstrip("\n") for ln in f]
    assert lines and lines[0].startswith("#"), f"{relpath} must start with a description"
    documented = False
    for number, line in enumerate(lines, 1):
        stripped = line.strip()
        if stripped.startswith("#"):
            documented = True
        elif stripped in ("", "---"):
            documented = False
        else:
            assert _DECL.match(stripped), f"{relpath}:{number}: not a declaration: {line!r}"
            assert documented or "#" in stripped, \
                f"{relpath}:{number}: {stripped!r} has no comment above it"


@pytest.mark.parametrize("relpath", _interface_files())
def test_installed_definitions_match_sources(relpath):
    """The venv holds interfaces built from this checkout (``make setup`` rebuilds)."""
    with open(os.path.join(MSG_DEFS, relpath), encoding="utf-8") as f:
        source = f.read()
    installed = os.path.join(SHARE, relpath)
    assert os.path.isfile(installed), f"{installed} missing: run make setup"
    with open(installed, encoding="utf-8") as f:
        assert f.read() == source, f"{relpath} changed since the last build: run make setup"


def test_package_xml_is_valid_for_catkin_pkg():
    from catkin_pkg.package import parse_package

    pkg = parse_package(os.path.join(MSG_DEFS, "package.xml"))  # validates strictly
    assert pkg.name == "deepprompt_msgs"
    assert pkg.get_build_type() == "ament_cmake"
    assert "rosidl_interface_packages" in [g.name for g in pkg.member_of_groups]
    deps = {d.name for d in pkg.build_depends} & {d.name for d in pkg.exec_depends}
    assert {"sensor_msgs", "geometry_msgs", "action_msgs"} <= deps
