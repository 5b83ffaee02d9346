"""``close_box``: the WAM pushes the open lid of a box shut.

A 16×22×10 cm box on the table at radius 0.5–0.72 m, bearing ±0.6 rad, yaw = bearing ±0.4 rad;
its lid (hinge on the edge nearest the robot) is open by θ = 40–100°. The demonstrator brings the
tool plate to the lid's outer face (at 65–95 % of the lid length, 2–3.5 cm off the face), then
sweeps the lid's arc from θ to ~0° in 4–6 via-poses (tool axis between the face normal and
straight down) and retreats 6–12 cm up. Context ``box`` = (θ rad, x m, y m, yaw rad) — the
paper's Close Box context is "the angle of the box's lid and box location" (54-D RLBench
state; here the 4 numbers that define it).
"""
from __future__ import annotations

import math

import numpy as np

from deepprompt_ros.robots.geometry import rot_y, rot_z
from deepprompt_ros.sim.tasks.scene import DOWN, Rejected, Scene, ik, jitter_start, plan, wam_cameras

__all__ = ["BOX_L", "BOX_W", "BOX_H", "LID_T", "demonstrate"]


# Box of close_box (m): depth along its x (hinge edge at -x, nearest the robot), width, height, lid.
BOX_L, BOX_W, BOX_H, LID_T = 0.16, 0.22, 0.10, 0.01


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
    q0 = jitter_start(spec, rng, 0.08)
    theta = math.radians(rng.uniform(40.0, 100.0))
    r, b = rng.uniform(0.5, 0.72), rng.uniform(-0.6, 0.6)
    x, y, yaw = r * math.cos(b), r * math.sin(b), b + rng.uniform(-0.4, 0.4)
    Rb = rot_z(yaw)
    origin = np.array([x, y, 0.0])

    def world(p_local):
        return origin + Rb @ p_local

    hinge = np.array([-BOX_L / 2, 0.0, BOX_H])
    rho, delta = rng.uniform(0.65, 0.95), rng.uniform(0.02, 0.035)
    kappa = rng.uniform(0.2, 0.5)  # how much the tool axis leans towards straight down

    def normal(phi):  # outer normal of the lid opened by phi (box frame)
        return np.array([-math.sin(phi), 0.0, math.cos(phi)])

    def contact(phi):
        return hinge + rho * BOX_L * np.array([math.cos(phi), 0.0, math.sin(phi)]) + (LID_T / 2 + delta) * normal(phi)

    def tool_axis(phi):
        a = (1 - kappa) * (Rb @ -normal(phi)) + kappa * DOWN
        return a / np.linalg.norm(a)

    pre = contact(theta) + rng.uniform(0.06, 0.12) * normal(theta) + [0.0, 0.0, rng.uniform(0.0, 0.06)]
    m = int(rng.integers(4, 7))
    phi_end = math.radians(rng.uniform(0.0, 3.0))
    phis = np.linspace(theta, phi_end, m)
    retreat = contact(phi_end) + np.array([-rng.uniform(0.0, 0.05), 0.0, rng.uniform(0.06, 0.12)])
    poses = [(world(pre), tool_axis(theta))] + [(world(contact(p)), tool_axis(p)) for p in phis]
    poses.append((world(retreat), DOWN))
    knots, q = [q0], q0
    for p, a in poses:
        q = ik(scene, p, q, rest=q0, axis=a)
        knots.append(q)
    traj = plan(scene, knots, rng)
    scene.add("box", "box", (BOX_L, BOX_W, BOX_H), world(np.array([0.0, 0.0, BOX_H / 2])), R=Rb,
              rgba=(0.75, 0.55, 0.3, 1.0))
    R_lid = Rb @ rot_y(-theta)
    lid_center = hinge + (BOX_L / 2) * np.array([math.cos(theta), 0.0, math.sin(theta)])
    scene.add("lid", "box", (BOX_L, BOX_W, LID_T), world(lid_center), R=R_lid, rgba=(0.85, 0.2, 0.15, 1.0))
    if scene.collides(traj, ["box"], margin=0.0):
        raise Rejected("the plan hits the box")
    images = scene.images(q0, wam_cameras(), wrist=True)
    return {"box": np.array([theta, x, y, yaw])}, images, traj
