"""Kinematic reaching demonstrations for a robot arm (the primitive shipped for ``make run``).

A demonstrator moves the arm from its home configuration to a point ``approach_height`` above an
object, passing through a lifted intermediate configuration whose height varies per demo, and
turns the wrist (last joint) towards the object's bearing. Joint targets come from
damped-least-squares inverse kinematics on the Pinocchio model
(:func:`~deepprompt_ros.robots.ik.solve_ik`, position only); the timing is the minimum-jerk profile
(:func:`~deepprompt_ros.sim.tasks.min_jerk.min_jerk`). Each demonstration carries the object's
position as its context ``object``. No simulator runs: the demonstrations are the plan itself.

:func:`context_reach_demos` is a smaller family for tests and benchmarks that need a trained
primitive within seconds: joint-space reaches from home whose final offset is linear in a 3-D
``object`` context (no IK).

It lives with the task demonstrators rather than in :mod:`deepprompt_ros.data` because it is one of
them: a scripted demonstrator built on a robot model, the IK and the minimum-jerk profile that the
PyBullet tasks share, and ``data`` sits below ``robots`` in the import order (the registry of
built-in datasets, :mod:`deepprompt_ros.data.builtin`, sits above both).
"""
from __future__ import annotations

import numpy as np

from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.data.demonstration import Demonstration
from deepprompt_ros.robots.ik import solve_ik
from deepprompt_ros.robots.kinematics import RobotKinematics
from deepprompt_ros.robots.spec import load_robot
from deepprompt_ros.sim.tasks.min_jerk import min_jerk

__all__ = ["reach_demos", "context_reach_demos"]


# Position-only damped least squares: 1 mrad from the limits, 200 steps, λ = 0.01, 10 µm tolerance,
# no null-space term, no step cap, the seed as given, the error as measured before the last step.
_POSITION_IK = dict(margin=1e-3, iterations=200, damping=1e-2, tol_position=1e-5, rest_gain=0.0,
                    max_step=None, clip_seed=False, measure_after_last_step=False)


def reach_demos(robot: str = "gen3_lite", n_demos: int = 120, n_points: int = 100, duration: float = 6.0,
                seed: int = 0, approach_height: float = 0.08,
                box: tuple[tuple[float, float], ...] = ((0.25, 0.45), (-0.2, 0.2), (0.02, 0.15))) -> DemoDataset:
    """Reaching demonstrations to objects placed uniformly in ``box`` (x, y, z ranges in m, base frame).

    Returns
    -------
    DemoDataset of ``n_demos`` demos, ``n_points`` samples over ``duration`` s, context ``object`` (3,).
    """
    spec = load_robot(robot)
    kin = RobotKinematics(spec)
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, n_points)
    demos = []
    while len(demos) < n_demos:
        obj = np.array([rng.uniform(*r) for r in box])
        goal, err, _ = solve_ik(kin, obj + [0.0, 0.0, approach_height], spec.home, **_POSITION_IK)
        if err > 1e-3:
            continue  # unreachable sample: the demonstrator would not show it
        lift = kin.forward_kinematics(spec.home).position * 0.5 + (obj + [0, 0, approach_height]) * 0.5
        lift[2] += rng.uniform(0.05, 0.15)
        mid, err_mid, _ = solve_ik(kin, lift, spec.home, **_POSITION_IK)
        if err_mid > 1e-3:
            continue
        # the wrist turns the gripper towards the object's bearing (a pure tool-axis rotation)
        goal[-1] = np.clip(spec.home[-1] + np.arctan2(obj[1], obj[0]), spec.lower[-1], spec.upper[-1])
        mid[-1] = 0.5 * (spec.home[-1] + goal[-1])
        # piecewise min-jerk through home → mid → goal, blended into one smooth path
        a = min_jerk(np.clip(s / 0.5, 0, 1))[:, None]
        b = min_jerk(np.clip((s - 0.5) / 0.5, 0, 1))[:, None]
        path = spec.home + a * (mid - spec.home) + b * (goal - mid)
        path = np.clip(path, spec.lower, spec.upper)
        demos.append(Demonstration(name=f"{robot}_reach_{len(demos):04d}", t=s * duration, q=path,
                                   joint_names=spec.joint_names, contexts={"object": obj[None, :]}))
    return DemoDataset(tuple(demos), source=f"reach_demos(robot={robot}, seed={seed})")


def context_reach_demos(n_demos: int = 40, n_points: int = 50, seed: int = 0) -> DemoDataset:
    """Joint-space reaches of the Gen3 lite (6 joints) from its home configuration over 6 s, with
    minimum-jerk timing: q(t) = home + 0.6 s(t/6) A c, where the context ``object`` c (3,) is
    uniform in [-0.5, 0.5]³ per demo and A (6, 3) is uniform in [-1, 1], drawn once per ``seed``.

    Returns
    -------
    DemoDataset of ``n_demos`` demos named ``d0``, ``d1``, ..., ``n_points`` samples each,
    context ``object`` (1, 3).
    """
    spec = load_robot("gen3_lite")
    rng = np.random.default_rng(seed)
    x = np.linspace(0, 1, n_points)
    s = min_jerk(x)
    a = rng.uniform(-1, 1, (6, 3))
    demos = [Demonstration(f"d{i}", x * 6.0, spec.home + s[:, None] * (a @ c)[None, :] * 0.6, spec.joint_names,
                           {"object": c[None]}) for i, c in enumerate(rng.uniform(-0.5, 0.5, (n_demos, 3)))]
    return DemoDataset(tuple(demos), source=f"context_reach_demos(seed={seed})")
