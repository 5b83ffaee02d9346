"""How long one request can hold up the server (no ROS): the service thread answers one request at a
time, so every request it accepts must end in bounded time.

* Refinement (``DeepProMP.refine`` / ``refine_exact``) stops at its ``time_budget`` with the best fit
  found, ``reachable=False``, ``out_of_time=True`` and a reason naming the budget, on a plain latent
  (Levenberg–Marquardt) and on a split latent (the exact re-conditioning of ``refine_split``, then
  LM); a budget that is not reached changes nothing.
* :class:`PrimitiveServerCore` with the shipped defaults (``ServerConfig()``): the largest request of
  each kind it accepts (Condition at max_via_points, max_images, max_preview_points and 10 000
  refinement iterations; Blend of max_blend_parts parts with max_via_points knots; Sample of
  max_sample_points points; an Execute plan of the largest blend; ListPrimitives) takes at most
  :data:`BOUND_S` of work; refinement adds at most refine_time_budget + :data:`REFINE_MARGIN_S`;
  one part or point more is refused with a message naming the parameter.

The timed requests run in a child process with one BLAS and one torch thread, as in primitive_server
(``OPENBLAS_NUM_THREADS=1``): work is the CPU time of its thread (``time.thread_time``), which other
processes on the shared machine do not inflate as they do the wall time; a time budget is wall time,
so a refinement is checked to run until its budget (wall) and to do no more than the budget and the
margin of work (CPU). ``python test/test_request_time_bounds.py DIR`` prints the child's figures.

Models: the shipped Gen3 lite reach model (128 hidden units), and, built here with random weights of
the same width, a split-latent model (k = 128, k_l = 120) and a model of 64x64 images.
"""
import json
import os
import pathlib
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from deepprompt_ros.common.results import Code, RequestError
from deepprompt_ros.model.checkpoint import Normalization, save_checkpoint
from deepprompt_ros.model.network import DeepProMPNet, ModelConfig
from deepprompt_ros.primitive.deep_promp import DeepProMP
from deepprompt_ros.primitive.linear_conditioning import refine_split
from deepprompt_ros.robots.spec import load_robot
from deepprompt_ros.server.config import ServerConfig, robot_limits
from deepprompt_ros.server.primitives_file import PrimitiveEntry, load_primitive
from deepprompt_ros.server.requests import (BlendRequest, ConditionRequest, ContextIn, ExecuteRequest, ImageIn,
                                            SampleRequest, ViaPointIn)
from deepprompt_ros.server.service import PrimitiveServerCore

REPO = pathlib.Path(__file__).resolve().parent.parent
#: a trained Gen3 lite reach primitive with a plain latent (latent_linear 0, latent 16, context 'object' (3)):
#: the plain-latent case beside the split model below
REACH = REPO / "test" / "data" / "gen3_lite_reach_plain.safetensors"
SPEC = load_robot("gen3_lite")
HOME = np.asarray(SPEC.home, dtype=np.float64)
#: the most work any accepted request without refinement may take (s of CPU): the shipped limits aim
#: at 1 s on the 2-core machine (measured: at most 0.13 s, a Sample of 1000 x 20 points; a Condition
#: of a split latent on 1000 via-points with a 10 000-point preview 0.10 s).
BOUND_S = 1.0
#: the work refinement may add beyond its time budget (s of CPU): about one iteration and the decoding
#: of its result (measured: 0.05-0.09 s of wall time beyond the budget at the shipped limits).
REFINE_MARGIN_S = 0.3
#: time_budget of the refinements timed at the DeepProMP level (s)
UNIT_BUDGET = 0.3


def far_via_points(n, seed=0, spread=0.3):
    """n via-points at distinct random phases, joints scattered around home: no latent meets them."""
    rng = np.random.default_rng(seed)
    return np.sort(rng.uniform(0.0, 1.0, n)), HOME + rng.normal(0.0, spread, (n, HOME.size))


def save_split_model(path):
    """6 Gen3 lite joints, k = 128 of which k_l = 120 linear (20 basis functions), 128 hidden units,
    context 'object' (3); random weights."""
    torch.manual_seed(0)
    net = DeepProMPNet(ModelConfig(n_joints=6, latent_dim=128, hidden=128, context_dims=(("object", 3),),
                                   decoder_basis=20, latent_linear=120))
    return save_checkpoint(path, net, Normalization(HOME, np.full(6, 0.1), {"object": np.zeros(3)},
                                                    {"object": np.ones(3)}), SPEC.joint_names)


def save_image_model(path):
    """6 Gen3 lite joints, 64x64 images, 128 hidden units; random weights."""
    torch.manual_seed(1)
    net = DeepProMPNet(ModelConfig(n_joints=6, latent_dim=16, hidden=128, image_shape=(64, 64)))
    return save_checkpoint(path, net, Normalization(HOME, np.full(6, 0.1)), SPEC.joint_names)


def model_files(tmp: pathlib.Path) -> dict:
    return {"reach": REACH, "split": save_split_model(tmp / "split.safetensors"),
            "camera": save_image_model(tmp / "camera.safetensors")}


def make_core(files: dict) -> PrimitiveServerCore:
    cfg = ServerConfig()
    prims = {n: load_primitive(PrimitiveEntry(n, str(p)), SPEC.joint_names, pathlib.Path) for n, p in files.items()}
    return PrimitiveServerCore(prims, cfg, robot_limits(SPEC, cfg))


def vias(n, seed=0, spread=0.1):
    x, y = far_via_points(n, seed, spread)
    return [ViaPointIn(float(a), b, np.zeros(0, bool)) for a, b in zip(x, y)]


def image_context(n):
    rng = np.random.default_rng(0)
    return ContextIn("image", np.zeros(0), tuple(
        ImageIn(64, 64, "rgb8", 64 * 3, rng.integers(0, 256, 64 * 64 * 3, dtype=np.uint8)) for _ in range(n)))


def largest_condition(cfg, primitive, refine):
    ctx = [image_context(cfg.max_images)] if primitive == "camera" else [ContextIn("object", np.array([0.4, 0.0, 0.1]))]
    return ConditionRequest(primitive, vias(cfg.max_via_points), ctx, refine, 10000, 0.0, cfg.max_preview_points)


def blend_of(core, parts, primitive="reach"):
    """A blended handle of ``parts`` (a power of 2) conditioned distributions: a handle blended with itself."""
    h = core.condition(ConditionRequest(primitive, vias(3, seed=5), preview_points=2)).handle
    n = 1
    while n < parts:
        h, n = core.blend(BlendRequest(h, h, preview_points=2)).handle, 2 * n
    return h


# ================================================================================================
# the child process: every timed request, figures as JSON
# ================================================================================================
def measure(tmp: pathlib.Path) -> dict:
    """Run every timed case; {case: {"wall": s, "cpu": s, ...what the test checks of its outcome}}."""
    out = {}

    def timed(case, fn, *args, **fields):
        w0, c0 = time.perf_counter(), time.thread_time()
        res = fn(*args)
        out[case] = dict(wall=time.perf_counter() - w0, cpu=time.thread_time() - c0, **fields)
        return res

    files = model_files(tmp)
    # refinement at the DeepProMP level: a plain latent (reach) and a split one
    for name, n, spread in (("reach", 200, 0.3), ("split", 300, 0.1)):
        prim = DeepProMP.from_checkpoint(str(files[name]))
        x, y = far_via_points(n, seed=1, spread=spread)
        prior = prim.condition(x, y)
        prim.refine(prior, x[:2], y[:2], max_iterations=3)  # first call: lazy set-up not timed
        res = timed(f"refine_{name}", lambda: prim.refine(prior, x, y, max_iterations=10000, time_budget=UNIT_BUDGET))
        out[f"refine_{name}"].update(
            out_of_time=res.out_of_time, reachable=res.reachable, reason=res.reason, iterations=res.iterations,
            max_error=res.max_error, start_error=float(np.abs(prim.decode(prior.mean, x) - y).max()),
            decoded_error=float(np.abs(prim.decode(res.latent.mean, x) - y).max()),
            history_last=float(res.error_history[-1]), history_falls=bool(np.all(np.diff(res.error_history) <= 0)))

    core = make_core(files)
    cfg = core.config
    h = core.condition(ConditionRequest("reach", [ViaPointIn(0.5, HOME, np.zeros(0, bool))], refine=True)).handle
    core.blend(BlendRequest(h, h))
    core.sample(SampleRequest(h, n_samples=10))  # first calls of every kind: not timed
    for name in files:
        for refine in (False, True):
            case = f"condition_{name}_{'refined' if refine else 'plain'}"
            r = timed(case, core.condition, largest_condition(cfg, name, refine))
            out[case].update(code=int(r.code), message=r.message, iterations=r.refine_iterations,
                             preview=list(r.preview.mean.shape), stored=core.handles.get(r.handle).primitive)
    half = blend_of(core, cfg.max_blend_parts // 2)
    knots = np.linspace(0.0, 1.0, cfg.max_via_points)
    weights = np.random.default_rng(0).uniform(0.0, 1.0, cfg.max_via_points)
    r = timed("blend", core.blend, BlendRequest(half, half, knots, weights, cfg.max_preview_points, True, 1))
    out["blend"].update(parts=core.handles.get(r.handle).parts, preview=list(r.preview.mean.shape),
                        finite=bool(np.all(np.isfinite(r.preview.std))))
    largest = r.handle
    sources = {"prior": dict(primitive="reach"), "blend": dict(handle=largest),
               "conditioned": dict(handle=core.condition(ConditionRequest("reach", vias(5))).handle),
               "split": dict(handle=core.condition(ConditionRequest("split", vias(5))).handle)}
    for source, req in sources.items():
        for s in (cfg.max_samples, cfg.max_sample_points // cfg.max_preview_points):
            t = cfg.max_sample_points // s
            r = timed(f"sample_{source}_{s}x{t}", core.sample, SampleRequest(**req, n_samples=s, n_points=t, seed=1))
            out[f"sample_{source}_{s}x{t}"].update(shape=list(r.samples.shape),
                                                   finite=bool(np.all(np.isfinite(r.samples))))
    plan = timed("execute_plan", core.plan_execution, ExecuteRequest(largest, duration=600.0))
    out["execute_plan"].update(grid=list(plan.reference.y.shape))
    desc = timed("list_primitives", core.describe)
    out["list_primitives"].update(names=sorted(d.name for d in desc))
    return out


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    run = subprocess.run([sys.executable, __file__, str(tmp_path_factory.mktemp("bounds"))], env=env,
                         capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-4000:]
    return json.loads(run.stdout.strip().splitlines()[-1])


# ================================================================================================
# refinement's time budget
# ================================================================================================
@pytest.mark.parametrize("name", ["reach", "split"])
def test_refinement_stops_at_its_time_budget_with_the_best_fit_and_says_so(measured, name):
    m = measured[f"refine_{name}"]
    assert m["wall"] >= UNIT_BUDGET and m["cpu"] <= UNIT_BUDGET + REFINE_MARGIN_S, m
    assert m["out_of_time"] and not m["reachable"], m
    assert f"time budget of {UNIT_BUDGET:g} s" in m["reason"], m["reason"]
    assert 0 < m["iterations"] < 10000
    # the best fit found by then: no worse than the start, the error history's last value, and the
    # error of the latent returned
    assert m["max_error"] <= m["start_error"] and m["history_falls"]
    assert m["history_last"] == pytest.approx(m["max_error"], abs=1e-12)
    assert m["decoded_error"] == pytest.approx(m["max_error"], abs=1e-9)
    if name == "reach":  # Levenberg–Marquardt lowers the error of a plain latent within the budget
        assert m["max_error"] < m["start_error"]


@pytest.fixture(scope="module")
def reach():
    return DeepProMP.from_checkpoint(str(REACH))


def test_a_budget_that_is_not_reached_changes_nothing(reach):
    rng = np.random.default_rng(2)
    x = np.array([0.3, 0.7])
    y = reach.decode(rng.normal(0.0, 0.5, reach.latent_dim), x)  # decoded from a latent: reachable
    prior = reach.condition(x, y + 0.01)
    free = reach.refine(prior, x, y)
    budget = reach.refine(prior, x, y, time_budget=60.0)
    assert free.reachable and budget.reachable and not budget.out_of_time
    assert budget.iterations == free.iterations and budget.reason == free.reason
    np.testing.assert_array_equal(budget.latent.mean, free.latent.mean)
    np.testing.assert_array_equal(budget.latent.var, free.latent.var)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_an_invalid_time_budget_is_refused(reach, bad):
    x, y = far_via_points(2)
    with pytest.raises(ValueError, match="time_budget must be a finite number of seconds > 0"):
        reach.refine(reach.condition(x, y), x, y, time_budget=bad)


def test_split_refinement_starts_no_iteration_after_its_deadline(tmp_path):
    prim = DeepProMP.from_checkpoint(str(save_split_model(tmp_path / "split.safetensors")))
    x, y = far_via_points(30, seed=1, spread=0.1)
    prior = prim.condition(x, y)
    mask = np.ones(y.shape, dtype=bool)
    late = refine_split(prim._np, prior, x, y, mask, 1e-6, 10000, deadline=time.perf_counter() - 1.0)
    assert late.iterations == 0 and late.reason == "time budget" and late.latent is prior
    on_time = refine_split(prim._np, prior, x, y, mask, 1e-6, 10000)
    assert on_time.iterations > 0 and on_time.reason != "time budget"


# ================================================================================================
# the largest accepted request of each kind, shipped limits
# ================================================================================================
@pytest.mark.parametrize("name", ["reach", "split", "camera"])
def test_the_largest_condition_is_bounded_and_refinement_adds_its_time_budget(measured, name):
    cfg = ServerConfig()
    plain, refined = measured[f"condition_{name}_plain"], measured[f"condition_{name}_refined"]
    assert plain["code"] == Code.SUCCESS and plain["preview"] == [cfg.max_preview_points, 6], plain
    assert plain["cpu"] <= BOUND_S, plain
    assert refined["wall"] >= cfg.refine_time_budget, refined
    assert refined["cpu"] - plain["cpu"] <= cfg.refine_time_budget + REFINE_MARGIN_S, (plain, refined)
    assert refined["code"] == Code.REFINEMENT_UNREACHABLE and 0 < refined["iterations"] < 10000, refined
    assert f"time budget of {cfg.refine_time_budget:g} s (parameter refine_time_budget)" in refined["message"]
    assert refined["stored"] == name  # the best fit is stored under the handle


def test_the_largest_blend_is_bounded(measured):
    cfg = ServerConfig()
    m = measured["blend"]
    assert m["parts"] == cfg.max_blend_parts and m["preview"] == [cfg.max_preview_points, 6] and m["finite"], m
    assert m["cpu"] <= BOUND_S, m


@pytest.mark.parametrize("source", ["prior", "conditioned", "split", "blend"])
def test_the_largest_sample_is_bounded(measured, source):
    cfg = ServerConfig()
    for s in (cfg.max_samples, cfg.max_sample_points // cfg.max_preview_points):
        t = cfg.max_sample_points // s
        m = measured[f"sample_{source}_{s}x{t}"]
        assert m["shape"] == [s, t, 6] and m["finite"] and m["cpu"] <= BOUND_S, m


def test_the_largest_execute_plan_and_list_are_bounded(measured):
    cfg = ServerConfig()
    plan, listed = measured["execute_plan"], measured["list_primitives"]
    assert plan["grid"] == [cfg.execution_grid_points, 6] and plan["cpu"] <= BOUND_S, plan
    assert listed["names"] == ["camera", "reach", "split"] and listed["cpu"] <= BOUND_S, listed


@pytest.fixture(scope="module")
def core(tmp_path_factory):
    return make_core(model_files(tmp_path_factory.mktemp("models")))


def test_one_blend_part_more_is_refused_naming_the_parameter(core):
    cfg = core.config
    full = blend_of(core, cfg.max_blend_parts)
    one = core.condition(ConditionRequest("reach", vias(2))).handle
    with pytest.raises(RequestError) as info:
        core.blend(BlendRequest(full, one))
    assert info.value.code == Code.INVALID_REQUEST and "parameter max_blend_parts" in info.value.message
    assert f"would be made of {cfg.max_blend_parts + 1}" in info.value.message


def test_one_sample_point_more_is_refused_naming_the_parameter(core):
    cfg = core.config
    s, t = cfg.max_samples, cfg.max_sample_points // cfg.max_samples + 1
    with pytest.raises(RequestError) as info:
        core.sample(SampleRequest(primitive="reach", n_samples=s, n_points=t))
    assert info.value.code == Code.INVALID_REQUEST and "parameter max_sample_points" in info.value.message
    assert f"{s} x {t} = {s * t} trajectory points" in info.value.message


if __name__ == "__main__":  # the child process of the fixture ``measured``: python <this file> DIR
    torch.set_num_threads(1)
    print(json.dumps(measure(pathlib.Path(sys.argv[1]))))
