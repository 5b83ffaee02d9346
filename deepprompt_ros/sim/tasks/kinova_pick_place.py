"""``kinova_pick_place``: the Gen3 lite picks a cube (subtask pick) or places it on a square (place).

Gen3 lite, a red 3 cm cube (yaw ±45°) and a green 9 cm square target on the table
(x 0.24–0.46 m, |y| ≤ 0.2 m, ≥ 14 cm apart). Even-indexed demos are ``pick``: from the
home pose (+ U(±0.05) rad) to 8–14 cm above the cube, down to the grasp (wrist yaw aligned
with the cube), a 0.3–0.6 s hold (gripper closing), lift 6–12 cm. Odd-indexed demos are
``place``: starting with the cube held above a random pick location, carry it above the square,
lower it onto the square, hold, retreat 6–10 cm up. Context ``object_px`` = normalized pixel
position (u right, v down, in [0, 1]) in the front camera's image of the subtask's goal (the
cube for pick, the square for place; :func:`~deepprompt_ros.sim.camera.project_point`, checked
visible by ray casts), and ``subtask`` = one-hot (pick, place).
"""
from __future__ import annotations

import math

import numpy as np

from deepprompt_ros.robots.geometry import rot_z
from deepprompt_ros.sim.camera import project_point
from deepprompt_ros.sim.tasks.scene import Rejected, Scene, ik, jitter_start, kinova_cameras, plan

__all__ = ["CUBE", "SQUARE", "TOOL_DOWN", "demonstrate"]

# Edge lengths (m) of the cube and of the square target.
CUBE, SQUARE = 0.03, 0.09
TOOL_DOWN = np.diag([1.0, -1.0, -1.0])  # Gen3 lite tool_frame pointing down at home


def _kinova_sample_xy(rng):
    return np.array([rng.uniform(0.24, 0.46), rng.uniform(-0.2, 0.2)])


def demonstrate(scene: Scene, rng: np.random.Generator, index: int):
    """One demonstration (demo ``index`` of the split, drawing from ``rng``).

    Returns
    -------
    contexts : dict str -> array, shape (c,)
    images : list of uint8 arrays, shape (image_size, image_size, 3)
    trajectory : ViaTrajectory

    Raises
    ------
    Rejected
        The drawn scene cannot be demonstrated; the caller draws again.
    """
    spec = scene.spec
    obj, square = _kinova_sample_xy(rng), _kinova_sample_xy(rng)
    if np.linalg.norm(obj - square) < 0.14:
        raise Rejected("cube and square too close")
    psi = rng.uniform(-math.pi / 4, math.pi / 4)
    pick = index % 2 == 0
    cams = kinova_cameras()
    if pick:
        q0 = jitter_start(spec, rng, 0.05)
        R_g = rot_z(psi) @ TOOL_DOWN
        p_pre = np.append(obj, CUBE / 2 + rng.uniform(0.08, 0.14))
        p_grasp = np.append(obj, rng.uniform(0.012, 0.02))
        p_lift = p_grasp + [0.0, 0.0, rng.uniform(0.06, 0.12)]
        knots, q = [q0], q0
        for p in (p_pre, p_grasp, p_lift):
            q = ik(scene, p, q, rest=q0, rotation=R_g)
            knots.append(q)
        traj = plan(scene, knots, rng, holds={2: rng.uniform(0.3, 0.6)})
        goal_name, goal_point = "cube", np.append(obj, CUBE / 2)
        cube_pos, cube_R = np.append(obj, CUBE / 2), rot_z(psi)
    else:
        held_yaw = rng.uniform(-0.5, 0.5)
        R_c = rot_z(held_yaw) @ TOOL_DOWN
        p_start = np.append(obj, rng.uniform(0.08, 0.14))
        q0 = ik(scene, p_start, spec.home, rest=spec.home, rotation=R_c)
        p_above = np.append(square, rng.uniform(0.08, 0.14))
        p_mid = 0.5 * (p_start + p_above) + [0.0, 0.0, rng.uniform(0.0, 0.06)]
        p_place = np.append(square, 0.004 + CUBE / 2 + rng.uniform(0.0, 0.01))
        p_retreat = p_place + [0.0, 0.0, rng.uniform(0.06, 0.1)]
        knots, q = [q0], q0
        for p in (p_mid, p_above, p_place, p_retreat):
            q = ik(scene, p, q, rest=q0, rotation=R_c)
            knots.append(q)
        traj = plan(scene, knots, rng, holds={3: rng.uniform(0.3, 0.6)})
        goal_name, goal_point = "square", np.append(square, 0.002)
    if scene.collides(traj, []):
        raise Rejected("the plan touches the table")
    if not pick:
        pose0 = scene.kin.forward_kinematics(q0)
        cube_pos, cube_R = pose0.position, pose0.rotation
    scene.add("square", "box", (SQUARE, SQUARE, 0.004), np.append(square, 0.002), rgba=(0.1, 0.7, 0.2, 1.0))
    scene.add("cube", "box", (CUBE,) * 3, cube_pos, R=cube_R, rgba=(0.9, 0.1, 0.1, 1.0))
    scene.sim.reset(q0)
    half = (CUBE if goal_name == "cube" else SQUARE) * 0.4
    top = goal_point + [0.0, 0.0, CUBE / 2 if goal_name == "cube" else 0.002]
    pts = np.array([top + [dx, dy, 0.0] for dx in (-half, 0.0, half) for dy in (-half, 0.0, half)])
    if scene.visible(cams[0], goal_name, pts) < 0.99:
        raise Rejected(f"the {goal_name} is hidden from the front camera")
    s = scene.image_size
    uv = project_point(cams[0], goal_point, s, s)
    images = scene.images(q0, cams[:1])
    radius = 0.045 if goal_name == "cube" else 0.075
    scene.add("marker", "cylinder", (radius, 0.002), np.append(goal_point[:2], 0.001),
              rgba=(1.0, 0.85, 0.0, 1.0))
    images += scene.images(q0, cams)
    contexts = {"object_px": uv, "subtask": np.array([1.0, 0.0] if pick else [0.0, 1.0])}
    return contexts, images, traj
