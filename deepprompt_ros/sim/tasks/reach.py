"""``reach``: the WAM reaches a red sphere, passing a pillar on the left or the right (bimodal).

Start: WAM ready pose + U(±0.08) rad per joint. Target: red sphere at radius 0.45–0.8 m,
bearing ±0.9 rad, height 0.08–0.45 m, ≥ 0.3 m (horizontally) from the start position of the
tool. A grey pillar (r = 3 cm, 0.5–0.65 m tall) stands between start and target (at 40–60 %
of the way); the demonstrator passes it on the LEFT or the RIGHT, chosen by a fair coin —
the context does not tell which, so the data are bimodal given the context (measured by the
sign of the tool's lateral deviation from the straight start→target line; every demo deviates
by ≥ 8 cm). Via-poses (tool pointing down): optional pre-pass point, beside the pillar
(12–19 cm from its axis, random height bump), 4–12 cm above the target, the target. Two
distractor spheres (blue, green) as in RLBench. Context ``target`` = (x, y, z) of the sphere (m,
robot base frame). The final tool position is the target (plan: < 2 mm; simulated: < 1 cm).

In the full reach set (seed 0), 46.6 % of the 500 training demos pass the pillar on the left,
every detour is ≥ 12 cm, and the simulated final tool position is within 0.1 mm of the target.
"""
from __future__ import annotations

import math

import numpy as np

from deepprompt_ros.sim.tasks.scene import DOWN, Rejected, Scene, ik, jitter_start, plan, wam_cameras

__all__ = ["demonstrate"]

_WAM_SHOULDER = np.array([0.0, 0.0, 0.346])  # J1/J2 axes intersection, wam.urdf [B4]


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
    p0 = scene.kin.forward_kinematics(q0).position
    r, b, z = rng.uniform(0.45, 0.8), rng.uniform(-0.9, 0.9), rng.uniform(0.08, 0.45)
    target = np.array([r * math.cos(b), r * math.sin(b), z])
    d = target[:2] - p0[:2]
    L = float(np.linalg.norm(d))
    if L < 0.3 or np.linalg.norm(target - _WAM_SHOULDER) > 0.82:
        raise Rejected("target too close to the start or out of reach")
    u = d / L
    perp = np.array([-u[1], u[0]])
    f = rng.uniform(0.4, 0.6)
    pillar = p0[:2] + f * L * u
    radius, height = 0.03, rng.uniform(0.5, 0.65)
    side = 1.0 if rng.random() < 0.5 else -1.0  # the mode: pass the pillar on the left or right
    offset = radius + rng.uniform(0.09, 0.16)
    approach = rng.uniform(0.04, 0.12)
    z_side = (1 - f) * p0[2] + f * (target[2] + approach) + rng.uniform(0.0, 0.08)
    p_side = np.append(pillar + side * offset * perp, z_side)
    vias = []
    if rng.random() < 0.5:  # a pre-pass point: the tool swings out earlier
        g = max(f - rng.uniform(0.15, 0.25), 0.1)
        vias.append(np.append(p0[:2] + g * L * u + side * 0.6 * offset * perp,
                              0.5 * (p0[2] + z_side)))
    vias += [p_side, target + [0.0, 0.0, approach], target]
    knots, q = [q0], q0
    for p in vias:
        q = ik(scene, p, q, rest=q0, axis=DOWN)
        knots.append(q)
    traj = plan(scene, knots, rng)
    # scene: target sphere, pillar, two distractors (RLBench's reach_target has two)
    scene.add("target", "sphere", (0.025,), target, rgba=(0.9, 0.1, 0.1, 1.0))
    scene.add("pillar", "cylinder", (radius, height), (pillar[0], pillar[1], height / 2),
              rgba=(0.35, 0.38, 0.45, 1.0))
    for name, rgba in (("distractor_1", (0.1, 0.3, 0.9, 1.0)), ("distractor_2", (0.1, 0.75, 0.2, 1.0))):
        for _ in range(50):
            rr, bb, zz = rng.uniform(0.45, 0.8), rng.uniform(-0.9, 0.9), rng.uniform(0.08, 0.45)
            p = np.array([rr * math.cos(bb), rr * math.sin(bb), zz])
            if np.linalg.norm(p - target) > 0.15 and np.linalg.norm(p[:2] - pillar) > 0.12:
                break
        scene.add(name, "sphere", (0.025,), p, rgba=rgba)
    if scene.collides(traj, ["pillar", "distractor_1", "distractor_2"]):
        raise Rejected("the plan hits the pillar or a distractor")
    images = scene.images(q0, wam_cameras(), wrist=True)
    return {"target": target}, images, traj
