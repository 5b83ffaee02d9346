"""PyBullet task datasets (deepprompt_ros.sim.tasks): real PyBullet and Pinocchio, no mocks.

Small seeded datasets are generated once per module (the quick configuration records the plan;
one small set is executed in the simulation) and checked against the scene they claim to show.
"""
import json
import math

import numpy as np
import pytest

from deepprompt_ros.data.builtin import builtin_dataset
from deepprompt_ros.data.demo_dataset import load_dataset
from deepprompt_ros.robots.kinematics import RobotKinematics
from deepprompt_ros.robots.spec import load_robot
from deepprompt_ros.sim.camera import project_point
from deepprompt_ros.sim.tasks.cli import main
from deepprompt_ros.sim.tasks.registry import SPLITS, TASKS, make_task
from deepprompt_ros.sim.tasks.scene import kinova_cameras, wam_cameras
from deepprompt_ros.sim.tasks.trajectory import ViaTrajectory

N = {"reach": 12, "close_box": 6, "pour": 10, "kinova_pick_place": 8}


@pytest.fixture(scope="module")
def data():
    out = {name: make_task(name, n=n, quick=True, seed=3) for name, n in N.items()}
    out["reach_96"] = make_task("reach", n=4, quick=True, seed=4, image_size=96)
    out["reach_sim"] = make_task("reach", n=3, seed=3, simulate=True)
    return out


@pytest.fixture(scope="module")
def kin():
    return {r: RobotKinematics(load_robot(r)) for r in ("wam", "gen3_lite")}


def _ee_path(k, q):
    return np.array([k.forward_kinematics(qi).position for qi in q])


def _color_centroid(img, rule):
    mask = rule(img.astype(int))
    rows, cols = np.nonzero(mask)
    return mask.sum(), np.array([cols.mean() + 0.5, rows.mean() + 0.5]) if mask.any() else None


def _red(im):
    return (im[..., 0] > 120) & (im[..., 1] < 70) & (im[..., 2] < 70)


def _green(im):
    return (im[..., 1] > 100) & (im[..., 0] < 80) & (im[..., 2] < 80)


def _yellow(im):
    return (im[..., 0] > 140) & (im[..., 1] > 110) & (im[..., 2] < 40)


# ----------------------------------------------------------------------------------------------
def test_registry_sizes_and_contexts():
    assert set(TASKS) == {"reach", "close_box", "pour", "kinova_pick_place"}
    assert TASKS["reach"].sizes == (500, 100, 200)  # the paper's Reach sizes
    assert TASKS["close_box"].sizes[0] == TASKS["pour"].sizes[0] == 1000
    assert sum(TASKS["kinova_pick_place"].sizes) == 100
    assert all(t.quick_sizes == (20, 5, 10) for t in TASKS.values())
    assert dict(TASKS["reach"].contexts) == {"target": 3}
    assert dict(TASKS["kinova_pick_place"].contexts) == {"object_px": 2, "subtask": 2}
    assert TASKS["kinova_pick_place"].robot == "gen3_lite" and TASKS["reach"].robot == "wam"
    assert load_robot("wam").n_joints == 7 and load_robot("gen3_lite").n_joints == 6


@pytest.mark.parametrize("name", list(N))
def test_format_shapes_and_limits(data, name):
    ds = data[name]
    task = TASKS[name]
    spec = load_robot(task.robot)
    assert len(ds) == N[name]
    assert ds.joint_names == spec.joint_names
    assert ds.context_dims == dict(sorted(task.contexts))
    for d in ds.demos:
        assert d.q.shape == (100, spec.n_joints) and d.t.shape == (100,)
        assert d.t[0] == 0.0 and np.all(np.diff(d.t) > 0)
        assert d.images.shape == (task.n_images, 64, 64, 3) and d.images.dtype == np.uint8
        # position limits, and velocities (finite differences) within the velocity limits
        assert np.all(d.q >= spec.lower) and np.all(d.q <= spec.upper)
        qd = np.diff(d.q, axis=0) / np.diff(d.t)[:, None]
        assert np.all(np.abs(qd) <= spec.velocity), (name, np.abs(qd).max(axis=0), spec.velocity)
        # the demonstrator starts and ends at rest (minimum-jerk start; a settled end)
        assert np.all(np.abs(qd[0]) <= 0.25 * np.abs(qd).max(axis=0) + 1e-9)
        np.testing.assert_allclose(qd[-1], 0.0, atol=1e-3)
    # genuinely varied: demos differ in duration and in their joint trajectories
    durations = [d.t[-1] for d in ds.demos]
    assert np.std(durations) > 0.1
    shapes = [d.resampled(50) for d in ds.demos]
    assert min(np.abs(a - b).max() for a, b in zip(shapes, shapes[1:])) > 0.1


def test_seeded_determinism_prefix_and_splits():
    a = make_task("close_box", n=2, quick=True, seed=5)
    b = make_task("close_box", n=2, quick=True, seed=5)
    for x, y in zip(a.demos, b.demos):
        np.testing.assert_array_equal(x.q, y.q)
        np.testing.assert_array_equal(x.t, y.t)
        np.testing.assert_array_equal(x.images, y.images)
        np.testing.assert_array_equal(x.contexts["box"], y.contexts["box"])
    one = make_task("close_box", n=1, quick=True, seed=5)  # demo i does not depend on n
    np.testing.assert_array_equal(one.demos[0].q, a.demos[0].q)
    other_seed = make_task("close_box", n=1, quick=True, seed=6)
    val = make_task("close_box", split="val", n=1, quick=True, seed=5)
    for ds in (other_seed, val):
        assert np.abs(ds.demos[0].contexts["box"] - a.demos[0].contexts["box"]).max() > 1e-3


def test_reach_ends_at_target_with_the_tool_pointing_down(data, kin):
    k = kin["wam"]
    for key, tol in (("reach", 2e-3), ("reach_sim", 1e-2)):
        for d in data[key].demos:
            pose = k.forward_kinematics(d.q[-1])
            assert np.linalg.norm(pose.position - d.contexts["target"][0]) < tol, key
            assert pose.rotation[2, 2] < -0.99  # tool z axis points down


def test_reach_simulated_execution_follows_the_plan_closely(data):
    sim = data["reach_sim"]
    plan = make_task("reach", n=3, seed=3, simulate=False)
    for s, p in zip(sim.demos, plan.demos):
        np.testing.assert_array_equal(s.contexts["target"], p.contexts["target"])
        diff = np.abs(s.q - p.q).max()
        assert 1e-5 < diff < 0.03  # really simulated (not the plan), and tracking well


def test_reach_is_bimodal_left_or_right_of_the_straight_line(data, kin):
    """Every demo detours ≥ 8 cm sideways from the straight start→target line, to either side."""
    k = kin["wam"]
    sides, detours = [], []
    for d in data["reach"].demos:
        p = _ee_path(k, d.q)
        target = d.contexts["target"][0]
        u = (target[:2] - p[0, :2]) / np.linalg.norm(target[:2] - p[0, :2])
        lateral = u[0] * (p[:, 1] - p[0, 1]) - u[1] * (p[:, 0] - p[0, 0])  # z of u × (p − p0)
        i = int(np.argmax(np.abs(lateral)))
        sides.append(np.sign(lateral[i]))
        detours.append(abs(lateral[i]))
    sides = np.array(sides)
    assert min(detours) > 0.08, detours
    assert 0.25 <= np.mean(sides > 0) <= 0.75, sides  # both modes, neither rare


def test_reach_images_show_the_target_where_the_context_says(data):
    cams = wam_cameras()
    checked = 0
    for d in data["reach_96"].demos:
        target = d.contexts["target"][0]
        for img, cam in zip(d.images[:4], cams):
            count, c = _color_centroid(img, _red)
            if count >= 3:  # the sphere can hide behind the arm in some views
                uv = project_point(cam, target, 96, 96)
                assert np.linalg.norm(c - uv * 96) < 2.0, (c, uv * 96)
                checked += 1
    assert checked >= 8


def test_images_differ_when_the_context_differs(data):
    for name in N:
        demos = data[name].demos
        for a, b in zip(demos, demos[1:]):
            ctx_diff = max(np.abs(a.contexts[k] - b.contexts[k]).max() for k in a.contexts)
            assert ctx_diff > 1e-3
            assert np.abs(a.images.astype(int) - b.images.astype(int)).mean() > 0.2, name


def test_close_box_motion_matches_box_pose_and_lid_angle(data, kin):
    from deepprompt_ros.sim.tasks.close_box import BOX_H, BOX_L, BOX_W, LID_T

    k = kin["wam"]
    for d in data["close_box"].demos:
        theta, x, y, yaw = d.contexts["box"][0]
        assert math.radians(40) <= theta <= math.radians(100)
        p = _ee_path(k, d.q)
        c, s = math.cos(yaw), math.sin(yaw)
        local = np.stack([c * (p[:, 0] - x) + s * (p[:, 1] - y), -s * (p[:, 0] - x) + c * (p[:, 1] - y), p[:, 2]], 1)
        # the tool pushes the closed lid: above the box's footprint, just above the lid
        on_top = ((np.abs(local[:, 0]) < BOX_L / 2) & (np.abs(local[:, 1]) < BOX_W / 2)
                  & (local[:, 2] > BOX_H + LID_T) & (local[:, 2] < BOX_H + LID_T + 0.05))
        assert on_top.any()
        # it reaches the open lid's outer face (2.5-4 cm off it, 65-95 % of its length) from outside
        h = np.array([-BOX_L / 2, BOX_H])
        rel = local[:, [0, 2]] - h
        along = rel @ np.array([math.cos(theta), math.sin(theta)])
        normal = rel @ np.array([-math.sin(theta), math.cos(theta)])
        off_region = (np.clip(0.6 * BOX_L - along, 0, None) + np.clip(along - BOX_L, 0, None)
                      + np.clip(0.02 - normal, 0, None) + np.clip(normal - 0.045, 0, None))
        i = int(np.argmin(off_region))
        assert off_region[i] < 0.015, off_region[i]
        inside = (along[:i] > 0) & (along[:i] < BOX_L) & (np.abs(local[:i, 1]) < BOX_W / 2)
        assert np.all(normal[:i][inside] > 0.01)  # never through the open lid before touching it
        # the lid angle: the tool sweeps an arc about the hinge (constant radius) from the open lid
        # down to the closed one; the swept angle equals θ (measured 6-12° more: the approach
        # crosses the arc's radius a little outside the lid)
        rad, pol = np.hypot(rel[:, 0], rel[:, 1]), np.arctan2(rel[:, 1], rel[:, 0])
        i_end = int(np.argmin(np.where(np.abs(local[:, 0]) < BOX_L / 2, local[:, 2], np.inf)))
        on_arc = np.abs(rad - rad[i_end]) < 0.01
        swept = pol[on_arc].max() - pol[i_end]
        assert 0.0 < swept - theta < math.radians(15), (math.degrees(swept), math.degrees(theta))
        # starts and ends out of the box
        assert local[0, 2] > BOX_H + 0.1 and local[-1, 2] > BOX_H + 0.05


def test_pour_grasps_the_cup_and_tilts_over_the_pot_to_either_side(data, kin):
    from deepprompt_ros.sim.tasks.pour import CUP_H, CUP_R

    k = kin["wam"]
    signs = []
    for d in data["pour"].demos:
        cx, cy, px, py, ph = d.contexts["pour"][0]
        p = _ee_path(k, d.q)
        axes = np.array([k.forward_kinematics(q).rotation[:, 2] for q in d.q])
        cup_axis_at = p + (CUP_R + 0.005) * axes  # where a cup held on the tool axis would be
        grasp = np.linalg.norm(cup_axis_at[:, :2] - [cx, cy], axis=1)
        i = int(np.argmin(grasp))
        assert grasp[i] < 0.01 and 0.0 < cup_axis_at[i, 2] < CUP_H
        roll = d.q[:, 6] - d.q[i, 6]
        j = int(np.argmax(np.abs(roll)))
        assert abs(roll[j]) > 1.3 and j > i
        assert np.linalg.norm(cup_axis_at[j, :2] - [px, py]) < 0.12  # tilting happens over the pot
        assert cup_axis_at[j, 2] > ph
        signs.append(np.sign(roll[j]))
    assert {-1.0, 1.0} <= set(signs)


def test_kinova_pixel_context_matches_image_and_motion(data, kin):
    k = kin["gen3_lite"]
    cam = kinova_cameras()[0]
    subtasks = []
    for d in data["kinova_pick_place"].demos:
        uv = d.contexts["object_px"][0]
        onehot = d.contexts["subtask"][0]
        assert set(onehot) == {0.0, 1.0} and onehot.sum() == 1.0
        assert np.all((uv > 0.05) & (uv < 0.95))
        pick = onehot[0] == 1.0
        subtasks.append(pick)
        # the goal's colour blob in the plain image sits at object_px
        count, c = _color_centroid(d.images[0], _red if pick else _green)
        assert count >= 4
        assert np.linalg.norm(c - uv * 64) < 1.5, (c, uv * 64)
        # images 1 and 2 carry the yellow marker, image 0 does not
        assert _yellow(d.images[0].astype(int)).sum() == 0
        assert _yellow(d.images[1].astype(int)).sum() >= 3 and _yellow(d.images[2].astype(int)).sum() >= 3
        # the lowest point of the motion (grasp / place) is over the goal seen at object_px
        p = _ee_path(k, d.q)
        low = p[int(np.argmin(p[:, 2]))]
        z = 0.015 if pick else 0.002
        assert np.linalg.norm(project_point(cam, [low[0], low[1], z], 64, 64) - uv) < 0.03
        assert low[2] < 0.04
    assert any(subtasks) and not all(subtasks)


def test_via_trajectory_passes_knots_rests_at_holds_and_respects_limits():
    spec = load_robot("wam")
    rng = np.random.default_rng(0)
    knots = spec.home + rng.uniform(-0.6, 0.6, (5, 7))
    knots[3] = knots[2]  # a hold
    traj = ViaTrajectory(knots, [1.0, 0.8, 0.5, 1.2], flow=1.0)
    q, qd, qdd = traj.evaluate(traj.times)
    np.testing.assert_allclose(q, knots, atol=1e-12)
    np.testing.assert_allclose(qdd, 0.0, atol=1e-9)
    np.testing.assert_allclose(qd[[0, 2, 3, 4]], 0.0, atol=1e-12)
    assert np.abs(qd[1]).max() > 0.01  # flows through the other via-configurations
    slow = traj.within_limits(spec, fraction=0.85)
    _, qd, qdd = slow.evaluate(np.linspace(0, slow.duration, 5001))
    assert np.all(np.abs(qd) <= 0.85 * spec.velocity * 1.001)
    assert np.all(np.abs(qdd) <= 0.85 * spec.acceleration * 1.001)
    assert slow.duration > traj.duration  # it had to be slowed down


def test_bad_arguments_are_refused_with_clear_messages():
    with pytest.raises(ValueError, match="unknown task 'reech'.*reach, close_box, pour, kinova_pick_place"):
        make_task("reech")
    with pytest.raises(ValueError, match="unknown split 'training'.*train, val, test"):
        make_task("reach", split="training")
    with pytest.raises(ValueError, match="n must be an integer >= 1"):
        make_task("reach", n=0)
    with pytest.raises(ValueError, match="seed must be an integer >= 0"):
        make_task("reach", n=1, seed=-1)
    with pytest.raises(ValueError, match="image_size must be an integer in 16..512"):
        make_task("reach", n=1, image_size=8)
    with pytest.raises(ValueError, match="n_points must be an integer in 2..500"):
        make_task("reach", n=1, n_points=1)
    with pytest.raises(ValueError, match="knots must have shape"):
        ViaTrajectory(np.zeros((1, 7)), [])
    with pytest.raises(ValueError, match="durations must be K-1 = 1 positive"):
        ViaTrajectory(np.zeros((2, 7)), [0.0])


def test_cli_writes_loadable_splits_and_a_manifest(tmp_path, capsys):
    out = tmp_path / "kpp"
    assert main(["kinova_pick_place", "--out", str(out), "--quick", "--n", "2", "--split", "val"]) == 0
    err = capsys.readouterr().err
    assert "2/2 demos" in err and str(out.resolve()) in err
    ds = load_dataset(out / "val")
    ref = make_task("kinova_pick_place", "val", n=2, quick=True)
    assert len(ds) == 2
    for a, b in zip(ds.demos, ref.demos):
        np.testing.assert_array_equal(a.q, b.q)
        np.testing.assert_array_equal(a.images, b.images)
        np.testing.assert_array_equal(a.contexts["object_px"], b.contexts["object_px"])
    manifest = json.loads((out / "task.json").read_text())
    assert manifest["task"] == "kinova_pick_place" and manifest["splits"]["val"]["n"] == 2
    assert manifest["contexts"] == {"object_px": 2, "subtask": 2}
    assert not (out / "train").exists()
    with pytest.raises(SystemExit) as exc:
        main(["reech", "--out", str(out)])
    assert exc.value.code == 2
    assert "unknown task 'reech'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["reach", "--out", str(out), "--split", "dev"])
    assert "expected one of train, val, test or all" in capsys.readouterr().err
    assert SPLITS == ("train", "val", "test")


def test_builtin_registry_generates_the_train_split():
    ds = builtin_dataset("pour", seed=2, n=1, quick=True)
    ref = make_task("pour", "train", n=1, quick=True, seed=2)
    np.testing.assert_array_equal(ds.demos[0].q, ref.demos[0].q)
    assert ds.context_dims == {"pour": 5}


def test_experiment_data_cache_key_covers_the_generating_code():
    """experiments.common keys its cache of generated task splits by a digest of the code that
    generates them: the tasks package and everything the registry imports, late imports included."""
    import pathlib
    import sys

    root = pathlib.Path(__file__).resolve().parents[1]
    sys.path.insert(0, str(root))
    from experiments import common

    files = {f.relative_to(root).as_posix() for f in common.import_closure("deepprompt_ros.sim.tasks.registry")}
    for need in ("sim/tasks/registry.py", "sim/tasks/reach.py", "sim/tasks/pour.py", "sim/tasks/scene.py",
                 "sim/tasks/trajectory.py", "sim/tasks/min_jerk.py", "sim/simulation.py", "sim/camera.py",
                 "robots/ik.py", "robots/geometry.py", "robots/kinematics.py", "robots/spec.py",
                 "data/demonstration.py", "data/demo_dataset.py"):
        assert f"deepprompt_ros/{need}" in files, need
    assert not any(f.startswith(("deepprompt_ros/training", "deepprompt_ros/ros/")) for f in files), files
    tasks, digest = common._tasks_module()
    assert tasks is common._tasks_module()[0] and len(digest) == 10
