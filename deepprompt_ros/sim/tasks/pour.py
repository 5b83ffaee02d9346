"""``pour``: the WAM grasps a cup, carries it over a pot and pours (tilting to either side).

A cup (r 3.5 cm, 11 cm, at radius 0.55-0.8 m) and a pot (r 6 cm, 5-16 cm tall, with a plant)
on the table, ≥ 20 cm apart. The demonstrator approaches the cup from the side and above
(tool axis towards the cup ±0.25 rad, 30-50° below horizontal: the WAM's wrist cannot hold a
horizontal tool axis close to its base), grasps it at 45-70 % of its height (a 0.2-0.5 s hold),
lifts 12-20 cm, carries it over the pot through a raised midpoint, tilts it by rolling the
wrist (J7, whose axis is the tool axis) by ±(1.4-2.0) rad — the direction is a fair coin, a
second bimodality — holds 0.4-1.0 s and turns it upright. The pour pose puts the mouth of the
tilted cup (modelled as held rigidly on the tool axis) 8-14 cm above the pot's rim. Context
``pour`` = (cup x, cup y, pot x, pot y, pot height) (m) — "the location of the watering can
and object to be watered".

In the full pour set (seed 0), 47.9 % of the training demos tilt to the positive side.
"""
from __future__ import annotations

import math

import numpy as np

from deepprompt_ros.robots.geometry import rodrigues
from deepprompt_ros.sim.tasks.scene import Rejected, Scene, ik, jitter_start, plan, wam_cameras

__all__ = ["CUP_R", "CUP_H", "POT_R", "demonstrate"]


# Cup and pot of pour (m).
CUP_R, CUP_H, POT_R = 0.035, 0.11, 0.06


def _tilted_axis(bearing: float, tilt: float) -> np.ndarray:
    """Unit tool axis pointing away from the base at ``bearing``, ``tilt`` rad below horizontal."""
    return np.array([math.cos(bearing) * math.cos(tilt), math.sin(bearing) * math.cos(tilt), -math.sin(tilt)])


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
    r, b = rng.uniform(0.55, 0.8), rng.uniform(-0.7, 0.7)
    cup = np.array([r * math.cos(b), r * math.sin(b)])
    r, b = rng.uniform(0.5, 0.8), rng.uniform(-0.8, 0.8)
    pot = np.array([r * math.cos(b), r * math.sin(b)])
    pot_h = rng.uniform(0.05, 0.16)
    if np.linalg.norm(cup - pot) < 0.2:
        raise Rejected("cup and pot too close")
    hold = CUP_R + 0.005  # the cup's axis is this far along the tool axis from the tool plate
    # grasp from the side and above: tool axis towards the cup, 30-50 deg below horizontal
    a_g = _tilted_axis(math.atan2(cup[1], cup[0]) + rng.uniform(-0.25, 0.25), math.radians(rng.uniform(30, 50)))
    p_grasp = np.append(cup, CUP_H * rng.uniform(0.45, 0.7)) - hold * a_g
    p_pre = p_grasp - rng.uniform(0.08, 0.14) * a_g + [0.0, 0.0, rng.uniform(0.0, 0.04)]
    p_lift = p_grasp + [0.0, 0.0, rng.uniform(0.12, 0.2)]
    a_p = _tilted_axis(math.atan2(pot[1], pot[0]) + rng.uniform(-0.25, 0.25), math.radians(rng.uniform(30, 50)))
    sign = 1.0 if rng.random() < 0.5 else -1.0  # the mode: tilt towards one side or the other
    tilt = sign * rng.uniform(1.4, 2.0)
    # Rolling J7 (axis = tool axis a_p) by `tilt` turns the cup's axis from z to R z; place the cup
    # so that its mouth (half a cup height along that axis) ends above the pot's centre.
    up = rodrigues(a_p, tilt) @ np.array([0.0, 0.0, 1.0])
    mouth = np.append(pot, pot_h + rng.uniform(0.08, 0.14))
    centre = mouth - (CUP_H / 2) * up
    p_pour = centre - hold * a_p
    p_carry = 0.5 * (p_lift + p_pour) + [0.0, 0.0, rng.uniform(0.03, 0.1)]
    a_c = (a_g + a_p) / max(np.linalg.norm(a_g + a_p), 1e-6)
    j7 = rng.uniform(-0.3, 0.3)  # J7 rolls about the tool axis: free for these 5-D via-poses
    knots, q = [q0], q0
    for p, a in ((p_pre, a_g), (p_grasp, a_g), (p_lift, a_g), (p_carry, a_c), (p_pour, a_p)):
        q = ik(scene, p, q, rest=q0, axis=a)
        q[-1] = j7
        knots.append(q)
    q_tilt = knots[-1].copy()
    q_tilt[-1] = j7 + tilt
    knots += [q_tilt, knots[-1].copy()]
    # holds: gripper closing at the grasp (knot 2) and pouring (the tilted knot 6)
    traj = plan(scene, knots, rng, holds={2: rng.uniform(0.2, 0.5), 6: rng.uniform(0.4, 1.0)})
    scene.add("cup", "cylinder", (CUP_R, CUP_H), np.append(cup, CUP_H / 2), rgba=(0.2, 0.45, 0.9, 1.0))
    scene.add("pot", "cylinder", (POT_R, pot_h), np.append(pot, pot_h / 2), rgba=(0.55, 0.3, 0.15, 1.0))
    scene.add("plant", "sphere", (0.035,), np.append(pot, pot_h + 0.015), rgba=(0.15, 0.65, 0.2, 1.0))
    if scene.collides(traj, ["pot", "plant"], margin=0.005):
        raise Rejected("the plan hits the pot")
    images = scene.images(q0, wam_cameras(), wrist=True)
    return {"pour": np.array([cup[0], cup[1], pot[0], pot[1], pot_h])}, images, traj
