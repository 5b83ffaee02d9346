"""deepprompt_ros.server (config, primitives_file, images, service) and the ROS-free control loop
(deepprompt_ros.execution: plan, stream_loop): parameters, primitive loading, request validation
with result codes, conditioning / refinement / blending / sampling, execution planning, and the
command stream (limits, splicing, cancel, stale state).

Models are small networks with fixed random weights saved as real checkpoints (no training:
fast); the robot is the Gen3 lite (limits from its URDF through pinocchio)."""
import dataclasses
import pathlib
import time

import numpy as np
import pytest
import torch
import yaml

from deepprompt_ros.common.params import ConfigError, markdown_table
from deepprompt_ros.common.results import Code, RequestError
from deepprompt_ros.execution.brake_tail import BrakeTail, trajectory_points
from deepprompt_ros.execution.controller import ExecutionController, ExecutionGoal, MeasuredState, Stage
from deepprompt_ros.execution.limits import check_limits
from deepprompt_ros.execution.plan import ExecutionReference
from deepprompt_ros.model.checkpoint import Normalization, save_checkpoint
from deepprompt_ros.model.network import DeepProMPNet, ModelConfig
from deepprompt_ros.robots.spec import load_robot
from deepprompt_ros.server.config import PARAMETERS, ServerConfig, robot_limits
from deepprompt_ros.server.images import decode_image
from deepprompt_ros.server.primitives_file import PrimitiveEntry, load_primitive, load_primitives, read_primitives_file
from deepprompt_ros.server.requests import (BlendRequest, ConditionRequest, ContextIn, ExecuteRequest, ImageIn,
                                            SampleRequest, ViaPointIn)
from deepprompt_ros.server.service import PrimitiveServerCore

REPO = pathlib.Path(__file__).resolve().parent.parent
SPEC = load_robot("gen3_lite")
NAMES = SPEC.joint_names
DT = 1e-3


def save_model(path, joint_names=NAMES, image_shape=None, seed=0, y_std=0.05, y_mean=None, phase_type="linear"):
    """Random encoders; a decoder whose ReLUs are all active (large positive biases), so that
    μ_y(z, x) = M z + N φ(x) + c is affine in z and smooth in x: refinement onto one via-point
    (6 equations, latent 8) has an exact solution, two far-apart ones generally do not."""
    torch.manual_seed(seed)
    d = len(joint_names)
    cfg = ModelConfig(n_joints=d, phase_type=phase_type, latent_dim=8, hidden=32, context_dims=(("object", 3),),
                      image_shape=image_shape, phase_harmonics=1)
    net = DeepProMPNet(cfg)
    with torch.no_grad():
        lin = [m for m in net.decoder if isinstance(m, torch.nn.Linear)]
        for m in lin[:2]:
            m.weight.mul_(0.5)
            m.bias.fill_(20.0)
        lin[0].weight[:, cfg.latent_dim:] *= 150.0  # phase dependence: a motion of a few tenths of a rad
        lin[0].weight[:, :cfg.latent_dim] *= 5.0
        lin[2].weight.mul_(2.0)
        lin[2].bias.copy_(-(lin[2].weight @ (lin[1].weight @ torch.full((32,), 20.0) + 20.0)))  # mean ≈ 0
    mean = np.array(SPEC.home if y_mean is None else y_mean, dtype=float)[:d].copy()
    norm = Normalization(y_mean=mean, y_std=np.full(d, y_std), ctx_mean={"object": np.zeros(3)},
                         ctx_std={"object": np.ones(3)})
    save_checkpoint(path, net, norm, joint_names)
    return pathlib.Path(path)


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("models")
    return {
        "reach": save_model(tmp / "reach.safetensors"),
        "camera": save_model(tmp / "camera.safetensors", image_shape=(8, 8), seed=1),
        "permuted": save_model(tmp / "permuted.safetensors", joint_names=NAMES[::-1], seed=2,
                               y_mean=SPEC.home[::-1]),
        "one_joint": save_model(tmp / "one.safetensors", joint_names=("joint_1",), seed=3),
        "wave": save_model(tmp / "wave.safetensors", seed=4, phase_type="rhythmic"),
    }


def make_core(models, config=None, names=("reach", "camera", "permuted", "wave")):
    config = config or ServerConfig()
    prims = {n: load_primitive(PrimitiveEntry(n, str(models[n])), NAMES, pathlib.Path) for n in names}
    return PrimitiveServerCore(prims, config, robot_limits(SPEC, config))


@pytest.fixture(scope="module")
def core(models):
    return make_core(models)


def via(phase, positions, mask=(), use_weight=False, weight=1.0):
    return ViaPointIn(phase, np.asarray(positions, dtype=float), np.asarray(mask, dtype=bool), use_weight, weight)


def code_of(fn, *args):
    with pytest.raises(RequestError) as info:
        fn(*args)
    return info.value.code, info.value.message


# ================================================================================================
# parameters
# ================================================================================================
def test_config_yaml_holds_exactly_the_declared_defaults():
    raw = yaml.safe_load((REPO / "config" / "primitive_server.yaml").read_text())
    values = raw["primitive_server"]["ros__parameters"]
    assert set(values) == {p.name for p in PARAMETERS}
    assert ServerConfig.from_mapping(values) == ServerConfig()


def test_every_parameter_is_documented_with_type_default_and_range():
    md = markdown_table(PARAMETERS)
    for p in PARAMETERS:
        assert f"`{p.name}`" in md and p.description
        assert p.type in ("bool", "int", "double", "string")
        if p.type in ("int", "double"):
            assert p.min is not None and p.max is not None and p.min <= p.default <= p.max, p.name
    assert ServerConfig().control_rate_hz == 0.0  # 0 = the robot's rate (1 kHz for the Gen3 lite)


def test_invalid_parameters_are_all_reported_with_what_is_expected():
    with pytest.raises(ConfigError) as info:
        ServerConfig.from_mapping({"max_handles": 0, "stale_timeout": "fast", "loop_mode": "spin",
                                   "velocity_scale": float("nan"), "bogus": 1})
    msg = str(info.value)
    assert "max_handles = 0: expected a value in [1, 100000]" in msg
    assert "stale_timeout = 'fast': expected a number" in msg
    assert "loop_mode = 'spin': expected one of 'thread', 'timer'" in msg
    assert "velocity_scale = nan: expected finite numbers" in msg
    assert "unknown parameter 'bogus'" in msg
    # ints are accepted for doubles (YAML writes 1000 for 1000.0)
    assert ServerConfig.from_mapping({"control_rate_hz": 500}).control_rate_hz == 500.0


# ================================================================================================
# primitives file and loading
# ================================================================================================
def test_primitives_file_keeps_valid_entries_and_explains_each_refusal(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text(yaml.safe_dump({"primitives": [
        {"name": "reach", "model": "a.safetensors", "default_duration": 4.0},
        {"name": "reach", "model": "b.safetensors"},
        {"name": "9bad", "model": "c.safetensors"},
        {"name": "extra", "model": "d.safetensors", "speed": 2},
        {"name": "nomodel"},
        {"name": "slow", "model": "e.safetensors", "default_duration": -1},
        "just a string"]}))
    entries, errors = read_primitives_file(f)
    assert entries == [PrimitiveEntry("reach", "a.safetensors", "", 4.0)]
    text = "\n".join(errors)
    assert len(errors) == 6
    for part in ("appears twice", "name '9bad' is invalid", "unknown keys ['speed']", "model must be",
                 "default_duration -1", "must be a mapping"):
        assert part in text
    with pytest.raises(ConfigError, match="does not exist"):
        read_primitives_file(tmp_path / "missing.yaml")
    (tmp_path / "bad.yaml").write_text("primitives: 3\n")
    with pytest.raises(ConfigError, match="list 'primitives"):
        read_primitives_file(tmp_path / "bad.yaml")


def test_shipped_primitives_file_parses():
    entries, errors = read_primitives_file(REPO / "config" / "primitives.yaml")
    assert not errors
    assert {e.name for e in entries} >= {"reach"}


def test_models_with_other_joints_or_missing_files_are_refused_the_rest_load(models):
    entries = [PrimitiveEntry("reach", str(models["reach"])), PrimitiveEntry("sine", str(models["one_joint"])),
               PrimitiveEntry("gone", "/nonexistent/x.safetensors")]
    prims, errors = load_primitives(entries, NAMES, pathlib.Path)
    assert list(prims) == ["reach"]
    assert len(errors) == 2
    assert "primitive 'sine' refused" in errors[0] and "has 1 joints [joint_1] but the robot has 6 joints" in errors[0]
    assert "missing: joint_2, joint_3" in errors[0]
    assert "primitive 'gone' refused" in errors[1] and "does not exist" in errors[1]


# ================================================================================================
# Condition
# ================================================================================================
def test_condition_reports_the_via_point_error_and_refine_meets_it(core):
    prior = core.condition(ConditionRequest("reach", preview_points=101))
    assert prior.code == Code.SUCCESS and prior.refine_max_error == 0.0
    target = prior.preview.mean[50] + np.array([0.02, -0.02, 0.01, 0.0, 0.015, -0.01])
    plain = core.condition(ConditionRequest("reach", [via(0.5, target)], preview_points=101))
    refined = core.condition(ConditionRequest("reach", [via(0.5, target)], refine=True, preview_points=101))
    assert plain.code == refined.code == Code.SUCCESS
    err_plain = np.abs(plain.preview.mean[50] - target).max()
    assert err_plain == pytest.approx(plain.refine_max_error, abs=1e-12)  # what the executed mean misses by
    assert plain.reachable == (err_plain <= 1e-6) and plain.refine_iterations == 0
    assert refined.reachable and refined.refine_iterations >= 1
    assert np.abs(refined.preview.mean[50] - target).max() <= 1e-6
    assert refined.refine_max_error <= 1e-6
    assert refined.preview.std.shape == (101, 6) and np.all(refined.preview.std > 0)
    assert "refined in" in refined.message
    assert refined.handle != plain.handle and refined.expires_in == ServerConfig().handle_ttl


def test_a_distribution_whose_spread_cannot_be_computed_is_refused_and_not_stored(models, monkeypatch):
    """The preview's standard deviation is computed before the handle is stored: a latent whose covariance
    cannot be factored (the model's ValueError) is refused INVALID_REQUEST with the model's reason, and the
    store holds nothing more; the next request is served."""
    core = make_core(models, names=("reach",))
    model = core.primitives["reach"].model
    reason = "the covariance of the exact conditioning of the linear latent block cannot be factored"

    def unfactorable(latent, x):
        raise ValueError(reason)

    before = len(core.handles)
    with monkeypatch.context() as m:
        m.setattr(model, "linearized_std", unfactorable)
        code, message = code_of(core.condition, ConditionRequest("reach", preview_points=20))
    assert code == Code.INVALID_REQUEST and reason in message
    assert len(core.handles) == before
    ok = core.condition(ConditionRequest("reach", preview_points=20))
    assert ok.code == Code.SUCCESS and len(core.handles) == before + 1


def test_refine_with_joint_mask_meets_only_the_constrained_joints(core):
    prior = core.condition(ConditionRequest("reach", preview_points=11))
    target = prior.preview.mean[5] + 0.03
    mask = [True, False, True, False, False, False]
    r = core.condition(ConditionRequest("reach", [via(0.5, target, mask)], refine=True, preview_points=11))
    assert r.code == Code.SUCCESS
    err = np.abs(r.preview.mean[5] - target)
    assert err[[0, 2]].max() <= 1e-6
    assert err[[1, 3, 4, 5]].min() > 1e-3  # not pulled onto the unconstrained values


def test_unreachable_refinement_returns_best_fit_handle_and_code(core):
    r = core.condition(ConditionRequest("reach", [via(0.3, SPEC.home + 2.0), via(0.31, SPEC.home - 2.0)],
                                        refine=True, refine_max_iterations=30))
    assert r.code == Code.REFINEMENT_UNREACHABLE
    assert r.handle and not r.reachable and r.refine_max_error > 0.1
    assert "cannot all be met" in r.message
    assert core.handles.get(r.handle).primitive == "reach"


def test_weight_zero_removes_a_via_point_exactly(core):
    a = core.condition(ConditionRequest("reach", [via(0.2, SPEC.home + 0.05)]))
    b = core.condition(ConditionRequest("reach", [via(0.2, SPEC.home + 0.05), via(0.8, SPEC.home - 0.5, (),
                                                                                    True, 0.0)]))
    la, lb = core.handles.get(a.handle).latent, core.handles.get(b.handle).latent
    np.testing.assert_allclose(la.mean, lb.mean, rtol=0, atol=1e-14)
    np.testing.assert_allclose(la.var, lb.var, rtol=0, atol=1e-14)


def test_contexts_and_images_condition_the_latent(core):
    r0 = core.condition(ConditionRequest("reach"))
    r1 = core.condition(ConditionRequest("reach", contexts=[ContextIn("object", np.array([0.3, 0.1, 0.2]))]))
    assert r1.code == Code.SUCCESS
    assert np.abs(r1.preview.mean - r0.preview.mean).max() > 1e-6
    img = ImageIn(8, 8, "rgb8", 24, np.arange(192, dtype=np.uint8))
    bgr = ImageIn(8, 8, "bgr8", 24, np.arange(192, dtype=np.uint8).reshape(8, 8, 3)[:, :, ::-1].reshape(-1).copy())
    r2 = core.condition(ConditionRequest("camera", contexts=[ContextIn("image", np.zeros(0), (img,))]))
    r3 = core.condition(ConditionRequest("camera", contexts=[ContextIn("image", np.zeros(0), (bgr,))]))
    assert r2.code == r3.code == Code.SUCCESS
    np.testing.assert_allclose(r2.preview.mean, r3.preview.mean, atol=1e-12)  # same pixels, other encoding


def test_decode_image_handles_row_padding_and_alpha():
    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    padded = np.zeros((2, 12), dtype=np.uint8)
    padded[:, :9] = rgb.reshape(2, 9)
    np.testing.assert_array_equal(decode_image(ImageIn(2, 3, "rgb8", 12, padded.reshape(-1)), (2, 3)), rgb)
    bgra = np.concatenate([rgb[:, :, ::-1], np.full((2, 3, 1), 255, np.uint8)], axis=2)
    np.testing.assert_array_equal(decode_image(ImageIn(2, 3, "bgra8", 12, bgra.reshape(-1)), (2, 3)), rgb)


MALFORMED = [
    # (description, request kwargs, code, part of the message)
    ("unknown primitive", dict(primitive="nope"), Code.UNKNOWN_PRIMITIVE, "loaded primitives: camera, permuted, reach"),
    ("phase > 1", dict(via_points=[via(1.5, SPEC.home)]), Code.INVALID_VIA_POINT, "phase 1.5 is outside [0, 1]"),
    ("phase NaN", dict(via_points=[via(float("nan"), SPEC.home)]), Code.INVALID_VIA_POINT, "phase nan"),
    ("joint count", dict(via_points=[via(0.5, SPEC.home[:5])]), Code.INVALID_VIA_POINT,
     "via-point 0 has 5 joint values; primitive 'reach' has 6 joints: joint_1, joint_2"),
    ("NaN position", dict(via_points=[via(0.5, np.r_[SPEC.home[:3], np.nan, SPEC.home[4:]])]),
     Code.INVALID_VIA_POINT, "joint 'joint_4' is nan"),
    ("mask length", dict(via_points=[via(0.5, SPEC.home, [True] * 4)]), Code.INVALID_VIA_POINT,
     "joint_mask has 4 entries; expected 0 (all joints) or 6"),
    ("empty mask", dict(via_points=[via(0.5, SPEC.home, [False] * 6)]), Code.INVALID_VIA_POINT, "selects no joint"),
    ("negative weight", dict(via_points=[via(0.5, SPEC.home, (), True, -1.0)]), Code.INVALID_VIA_POINT,
     "weight -1.0 is invalid"),
    ("too many via-points", dict(via_points=[via(0.5, SPEC.home)] * 1001), Code.INVALID_REQUEST,
     "1001 via-points; the server accepts at most 1000 (parameter max_via_points)"),
    ("absurd preview", dict(preview_points=10_000_000), Code.INVALID_REQUEST, "preview_points = 10000000"),
    ("one preview point", dict(preview_points=1), Code.INVALID_REQUEST, "expected 0 (server default 100) or 2..10000"),
    ("unknown context", dict(contexts=[ContextIn("color", np.ones(3))]), Code.INVALID_CONTEXT,
     "unknown modality; primitive 'reach' accepts 'object'"),
    ("context size", dict(contexts=[ContextIn("object", np.ones(2))]), Code.INVALID_CONTEXT,
     "has 2 values; expected exactly 3"),
    ("context NaN", dict(contexts=[ContextIn("object", np.array([0, np.nan, 0]))]), Code.INVALID_CONTEXT, "NaN"),
    ("duplicate context", dict(contexts=[ContextIn("object", np.ones(3))] * 2), Code.INVALID_CONTEXT,
     "modality given twice"),
    ("context weight", dict(contexts=[ContextIn("object", np.ones(3), (), True, float("inf"))]),
     Code.INVALID_CONTEXT, "weight inf is invalid"),
    ("image to a primitive without images", dict(contexts=[ContextIn(
        "image", np.zeros(0), (ImageIn(8, 8, "rgb8", 24, np.zeros(192, np.uint8)),))]),
     Code.INVALID_IMAGE, "accepts no images"),
    ("refine tolerance NaN", dict(refine=True, refine_tolerance=float("nan")), Code.INVALID_REQUEST,
     "refine_tolerance nan is invalid"),
    ("refine budget", dict(refine=True, refine_max_iterations=10**6), Code.INVALID_REQUEST, "too large"),
    # finite but huge values overflow into a NaN latent: refused, never a SUCCESS with a NaN preview
    ("huge position", dict(via_points=[via(0.5, np.r_[SPEC.home[:5], 1e308])]), Code.INVALID_REQUEST,
     "NaN or inf (an overflow): largest |via-point position| 1e+308 rad"),
    ("huge context", dict(contexts=[ContextIn("object", np.array([1e308, 0.0, 0.0]))]), Code.INVALID_REQUEST,
     "largest |context value| 1e+308"),
]


@pytest.mark.parametrize("what,kwargs,code,part", MALFORMED, ids=[m[0] for m in MALFORMED])
def test_malformed_condition_requests_get_the_named_code_and_message(core, what, kwargs, code, part):
    req = ConditionRequest(**{"primitive": "reach", **kwargs})
    got, msg = code_of(core.condition, req)
    assert got == code, msg
    assert part in msg, msg


IMAGE_CASES = [
    ("wrong size", ImageIn(16, 8, "rgb8", 24, np.zeros(384, np.uint8)), "16x8 (height x width); the primitive expects 8x8"),
    ("wrong encoding", ImageIn(8, 8, "mono8", 8, np.zeros(64, np.uint8)), "encoding 'mono8'; expected one of"),
    ("truncated", ImageIn(8, 8, "rgb8", 24, np.zeros(100, np.uint8)), "100 bytes of data; expected step x height"),
    ("short step", ImageIn(8, 8, "rgb8", 10, np.zeros(80, np.uint8)), "step 10 bytes per row"),
]


@pytest.mark.parametrize("what,image,part", IMAGE_CASES, ids=[c[0] for c in IMAGE_CASES])
def test_bad_images_get_invalid_image(core, what, image, part):
    got, msg = code_of(core.condition, ConditionRequest("camera", contexts=[ContextIn("image", np.zeros(0),
                                                                                           (image,))]))
    assert got == Code.INVALID_IMAGE and part in msg, msg


def test_full_store_without_eviction_gives_handle_limit(models):
    core = make_core(models, dataclasses.replace(ServerConfig(), max_handles=2, evict_when_full=False), ("reach",))
    core.condition(ConditionRequest("reach"))
    core.condition(ConditionRequest("reach"))
    got, msg = code_of(core.condition, ConditionRequest("reach"))
    assert got == Code.HANDLE_LIMIT and "max_handles" in msg


# ================================================================================================
# Blend and Sample
# ================================================================================================
def test_blend_hands_over_from_a_to_b(core):
    a = core.condition(ConditionRequest("reach", [via(0.0, SPEC.home + 0.05)], preview_points=21))
    b = core.condition(ConditionRequest("reach", [via(1.0, SPEC.home - 0.05)], preview_points=21))
    r = core.blend(BlendRequest(a.handle, b.handle, preview_points=21))
    np.testing.assert_allclose(r.preview.mean[0], a.preview.mean[0], atol=1e-12)
    np.testing.assert_allclose(r.preview.mean[-1], b.preview.mean[-1], atol=1e-12)
    mid = r.preview.mean[10]
    assert not np.allclose(mid, a.preview.mean[10]) and not np.allclose(mid, b.preview.mean[10])
    # sample=true: one ε kept with the handle, so the executed grid is reproducible
    s1 = core.blend(BlendRequest(a.handle, b.handle, sample=True, seed=7))
    s2 = core.blend(BlendRequest(a.handle, b.handle, sample=True, seed=7))
    np.testing.assert_allclose(s1.preview.mean, s2.preview.mean)
    assert np.abs(s1.preview.mean - core.blend(BlendRequest(a.handle, b.handle)).preview.mean).max() > 1e-6


def test_blend_refusals(core):
    a = core.condition(ConditionRequest("reach")).handle
    w = core.condition(ConditionRequest("permuted")).handle
    assert code_of(core.blend, BlendRequest(a, "nope"))[0] == Code.UNKNOWN_HANDLE
    got, msg = code_of(core.blend, BlendRequest(a, w))
    assert got == Code.INVALID_REQUEST and "same primitive" in msg
    got, msg = code_of(core.blend, BlendRequest(a, a, [0.0, 0.5], [1.0]))
    assert got == Code.INVALID_REQUEST and "one weight per phase" in msg
    got, msg = code_of(core.blend, BlendRequest(a, a, [0.5, 0.2], [1.0, 0.0]))
    assert got == Code.INVALID_REQUEST and "strictly increasing" in msg


def test_sample_shapes_seed_and_bounds(core):
    h = core.condition(ConditionRequest("reach", [via(0.5, SPEC.home + 0.02)])).handle
    s1 = core.sample(SampleRequest(handle=h, n_samples=5, n_points=30, seed=3))
    s2 = core.sample(SampleRequest(handle=h, n_samples=5, n_points=30, seed=3))
    assert s1.samples.shape == (5, 30, 6)
    np.testing.assert_array_equal(s1.samples, s2.samples)
    prior = core.sample(SampleRequest(primitive="reach"))
    assert prior.samples.shape == (1, 100, 6)
    assert code_of(core.sample, SampleRequest())[0] == Code.INVALID_REQUEST
    assert code_of(core.sample, SampleRequest(primitive="nope"))[0] == Code.UNKNOWN_PRIMITIVE
    assert code_of(core.sample, SampleRequest(handle="nope"))[0] == Code.UNKNOWN_HANDLE
    got, msg = code_of(core.sample, SampleRequest(handle=h, n_samples=10**6))
    assert got == Code.INVALID_REQUEST and "max_samples" in msg
    got, msg = code_of(core.sample, SampleRequest(handle=h, n_samples=1000, n_points=21))
    assert got == Code.INVALID_REQUEST and "max_sample_points" in msg and "1000 x 21 = 21000" in msg
    assert core.sample(SampleRequest(handle=h, n_samples=1000, n_points=20)).samples.shape == (1000, 20, 6)


def test_list_describes_joints_limits_contexts_and_images(core):
    desc = {d.name: d for d in core.describe()}
    assert list(desc) == ["camera", "permuted", "reach", "wave"]
    r, c, p = desc["reach"], desc["camera"], desc["permuted"]
    assert r.joint_names == NAMES and r.context_modalities == ("object",) and r.context_dims == (3,)
    np.testing.assert_array_equal(r.position_lower, SPEC.lower)
    assert not r.accepts_images and (c.accepts_images, c.image_height, c.image_width, c.image_encoding) == (
        True, 8, 8, "rgb8")
    assert p.joint_names == NAMES[::-1]
    np.testing.assert_array_equal(p.position_upper, SPEC.upper[::-1])  # in the primitive's joint order
    assert desc["wave"].phase_type == "rhythmic"


# ================================================================================================
# execution planning
# ================================================================================================
def test_plan_grid_is_the_executed_mean_in_robot_joint_order(core):
    r = core.condition(ConditionRequest("permuted", preview_points=11))
    plan = core.plan_execution(ExecuteRequest(r.handle, duration=4.0))
    x = np.linspace(0, 1, 11)
    np.testing.assert_allclose(plan.reference.positions(x), r.preview.mean[:, ::-1], atol=1e-7)
    assert plan.duration == 4.0 and plan.phase_rate == 0.25 and not plan.rhythmic
    assert core.plan_execution(ExecuteRequest(r.handle, phase_rate=0.5)).duration == 2.0
    assert core.plan_execution(ExecuteRequest(r.handle)).duration == ServerConfig().default_duration


def test_execution_reference_derivatives_follow_the_chain_rule():
    x = np.linspace(0, 1, 4001)
    y = np.stack([np.sin(2 * np.pi * x), x ** 3], axis=1)
    ref = ExecutionReference(y, periodic=False, h=0.002)
    q, qd, qdd = ref.state(0.3, 0.5, 0.1)
    dy = np.array([2 * np.pi * np.cos(0.6 * np.pi), 3 * 0.09])
    ddy = np.array([-(2 * np.pi) ** 2 * np.sin(0.6 * np.pi), 6 * 0.3])
    np.testing.assert_allclose(q, [np.sin(0.6 * np.pi), 0.027], atol=1e-6)
    np.testing.assert_allclose(qd, dy * 0.5, rtol=1e-4)
    np.testing.assert_allclose(qdd, ddy * 0.25 + dy * 0.1, rtol=1e-3)
    per = ExecutionReference(y[:, :1], periodic=True, h=0.002)
    np.testing.assert_allclose(per.state(0.999999, 1.0, 0.0)[0], per.state(0.0, 1.0, 0.0)[0], atol=1e-4)
    np.testing.assert_allclose(per.state(0.0, 1.0, 0.0)[1], [2 * np.pi], rtol=1e-4)


def test_execute_requests_are_validated(core):
    h = core.condition(ConditionRequest("reach")).handle
    cases = [(ExecuteRequest("nope"), Code.UNKNOWN_HANDLE, "unknown handle"),
             (ExecuteRequest(h, duration=2.0, phase_rate=0.5), Code.INVALID_REQUEST, "set at most one"),
             (ExecuteRequest(h, duration=float("nan")), Code.INVALID_REQUEST, "duration nan is invalid"),
             (ExecuteRequest(h, phase_rate=-1.0), Code.INVALID_REQUEST, "phase_rate -1.0 is invalid"),
             (ExecuteRequest(h, phase_rate=1e-9), Code.INVALID_REQUEST, "out of range"),
             (ExecuteRequest(h, duration=0.05), Code.LIMIT_VIOLATION, "velocity limit is 0.5 rad/s: use a duration >=")]
    for req, code, part in cases:
        got, msg = code_of(core.plan_execution, req)
        assert got == code and part in msg, msg
    w = core.condition(ConditionRequest("wave")).handle
    got, msg = code_of(core.plan_execution, ExecuteRequest(w, duration=30.0, cycles=10**7))
    assert got == Code.INVALID_REQUEST and "max_cycles" in msg
    assert core.plan_execution(ExecuteRequest(w, duration=30.0, cycles=3)).cycles == 3


def test_a_handle_that_decodes_to_nan_is_refused_before_the_control_loop(core):
    from deepprompt_ros.primitive.latent import LatentGaussian
    from deepprompt_ros.server.handles import ConditionedLatent

    h, _ = core.handles.put(ConditionedLatent("reach", LatentGaussian(np.full(8, np.nan), np.ones(8))), "reach")
    got, msg = code_of(core.plan_execution, ExecuteRequest(h, duration=2.0))
    assert got == Code.INVALID_REQUEST and f"handle '{h}' decodes to a trajectory with NaN or inf" in msg, msg


def test_trajectory_outside_the_position_limits_is_refused(models, tmp_path):
    mean = SPEC.upper - 0.01  # the decoder's output sits around the upper limits
    path = save_model(tmp_path / "edge.safetensors", y_mean=mean, y_std=0.2)
    prims = {"edge": load_primitive(PrimitiveEntry("edge", str(path)), NAMES, pathlib.Path)}
    core = PrimitiveServerCore(prims, ServerConfig(), robot_limits(SPEC, ServerConfig()))
    h = core.condition(ConditionRequest("edge")).handle
    got, msg = code_of(core.plan_execution, ExecuteRequest(h, duration=30.0))
    assert got == Code.LIMIT_VIOLATION and "leaves the position limits" in msg and "upper limit" in msg


# ================================================================================================
# the command stream (ExecutionController, as the control thread runs it)
# ================================================================================================
CFG = ServerConfig()
LIMITS = robot_limits(SPEC, CFG)


class Run:
    """Drive an ExecutionController tick by tick with a simulated perfect robot."""

    def __init__(self, start_q):
        self.ctl = ExecutionController(LIMITS, DT, CFG)
        self.t = time.monotonic()
        self.measured = MeasuredState(np.array(start_q, float), None, self.t)
        self.q, self.qd, self.qdd = [np.array(start_q, float)], [np.zeros(6)], [np.zeros(6)]
        self.stale = False

    def tick(self):
        s = self.ctl.pop_due(self.measured, self.t)
        if s is not None:
            self.q.append(s.q), self.qd.append(s.qd), self.qdd.append(s.qdd)
            if not self.stale:  # the robot reports the command it was given
                self.measured = MeasuredState(s.q.copy(), s.qd.copy(), self.t)
        self.ctl.check_faults(self.measured, self.t)
        self.ctl.compute_next()
        self.t += DT
        return s

    def until(self, pred, max_ticks=40000):
        for _ in range(max_ticks):
            self.tick()
            if pred():
                return
        raise AssertionError("condition not reached")

    def report(self):
        return check_limits(np.array(self.q), np.array(self.qd), np.array(self.qdd), DT, LIMITS)


def plan_for(core, target_offset=0.03, duration=3.0, seed_phase=0.5):
    prior = core.condition(ConditionRequest("reach", preview_points=11))
    r = core.condition(ConditionRequest("reach", [via(seed_phase, prior.preview.mean[5] + target_offset)],
                                        refine=True))
    return core.plan_execution(ExecuteRequest(r.handle, duration=duration))


def test_goal_runs_from_measured_state_to_rest_at_the_end_within_limits(core):
    plan = plan_for(core)
    start = plan.reference.positions([0.0])[0] + 0.05  # off the start: approach first
    run = Run(start)
    goal = ExecutionGoal(plan)
    run.ctl.start_goal(goal, run.measured, run.t)
    stages = set()
    run.until(lambda: (stages.add(goal.stage), goal.done.is_set())[1])
    assert Stage.APPROACH in stages and Stage.RUN in stages
    assert goal.outcome.code == Code.SUCCESS and goal.outcome.final_phase == 1.0
    np.testing.assert_allclose(run.q[1], start, atol=1e-12)  # starts where the robot is
    np.testing.assert_allclose(run.q[-1], plan.reference.positions([1.0])[0], atol=1e-6)
    assert np.all(run.qd[-1] == 0) and np.all(run.qdd[-1] == 0)
    rep = run.report()
    assert rep.ok(), rep
    # on the primitive while running: the stream follows the grid closely
    run.until(lambda: run.ctl.idle, 100)
    assert run.ctl.idle


def test_preempting_goal_splices_without_a_jump(core):
    a, b = plan_for(core, 0.03, 3.0), plan_for(core, -0.03, 2.5, 0.4)
    run = Run(a.reference.positions([0.0])[0])
    ga, gb = ExecutionGoal(a), ExecutionGoal(b)
    run.ctl.start_goal(ga, run.measured, run.t)
    run.until(lambda: ga.progress.phase > 0.4)
    run.ctl.start_goal(gb, run.measured, run.t)
    run.until(lambda: gb.done.is_set())
    assert ga.outcome.code == Code.PREEMPTED and gb.outcome.code == Code.SUCCESS
    rep = run.report()  # velocity/acceleration/jerk limits hold across the splice
    assert rep.ok(), rep
    np.testing.assert_allclose(run.q[-1], b.reference.positions([1.0])[0], atol=1e-6)


def test_cancel_brakes_to_rest_within_limits(core):
    plan = plan_for(core, 0.03, 3.0)
    run = Run(plan.reference.positions([0.0])[0])
    goal = ExecutionGoal(plan)
    run.ctl.start_goal(goal, run.measured, run.t)
    run.until(lambda: goal.progress.phase > 0.5)
    speed = np.abs(run.qd[-1]).max()
    assert speed > 0.01
    run.ctl.cancel(goal)
    n0 = len(run.q)
    run.until(lambda: goal.done.is_set())
    assert goal.outcome.code == Code.CANCELED and 0.5 < goal.outcome.final_phase < 1.0
    assert np.all(run.qd[-1] == 0) and np.all(run.qdd[-1] == 0)
    assert (len(run.q) - n0) * DT < 3.0  # braking time (lookahead + brake)
    assert run.report().ok()


def test_set_rate_while_moving_keeps_the_stream_continuous_and_zero_holds(core):
    plan = plan_for(core, 0.03, 3.0)
    run = Run(plan.reference.positions([0.0])[0])
    goal = ExecutionGoal(plan)
    run.ctl.start_goal(goal, run.measured, run.t)
    run.until(lambda: goal.progress.phase > 0.3)
    run.ctl.set_rate(goal, 0.0)
    for _ in range(1500):
        run.tick()
    held = goal.progress.phase
    for _ in range(300):
        run.tick()
    assert goal.progress.phase == pytest.approx(held, abs=1e-12)
    assert np.abs(run.qd[-1]).max() < 1e-4  # settled on the held reference
    run.ctl.set_rate(goal, 0.5)
    run.until(lambda: goal.done.is_set())
    assert goal.outcome.code == Code.SUCCESS
    assert run.report().ok()


def test_stale_joint_states_stop_the_stream_with_robot_state_stale(core):
    plan = plan_for(core, 0.03, 3.0)
    run = Run(plan.reference.positions([0.0])[0])
    goal = ExecutionGoal(plan)
    run.ctl.start_goal(goal, run.measured, run.t)
    run.until(lambda: goal.progress.phase > 0.3)
    run.stale = True
    run.until(lambda: goal.done.is_set(), 5000)
    assert goal.outcome.code == Code.ROBOT_STATE_STALE and "stale_timeout" in goal.outcome.message
    assert np.all(run.qd[-1] == 0)
    assert run.report().ok()


def test_tracking_error_bound_aborts_with_limit_violation(core):
    cfg = dataclasses.replace(CFG, max_tracking_error=0.01)
    plan = plan_for(core, 0.03, 3.0)
    ctl = ExecutionController(LIMITS, DT, cfg)
    q0 = plan.reference.positions([0.0])[0]
    goal = ExecutionGoal(plan)
    t = 0.0
    ctl.start_goal(goal, MeasuredState(q0, None, t), t)
    for _ in range(20000):  # the "robot" never moves
        ctl.pop_due(MeasuredState(q0, None, t), t)
        ctl.check_faults(MeasuredState(q0, None, t), t)
        ctl.compute_next()
        t += DT
        if goal.done.is_set():
            break
    assert goal.outcome.code == Code.LIMIT_VIOLATION and "tracking error" in goal.outcome.message


def test_start_outside_limits_is_refused(core):
    plan = plan_for(core)
    ctl = ExecutionController(LIMITS, DT, CFG)
    goal = ExecutionGoal(plan)
    q = SPEC.home.copy()
    q[1] = SPEC.upper[1] + 0.1
    ctl.start_goal(goal, MeasuredState(q, None, 0.0), 0.0)
    assert goal.outcome.code == Code.LIMIT_VIOLATION and "joint_2" in goal.outcome.message


def test_trajectory_snapshots_and_brake_tail_make_valid_controller_messages(core):
    plan = plan_for(core, 0.03, 3.0)
    run = Run(plan.reference.positions([0.0])[0])
    goal = ExecutionGoal(plan)
    run.ctl.start_goal(goal, run.measured, run.t)
    run.until(lambda: goal.progress.phase > 0.5)
    snap = run.ctl.snapshot(100.0, 3)
    assert snap.times.shape == (3,) and np.all(np.diff(snap.times) > 0) and snap.times[0] > 0
    assert snap.t0 == pytest.approx(100.0 - DT)
    np.testing.assert_allclose(snap.q[-1], run.ctl.buffer[-1].q)  # the last point: the newest sample
    tail = BrakeTail(LIMITS)
    tt, tq, tv, ta = tail(snap.q[-1], snap.qd[-1], snap.qdd[-1])
    assert tt.size == 3 and np.all(np.diff(tt) > 0)
    assert np.all(tv[-1] == 0) and np.all(ta[-1] == 0)
    assert np.all(tq >= LIMITS.lower) and np.all(tq <= LIMITS.upper)
    assert np.all(np.abs(tv) <= LIMITS.max_velocity * (1 + 1e-9))
    assert tail(SPEC.home, np.zeros(6), np.zeros(6))[0].size == 0  # at rest: nothing to add
    times, q, qd, qdd = trajectory_points(snap, tail)
    assert times.shape == (6,) and np.all(np.diff(times) > 0) and np.all(qd[-1] == 0) and np.all(qdd[-1] == 0)
    nearly = snap._replace(qd=snap.qd * 1e-12, qdd=snap.qdd * 1e-12)  # at rest up to rounding: zeroed
    times, q, qd, qdd = trajectory_points(nearly, tail)
    assert times.shape == (3,) and np.all(qd[-1] == 0) and np.all(qdd[-1] == 0)


def test_reverse_runs_the_primitive_backwards(core):
    r = core.condition(ConditionRequest("reach"))
    plan = core.plan_execution(ExecuteRequest(r.handle, duration=3.0, reverse=True))
    assert plan.start_phase == 1.0 and plan.end_phase == 0.0
    run = Run(plan.reference.positions([1.0])[0])
    goal = ExecutionGoal(plan)
    run.ctl.start_goal(goal, run.measured, run.t)
    phases = []
    run.until(lambda: (phases.append(goal.progress.phase), goal.done.is_set())[1])
    assert goal.outcome.code == Code.SUCCESS and goal.outcome.final_phase == 0.0
    assert np.all(np.diff(phases) <= 1e-12)  # the phase only decreases
    np.testing.assert_allclose(run.q[-1], plan.reference.positions([0.0])[0], atol=1e-6)
    assert run.report().ok()


def test_rhythmic_goal_runs_its_cycles_without_a_seam(tmp_path):
    path = save_model(tmp_path / "wave.safetensors", seed=4, phase_type="rhythmic", y_std=0.004)
    prims = {"wave": load_primitive(PrimitiveEntry("wave", str(path)), NAMES, pathlib.Path)}
    core = PrimitiveServerCore(prims, CFG, LIMITS)
    h = core.condition(ConditionRequest("wave")).handle
    plan = core.plan_execution(ExecuteRequest(h, duration=1.5, cycles=2))
    ref = plan.reference
    np.testing.assert_allclose(ref.positions([0.0]), ref.positions([1.0]), atol=1e-12)  # periodic
    run = Run(ref.positions([0.0])[0])
    goal = ExecutionGoal(plan)
    run.ctl.start_goal(goal, run.measured, run.t)
    cycles = set()
    run.until(lambda: (cycles.add(goal.progress.cycle), goal.done.is_set())[1])
    assert goal.outcome.code == Code.SUCCESS and goal.outcome.cycles_completed == 2
    assert {0, 1} <= cycles
    assert np.ptp(np.array(run.q), axis=0).max() > 0.01  # it moved
    assert run.report().ok()  # limits hold across the wrap x: 1 -> 0


def test_linearized_preview_std_matches_sampling_for_a_decoder_linear_in_z(models):
    lin = make_core(models, names=("reach",))
    mc = make_core(models, dataclasses.replace(ServerConfig(), preview_std_method="sampled",
                                               preview_std_samples=4000), ("reach",))
    req = ConditionRequest("reach", [via(0.3, SPEC.home + 0.01)], preview_points=26)
    a, b = lin.condition(req).preview.std, mc.condition(req).preview.std
    rel = np.abs(a - b) / b
    assert np.median(rel) < 0.03  # Monte-Carlo error of 4000 samples ~ 1 %
    assert rel.max() < 0.25  # where a sample leaves the linear region of a few ReLUs
