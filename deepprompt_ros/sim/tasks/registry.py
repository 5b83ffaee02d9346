"""Task datasets generated in PyBullet by scripted demonstrators (analogues of the paper's Sec. IV tasks).

The paper evaluates reconstruction on three RLBench tasks (Reach, Close Box, Pour Water) and a
Kinova Gen3 lite pick-and-place task; the Barrett WAM shaking task is the built-in
:func:`~deepprompt_ros.data.dataset.wam_shake`. RLBench (CoppeliaSim) cannot run here, so each task
below is re-created in PyBullet with a scripted demonstrator. Every demonstration has joint
trajectories (``t`` (T,), ``q`` (T, d), joint names), one low-dimensional context vector and
several camera images of the scene, in the format of :mod:`deepprompt_ros.data.dataset`.

Usage::

    from deepprompt_ros.sim.tasks.registry import make_task, TASKS
    train = make_task("reach", split="train")             # 500 demos, the paper's size
    quick = make_task("close_box", split="val", quick=True)

    python -m deepprompt_ros.sim.tasks.registry reach --out data/reach [--quick] [--split train] [--n 50]

The command writes ``DIR/train``, ``DIR/val``, ``DIR/test`` (each a dataset folder for
``train --data``) and ``DIR/task.json`` (task, seed, sizes, context layout, generation time).
``python -m deepprompt_ros.training.loop --builtin reach`` generates the full training split in
memory (with simulated execution: minutes, see below); generating once to a folder and training
with ``--data DIR/train`` avoids repeating that.

Tasks
-----
=====================  =========  ==================  ======  ========================  ===========
task                   robot      context (dim)       images  sizes train / val / test  quick
=====================  =========  ==================  ======  ========================  ===========
``reach``              WAM 7-DoF  ``target`` (3)      5       500 / 100 / 200 (paper)   20 / 5 / 10
``close_box``          WAM 7-DoF  ``box`` (4)         5       1000 / 100 / 200 (paper)  20 / 5 / 10
``pour``               WAM 7-DoF  ``pour`` (5)        5       1000 / 100 / 200 (paper)  20 / 5 / 10
``kinova_pick_place``  Gen3 lite  ``object_px`` (2),  3       80 / 10 / 10 (100 demos)  20 / 5 / 10
                       6-DoF      ``subtask`` (2)
=====================  =========  ==================  ======  ========================  ===========

The 7-DoF arm is the Barrett WAM of ``load_robot("wam")`` (the paper's own 7-DoF robot; its
URDF of simple shapes renders in ~2 ms at 64×64 where example-robot-data's Panda meshes take
~130 ms). Images are 64×64 RGB (``image_size``) rendered with PyBullet's tiny renderer of the
scene at the start of the demonstration: arm in its start configuration, objects placed per the
context. WAM tasks use five cameras (front, left shoulder, right shoulder, overhead, wrist — the
RLBench set-up); the Kinova task uses three images: the scene from the front camera, then the same
view and a side view with a yellow marker disc under the designated object (the paper: "a
picture of the object to be moved ... three additional pictures that contain markers on the
desired object").

Demonstrators. All of them compute via-poses of the end effector from the context, solve inverse
kinematics (:func:`solve_ik`: damped least squares on the Pinocchio model, seeded with the previous
via-configuration, joint limits kept with a 0.05 rad margin, null-space pull to the start posture),
and join the via-configurations with minimum-jerk quintic segments (:class:`ViaTrajectory`): zero
acceleration at every via-configuration, zero velocity at start / end / holds, monotone
(Fritsch–Butland) velocities elsewhere scaled by a per-demo "flow" factor, segment durations
from the joint distance with per-demo random factors, then the whole timing stretched until peak
velocities and accelerations are ≤ 85 % of the robot's limits. The trajectory is executed in the
PyBullet position control of :class:`~deepprompt_ros.sim.simulation.Simulation` (500 Hz, feed-forward
velocity) and the *simulated* joint states are recorded at ``n_points`` equally spaced times
(``simulate=False`` records the plan instead; the quick configuration does that by default),
including a 0.3 s settling tail. Simulated and planned joint positions differ by ≤ ~0.01 rad. Each demo draws
its randomness from its own generator seeded with (seed, task, split, index), so demos are
reproducible one by one; a demo whose plan fails (IK error > 2 mm / 0.05 rad, or a collision in
a kinematic sweep of the plan against the scene) is redrawn from that same generator.

``reach``
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
``close_box``
    A 16×22×10 cm box on the table at radius 0.5–0.72 m, bearing ±0.6 rad, yaw = bearing ±0.4 rad;
    its lid (hinge on the edge nearest the robot) is open by θ = 40–100°. The demonstrator brings the
    tool plate to the lid's outer face (at 65–95 % of the lid length, 2–3.5 cm off the face), then
    sweeps the lid's arc from θ to ~0° in 4–6 via-poses (tool axis between the face normal and
    straight down) and retreats 6–12 cm up. Context ``box`` = (θ rad, x m, y m, yaw rad) — the
    paper's Close Box context is "the angle of the box's lid and box location" (54-D RLBench
    state; here the 4 numbers that define it).
``pour``
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
``kinova_pick_place``
    Gen3 lite, a red 3 cm cube (yaw ±45°) and a green 9 cm square target on the table
    (x 0.24–0.46 m, |y| ≤ 0.2 m, ≥ 14 cm apart). Even-indexed demos are ``pick``: from the
    home pose (+ U(±0.05) rad) to 8–14 cm above the cube, down to the grasp (wrist yaw aligned
    with the cube), a 0.3–0.6 s hold (gripper closing), lift 6–12 cm. Odd-indexed demos are
    ``place``: starting with the cube held above a random pick location, carry it above the square,
    lower it onto the square, hold, retreat 6–10 cm up. Context ``object_px`` = normalized pixel
    position (u right, v down, in [0, 1]) in the front camera's image of the subtask's goal (the
    cube for pick, the square for place; :func:`project_point`, checked visible by ray casts), and
    ``subtask`` = one-hot (pick, place).

Generation time, measured on the project's 2-core machine while other jobs ran (load average
4.5-6.7), one process at ``nice 10``, 64×64 images, writing included:

=====================  ==============  ==================  ===========  =====================
full configuration     demos           wall (s/demo)       CPU (s/demo) demo length (s)
=====================  ==============  ==================  ===========  =====================
``reach``              800             237 s (0.30)        0.16         2.4-4.1
``close_box``          1300            559 s (0.43)        0.23         3.6-5.9
``pour``               1300            1745 s (1.34)       0.61         11.7-17.5
``kinova_pick_place``  100             44 s (0.44)         0.28         5.8-11.5
=====================  ==============  ==================  ===========  =====================

(``python -m deepprompt_ros.sim.tasks.registry NAME --out DIR``; the simulated execution at 250 Hz is
most of the cost, so time grows with the demo length.) The quick configuration (35 demos, plan
recorded) took 4.3 s (reach), 4.7 s (close_box), 3.6 s (pour) and 1.8 s (kinova_pick_place) for
the three splits. On disk (compressed .npz): reach 9.5 MB, close_box 16 MB, pour 16 MB,
kinova_pick_place 0.8 MB. In the full reach set, 46.6 % of the 500 training demos pass the
pillar on the left, every detour is ≥ 12 cm, and the simulated final tool position is within
0.1 mm of the target; 47.9 % of the pour demos tilt to the positive side.
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import pathlib
import sys
import time
from typing import Callable, Sequence

import numpy as np

from deepprompt_ros.data.dataset import DatasetError, Demonstration, DemoDataset
from deepprompt_ros.robots.geometry import quat_xyzw, rodrigues, rot_y, rot_z
from deepprompt_ros.robots.ik import solve_ik

__all__ = [
    "TASKS",
    "SPLITS",
    "TaskSpec",
    "ViaTrajectory",
    "make_task",
    "project_point",
    "main",
]

SPLITS = ("train", "val", "test")

#: Wall-clock seconds per demonstration of the full configuration (see the module docstring).
MEASURED_SECONDS_PER_DEMO = {"reach": 0.30, "close_box": 0.43, "pour": 1.34, "kinova_pick_place": 0.44}

# Planned peak velocity / acceleration as a fraction of the robot's limits.
_LIMIT_FRACTION = 0.85
# Physics step (s) of the recorded execution; position targets are streamed at every step (250 Hz).
_SIM_DT = 4e-3
_SETTLE = 0.3


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """Description of one task.

    Attributes
    ----------
    name : str
    robot : str
        Name for :func:`~deepprompt_ros.robots.spec.load_robot`.
    contexts : tuple of (str, int)
        Context modalities and their dimensions.
    n_images : int
        Images per demonstration.
    sizes, quick_sizes : tuple of 3 ints
        Number of demonstrations of the train, val and test splits (full / quick configuration).
    description : str
    """

    name: str
    robot: str
    contexts: tuple[tuple[str, int], ...]
    n_images: int
    sizes: tuple[int, int, int]
    quick_sizes: tuple[int, int, int]
    description: str

    def size(self, split: str, quick: bool = False) -> int:
        return (self.quick_sizes if quick else self.sizes)[SPLITS.index(split)]


# ----------------------------------------------------------------------------------------------
# Joint-space interpolation with minimum-jerk segments
# ----------------------------------------------------------------------------------------------
class ViaTrajectory:
    """Joint trajectory through via-configurations made of minimum-jerk (quintic) segments.

    Segment k joins (q_k, v_k, 0) at t_k to (q_{k+1}, v_{k+1}, 0) at t_{k+1}: the minimum-jerk
    curve between these boundary states is the quintic Hermite interpolant
    q(u) = H₀(u) q_k + h H₁(u) v_k + h H₂(u) v_{k+1} + H₃(u) q_{k+1}, u = (t − t_k)/h (Flash & Hogan
    1985), with H₀ = 1 − 10u³ + 15u⁴ − 6u⁵, H₁ = u − 6u³ + 8u⁴ − 3u⁵, H₂ = −4u³ + 7u⁴ − 3u⁵,
    H₃ = 10u³ − 15u⁴ + 6u⁵. Velocities: 0 at both ends and wherever a joint's motion reverses or
    stops (a repeated via-configuration is a hold); elsewhere the Fritsch–Butland weighted
    harmonic mean of the neighbouring slopes, times ``flow`` in [0, 1] (0 = stop at every via).

    Parameters
    ----------
    knots : array, shape (K, n)
        Via-configurations, K >= 2.
    durations : array, shape (K-1,)
        Segment durations (s), > 0.
    flow : float
    """

    def __init__(self, knots, durations, flow: float = 1.0):
        self.knots = np.asarray(knots, dtype=np.float64)
        self.durations = np.asarray(durations, dtype=np.float64)
        if self.knots.ndim != 2 or self.knots.shape[0] < 2:
            raise ValueError(f"knots must have shape (K, n) with K >= 2; got {self.knots.shape}")
        if self.durations.shape != (self.knots.shape[0] - 1,) or np.any(~(self.durations > 0)):
            raise ValueError(f"durations must be K-1 = {self.knots.shape[0] - 1} positive numbers; "
                             f"got {self.durations}")
        self.flow = float(flow)
        self.times = np.concatenate([[0.0], np.cumsum(self.durations)])
        self.velocities = self._knot_velocities()

    @property
    def duration(self) -> float:
        return float(self.times[-1])

    def _knot_velocities(self) -> np.ndarray:
        q, h = self.knots, self.durations
        d = np.diff(q, axis=0) / h[:, None]  # secant slopes, (K-1, n)
        v = np.zeros_like(q)
        for k in range(1, q.shape[0] - 1):
            d0, d1 = d[k - 1], d[k]
            w1, w2 = 2 * h[k] + h[k - 1], h[k] + 2 * h[k - 1]
            same = (d0 * d1) > 0
            with np.errstate(divide="ignore", invalid="ignore"):
                hm = (w1 + w2) / (w1 / d0 + w2 / d1)
            v[k] = np.where(same, hm, 0.0) * self.flow
        return v

    def scaled(self, factor: float) -> "ViaTrajectory":
        """The same path, ``factor`` times slower (velocities / factor, accelerations / factor²)."""
        return ViaTrajectory(self.knots, self.durations * factor, self.flow)

    def evaluate(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions, velocities and accelerations at times t, each shape (len(t), n).

        Times outside [0, duration] are clamped (the arm rests at the first / last knot).
        """
        t = np.clip(np.asarray(t, dtype=np.float64), 0.0, self.duration)
        k = np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.durations) - 1)
        h = self.durations[k][:, None]
        u = ((t - self.times[k]) / self.durations[k])[:, None]
        q0, q1 = self.knots[k], self.knots[k + 1]
        v0, v1 = self.velocities[k], self.velocities[k + 1]
        u2, u3, u4, u5 = u**2, u**3, u**4, u**5
        H0, H1, H2, H3 = (1 - 10 * u3 + 15 * u4 - 6 * u5, u - 6 * u3 + 8 * u4 - 3 * u5,
                          -4 * u3 + 7 * u4 - 3 * u5, 10 * u3 - 15 * u4 + 6 * u5)
        dH0, dH1, dH2 = (-30 * u2 + 60 * u3 - 30 * u4, 1 - 18 * u2 + 32 * u3 - 15 * u4,
                         -12 * u2 + 28 * u3 - 15 * u4)
        ddH0, ddH1, ddH2 = (-60 * u + 180 * u2 - 120 * u3, -36 * u + 96 * u2 - 60 * u3,
                            -24 * u + 84 * u2 - 60 * u3)
        q = H0 * q0 + h * H1 * v0 + h * H2 * v1 + H3 * q1
        qd = (dH0 * (q0 - q1)) / h + dH1 * v0 + dH2 * v1
        qdd = (ddH0 * (q0 - q1)) / h**2 + (ddH1 * v0 + ddH2 * v1) / h
        return q, qd, qdd

    def within_limits(self, spec, fraction: float = _LIMIT_FRACTION, rounds: int = 20) -> "ViaTrajectory":
        """The same path with every segment slowed down (only as much as needed) until
        |q̇| <= fraction·v_max and |q̈| <= fraction·a_max everywhere.

        A segment whose peak ratio r = max(|q̇|/v_lim, sqrt(|q̈|/a_lim)) exceeds 1 is stretched by
        r (velocities scale with 1/r, accelerations with 1/r²); knot velocities depend on the
        neighbouring durations, hence a few rounds.
        """
        traj = self
        m = 30
        u = (np.arange(m) + 0.5) / m
        for _ in range(rounds):
            t = (traj.times[:-1, None] + u[None, :] * traj.durations[:, None]).ravel()
            _, qd, qdd = traj.evaluate(t)
            rv = np.max(np.abs(qd) / (fraction * spec.velocity), axis=1).reshape(-1, m).max(axis=1)
            ra = np.max(np.abs(qdd) / (fraction * spec.acceleration), axis=1).reshape(-1, m).max(axis=1)
            r = np.maximum(rv, np.sqrt(ra))
            if np.all(r <= 1.0):
                return traj
            traj = ViaTrajectory(traj.knots, traj.durations * np.where(r > 1.0, r * 1.02, 1.0), traj.flow)
        return traj.scaled(float(max(1.0, r.max())) * 1.02)


def _segment_durations(knots: np.ndarray, spec, rng, minimum: float = 0.3,
                       spread: tuple[float, float] = (0.85, 1.3)) -> np.ndarray:
    """Per-segment durations: the slowest joint at an average 45 % of its velocity limit, randomized."""
    dist = np.max(np.abs(np.diff(knots, axis=0)) / (0.45 * spec.velocity), axis=1)
    return np.maximum(dist, minimum) * rng.uniform(*spread, size=len(dist))


# ----------------------------------------------------------------------------------------------
# Cameras and projection
# ----------------------------------------------------------------------------------------------
def project_point(camera, point, width: int, height: int) -> np.ndarray:
    """Normalized pixel position (u, v) of a world point in ``camera``'s image.

    Uses the same view / projection matrices as
    :meth:`~deepprompt_ros.sim.simulation.Simulation.camera_image` (PyBullet's
    ``computeViewMatrix`` / ``computeProjectionMatrixFOV``, OpenGL conventions): u = (x_ndc + 1)/2
    from the left edge, v = (1 − y_ndc)/2 from the top edge, so pixel column = u·width and
    row = v·height (pixel centres at half-integers).

    Parameters
    ----------
    camera : CameraPose
    point : array_like, shape (3,)
    width, height : int
        Image size in pixels (the aspect ratio matters).

    Returns
    -------
    uv : array, shape (2,)
    """
    import pybullet as pb

    view = np.array(pb.computeViewMatrix(camera.eye, camera.target, camera.up)).reshape(4, 4).T
    proj = np.array(pb.computeProjectionMatrixFOV(camera.fov_deg, width / height, camera.near,
                                                  camera.far)).reshape(4, 4).T
    clip = proj @ view @ np.append(np.asarray(point, dtype=np.float64), 1.0)
    ndc = clip[:3] / clip[3]
    return np.array([(ndc[0] + 1.0) / 2.0, (1.0 - ndc[1]) / 2.0])


def _wam_cameras():
    from deepprompt_ros.sim.simulation import CameraPose

    return (
        CameraPose(eye=(1.7, 0.0, 1.0), target=(0.5, 0.0, 0.25), fov_deg=50.0),        # front
        CameraPose(eye=(0.9, 1.15, 1.1), target=(0.5, 0.0, 0.25), fov_deg=55.0),       # left shoulder
        CameraPose(eye=(0.9, -1.15, 1.1), target=(0.5, 0.0, 0.25), fov_deg=55.0),      # right shoulder
        CameraPose(eye=(0.55, 0.0, 1.9), target=(0.55, 0.0, 0.0), up=(1.0, 0.0, 0.0), fov_deg=50.0),  # overhead
    )


def _wrist_camera(pose):
    """Camera on the tool plate looking along the tool axis (the 5th, moving camera)."""
    from deepprompt_ros.sim.simulation import CameraPose

    z, x = pose.rotation[:, 2], pose.rotation[:, 0]
    eye = pose.position + 0.02 * z
    return CameraPose(eye=tuple(eye), target=tuple(eye + 0.5 * z), up=tuple(x), fov_deg=70.0, near=0.01)


def _kinova_cameras():
    from deepprompt_ros.sim.simulation import CameraPose

    return (
        CameraPose(eye=(0.95, 0.0, 0.55), target=(0.34, 0.0, 0.0), fov_deg=42.0),       # front
        CameraPose(eye=(0.45, -0.75, 0.6), target=(0.34, 0.0, 0.0), fov_deg=48.0),      # side
    )


# ----------------------------------------------------------------------------------------------
# The scene: one Simulation reused for all demos of a make_task call
# ----------------------------------------------------------------------------------------------
class _Scene:
    """A Simulation with a table, temporary objects, collision sweeps, images and execution."""

    def __init__(self, robot: str, image_size: int):
        from deepprompt_ros.sim.simulation import Simulation

        self.sim = Simulation(robot, timestep=_SIM_DT, ground=False)
        self.spec = self.sim.spec
        self.kin = self.sim.kinematics
        self.image_size = image_size
        self.bodies = {"table": self.sim.spawn_object("table", "box", (3.0, 3.0, 0.02), (0.0, 0.0, -0.01),
                                                      rgba=(0.55, 0.55, 0.52, 1.0), mass=0.0)}
        self.temp: list[str] = []

    def close(self) -> None:
        self.sim.close()

    def add(self, name: str, shape: str, size, position, R=None, rgba=(0.85, 0.1, 0.1, 1.0)) -> int:
        orn = (0.0, 0.0, 0.0, 1.0) if R is None else tuple(quat_xyzw(R))
        body = self.sim.spawn_object(name, shape, size, position, orn, rgba=rgba, mass=0.0)
        self.temp.append(name)
        self.bodies[name] = body
        return body

    def clear(self) -> None:
        for name in self.temp:
            self.sim.remove_object(name)
            del self.bodies[name]
        self.temp = []

    def body(self, name: str) -> int:
        return self.bodies[name]

    def collides(self, traj: ViaTrajectory, names: Sequence[str], margin: float = 0.01,
                 samples_per_segment: int = 12, table_from_link: int | None = 3) -> bool:
        """Kinematic sweep of the plan: any robot link within ``margin`` of the named objects
        (or, for links from index ``table_from_link`` on, of the table)?"""
        import pybullet as pb

        c, robot = self.sim.client_id, self.sim.robot_id
        bodies = [self.body(n) for n in names]
        table = self.body("table")
        n_links = pb.getNumJoints(robot, physicsClientId=c)
        t = np.linspace(0.0, traj.duration, samples_per_segment * len(traj.durations) + 1)
        q_path, _, _ = traj.evaluate(t)
        hit = False
        for q in q_path:
            self.sim.reset(q)
            for b in bodies:
                if pb.getClosestPoints(robot, b, margin, physicsClientId=c):
                    hit = True
                    break
            if not hit and table_from_link is not None:
                for li in range(table_from_link, n_links):
                    if pb.getClosestPoints(robot, table, 0.005, linkIndexA=li, physicsClientId=c):
                        hit = True
                        break
            if hit:
                break
        return hit

    def images(self, q0, cameras, wrist: bool = False) -> list[np.ndarray]:
        self.sim.reset(q0)
        s = self.image_size
        out = [self.sim.camera_image(s, s, camera=cam) for cam in cameras]
        if wrist:
            out.append(self.sim.camera_image(s, s, camera=_wrist_camera(self.kin.forward_kinematics(q0))))
        return out

    def visible(self, camera, name: str, points: np.ndarray) -> float:
        """Fraction of the rays from the camera to ``points`` (on object ``name``) that hit it first."""
        import pybullet as pb

        eye = np.asarray(camera.eye)
        ends = points + 0.003 * (eye - points) / np.linalg.norm(eye - points, axis=1, keepdims=True)
        res = pb.rayTestBatch([tuple(eye)] * len(points), [tuple(p) for p in ends],
                              physicsClientId=self.sim.client_id)
        body = self.body(name)
        ok = [r[0] in (-1, body) for r in res]
        return float(np.mean(ok))

    def execute(self, traj: ViaTrajectory, n_points: int, simulate: bool) -> tuple[np.ndarray, np.ndarray]:
        """Run the plan (plus a settling tail) and record ``n_points`` equally spaced joint states.

        Returns
        -------
        t : array, shape (n_points,); q : array, shape (n_points, n)
        """
        total = traj.duration + _SETTLE
        n_steps = int(math.ceil(total / _SIM_DT))
        sample_steps = np.round(np.linspace(0, n_steps, n_points)).astype(int)
        t = sample_steps * _SIM_DT
        if not simulate:
            q, _, _ = traj.evaluate(t)
            return t, self.spec.clip_positions(q)
        q_ref, qd_ref, _ = traj.evaluate(np.arange(n_steps + 1) * _SIM_DT)
        qd_ref = np.clip(qd_ref, -self.spec.velocity, self.spec.velocity)
        sim = self.sim
        sim.reset(q_ref[0])
        rec = np.empty((n_points, self.spec.n_joints))
        j = 0
        for k in range(n_steps + 1):
            while j < n_points and sample_steps[j] == k:
                rec[j] = sim.joint_state().position
                j += 1
            if k == n_steps:
                break
            sim.set_position_targets(q_ref[k + 1], qd_ref[k + 1])
            sim.step()
        return t, self.spec.clip_positions(rec)


class _Rejected(Exception):
    """The sampled scene cannot be demonstrated (IK failure or collision): draw again."""


def _ik(scene: _Scene, position, seed, *, rest=None, axis=None, rotation=None,
        tol_position: float = 2e-3, tol_angle: float = 0.05) -> np.ndarray:
    res = solve_ik(scene.kin, position, seed, axis=axis, rotation=rotation, rest=rest)
    if res.position_error > tol_position or res.angle_error > tol_angle:
        raise _Rejected(f"IK error {res.position_error:.4f} m / {res.angle_error:.3f} rad")
    return res.q


def _plan(scene: _Scene, knots, rng, holds: dict[int, float] | None = None,
          flow: tuple[float, float] = (0.5, 1.0)) -> ViaTrajectory:
    """Min-jerk trajectory through ``knots``; ``holds`` maps a knot index to a hold time (s)
    (the knot is repeated, the segment between the copies lasts that long)."""
    knots = [np.asarray(k, dtype=np.float64) for k in knots]
    spec = scene.spec
    durations = list(_segment_durations(np.array(knots), spec, rng))
    if holds:
        for idx in sorted(holds, reverse=True):
            knots.insert(idx + 1, knots[idx].copy())
            durations.insert(idx, holds[idx])
    traj = ViaTrajectory(np.array(knots), np.array(durations), flow=rng.uniform(*flow))
    return traj.within_limits(spec)


def _jitter_start(spec, rng, scale: float) -> np.ndarray:
    return spec.clip_positions(spec.home + rng.uniform(-scale, scale, spec.n_joints))


# ----------------------------------------------------------------------------------------------
# Demonstrators. Each returns (contexts, images, trajectory) or raises _Rejected.
# ----------------------------------------------------------------------------------------------
_DOWN = np.array([0.0, 0.0, -1.0])
_WAM_SHOULDER = np.array([0.0, 0.0, 0.346])  # J1/J2 axes intersection, wam.urdf [B4]


def _demo_reach(scene: _Scene, rng, index: int):
    spec = scene.spec
    q0 = _jitter_start(spec, rng, 0.08)
    p0 = scene.kin.forward_kinematics(q0).position
    r, b, z = rng.uniform(0.45, 0.8), rng.uniform(-0.9, 0.9), rng.uniform(0.08, 0.45)
    target = np.array([r * math.cos(b), r * math.sin(b), z])
    d = target[:2] - p0[:2]
    L = float(np.linalg.norm(d))
    if L < 0.3 or np.linalg.norm(target - _WAM_SHOULDER) > 0.82:
        raise _Rejected("target too close to the start or out of reach")
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
        q = _ik(scene, p, q, rest=q0, axis=_DOWN)
        knots.append(q)
    traj = _plan(scene, knots, rng)
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
        raise _Rejected("the plan hits the pillar or a distractor")
    images = scene.images(q0, _wam_cameras(), wrist=True)
    return {"target": target}, images, traj


# Box of close_box (m): depth along its x (hinge edge at -x, nearest the robot), width, height, lid.
_BOX_L, _BOX_W, _BOX_H, _LID_T = 0.16, 0.22, 0.10, 0.01


def _demo_close_box(scene: _Scene, rng, index: int):
    spec = scene.spec
    q0 = _jitter_start(spec, rng, 0.08)
    theta = math.radians(rng.uniform(40.0, 100.0))
    r, b = rng.uniform(0.5, 0.72), rng.uniform(-0.6, 0.6)
    x, y, yaw = r * math.cos(b), r * math.sin(b), b + rng.uniform(-0.4, 0.4)
    Rb = rot_z(yaw)
    origin = np.array([x, y, 0.0])

    def world(p_local):
        return origin + Rb @ p_local

    hinge = np.array([-_BOX_L / 2, 0.0, _BOX_H])
    rho, delta = rng.uniform(0.65, 0.95), rng.uniform(0.02, 0.035)
    kappa = rng.uniform(0.2, 0.5)  # how much the tool axis leans towards straight down

    def normal(phi):  # outer normal of the lid opened by phi (box frame)
        return np.array([-math.sin(phi), 0.0, math.cos(phi)])

    def contact(phi):
        return hinge + rho * _BOX_L * np.array([math.cos(phi), 0.0, math.sin(phi)]) + (_LID_T / 2 + delta) * normal(phi)

    def tool_axis(phi):
        a = (1 - kappa) * (Rb @ -normal(phi)) + kappa * _DOWN
        return a / np.linalg.norm(a)

    pre = contact(theta) + rng.uniform(0.06, 0.12) * normal(theta) + [0.0, 0.0, rng.uniform(0.0, 0.06)]
    m = int(rng.integers(4, 7))
    phi_end = math.radians(rng.uniform(0.0, 3.0))
    phis = np.linspace(theta, phi_end, m)
    retreat = contact(phi_end) + np.array([-rng.uniform(0.0, 0.05), 0.0, rng.uniform(0.06, 0.12)])
    poses = [(world(pre), tool_axis(theta))] + [(world(contact(p)), tool_axis(p)) for p in phis]
    poses.append((world(retreat), _DOWN))
    knots, q = [q0], q0
    for p, a in poses:
        q = _ik(scene, p, q, rest=q0, axis=a)
        knots.append(q)
    traj = _plan(scene, knots, rng)
    scene.add("box", "box", (_BOX_L, _BOX_W, _BOX_H), world(np.array([0.0, 0.0, _BOX_H / 2])), R=Rb,
              rgba=(0.75, 0.55, 0.3, 1.0))
    R_lid = Rb @ rot_y(-theta)
    lid_center = hinge + (_BOX_L / 2) * np.array([math.cos(theta), 0.0, math.sin(theta)])
    scene.add("lid", "box", (_BOX_L, _BOX_W, _LID_T), world(lid_center), R=R_lid, rgba=(0.85, 0.2, 0.15, 1.0))
    if scene.collides(traj, ["box"], margin=0.0):
        raise _Rejected("the plan hits the box")
    images = scene.images(q0, _wam_cameras(), wrist=True)
    return {"box": np.array([theta, x, y, yaw])}, images, traj


# Cup and pot of pour (m).
_CUP_R, _CUP_H, _POT_R = 0.035, 0.11, 0.06


def _tilted_axis(bearing: float, tilt: float) -> np.ndarray:
    """Unit tool axis pointing away from the base at ``bearing``, ``tilt`` rad below horizontal."""
    return np.array([math.cos(bearing) * math.cos(tilt), math.sin(bearing) * math.cos(tilt), -math.sin(tilt)])


def _demo_pour(scene: _Scene, rng, index: int):
    spec = scene.spec
    q0 = _jitter_start(spec, rng, 0.08)
    r, b = rng.uniform(0.55, 0.8), rng.uniform(-0.7, 0.7)
    cup = np.array([r * math.cos(b), r * math.sin(b)])
    r, b = rng.uniform(0.5, 0.8), rng.uniform(-0.8, 0.8)
    pot = np.array([r * math.cos(b), r * math.sin(b)])
    pot_h = rng.uniform(0.05, 0.16)
    if np.linalg.norm(cup - pot) < 0.2:
        raise _Rejected("cup and pot too close")
    hold = _CUP_R + 0.005  # the cup's axis is this far along the tool axis from the tool plate
    # grasp from the side and above: tool axis towards the cup, 30-50 deg below horizontal
    a_g = _tilted_axis(math.atan2(cup[1], cup[0]) + rng.uniform(-0.25, 0.25), math.radians(rng.uniform(30, 50)))
    p_grasp = np.append(cup, _CUP_H * rng.uniform(0.45, 0.7)) - hold * a_g
    p_pre = p_grasp - rng.uniform(0.08, 0.14) * a_g + [0.0, 0.0, rng.uniform(0.0, 0.04)]
    p_lift = p_grasp + [0.0, 0.0, rng.uniform(0.12, 0.2)]
    a_p = _tilted_axis(math.atan2(pot[1], pot[0]) + rng.uniform(-0.25, 0.25), math.radians(rng.uniform(30, 50)))
    sign = 1.0 if rng.random() < 0.5 else -1.0  # the mode: tilt towards one side or the other
    tilt = sign * rng.uniform(1.4, 2.0)
    # Rolling J7 (axis = tool axis a_p) by `tilt` turns the cup's axis from z to R z; place the cup
    # so that its mouth (half a cup height along that axis) ends above the pot's centre.
    up = rodrigues(a_p, tilt) @ np.array([0.0, 0.0, 1.0])
    mouth = np.append(pot, pot_h + rng.uniform(0.08, 0.14))
    centre = mouth - (_CUP_H / 2) * up
    p_pour = centre - hold * a_p
    p_carry = 0.5 * (p_lift + p_pour) + [0.0, 0.0, rng.uniform(0.03, 0.1)]
    a_c = (a_g + a_p) / max(np.linalg.norm(a_g + a_p), 1e-6)
    j7 = rng.uniform(-0.3, 0.3)  # J7 rolls about the tool axis: free for these 5-D via-poses
    knots, q = [q0], q0
    for p, a in ((p_pre, a_g), (p_grasp, a_g), (p_lift, a_g), (p_carry, a_c), (p_pour, a_p)):
        q = _ik(scene, p, q, rest=q0, axis=a)
        q[-1] = j7
        knots.append(q)
    q_tilt = knots[-1].copy()
    q_tilt[-1] = j7 + tilt
    knots += [q_tilt, knots[-1].copy()]
    # holds: gripper closing at the grasp (knot 2) and pouring (the tilted knot 6)
    traj = _plan(scene, knots, rng, holds={2: rng.uniform(0.2, 0.5), 6: rng.uniform(0.4, 1.0)})
    scene.add("cup", "cylinder", (_CUP_R, _CUP_H), np.append(cup, _CUP_H / 2), rgba=(0.2, 0.45, 0.9, 1.0))
    scene.add("pot", "cylinder", (_POT_R, pot_h), np.append(pot, pot_h / 2), rgba=(0.55, 0.3, 0.15, 1.0))
    scene.add("plant", "sphere", (0.035,), np.append(pot, pot_h + 0.015), rgba=(0.15, 0.65, 0.2, 1.0))
    if scene.collides(traj, ["pot", "plant"], margin=0.005):
        raise _Rejected("the plan hits the pot")
    images = scene.images(q0, _wam_cameras(), wrist=True)
    return {"pour": np.array([cup[0], cup[1], pot[0], pot[1], pot_h])}, images, traj


_CUBE, _SQUARE = 0.03, 0.09
_TOOL_DOWN = np.diag([1.0, -1.0, -1.0])  # Gen3 lite tool_frame pointing down at home


def _kinova_sample_xy(rng):
    return np.array([rng.uniform(0.24, 0.46), rng.uniform(-0.2, 0.2)])


def _demo_kinova(scene: _Scene, rng, index: int):
    spec = scene.spec
    obj, square = _kinova_sample_xy(rng), _kinova_sample_xy(rng)
    if np.linalg.norm(obj - square) < 0.14:
        raise _Rejected("cube and square too close")
    psi = rng.uniform(-math.pi / 4, math.pi / 4)
    pick = index % 2 == 0
    cams = _kinova_cameras()
    if pick:
        q0 = _jitter_start(spec, rng, 0.05)
        R_g = rot_z(psi) @ _TOOL_DOWN
        p_pre = np.append(obj, _CUBE / 2 + rng.uniform(0.08, 0.14))
        p_grasp = np.append(obj, rng.uniform(0.012, 0.02))
        p_lift = p_grasp + [0.0, 0.0, rng.uniform(0.06, 0.12)]
        knots, q = [q0], q0
        for p in (p_pre, p_grasp, p_lift):
            q = _ik(scene, p, q, rest=q0, rotation=R_g)
            knots.append(q)
        traj = _plan(scene, knots, rng, holds={2: rng.uniform(0.3, 0.6)})
        goal_name, goal_point = "cube", np.append(obj, _CUBE / 2)
        cube_pos, cube_R = np.append(obj, _CUBE / 2), rot_z(psi)
    else:
        held_yaw = rng.uniform(-0.5, 0.5)
        R_c = rot_z(held_yaw) @ _TOOL_DOWN
        p_start = np.append(obj, rng.uniform(0.08, 0.14))
        q0 = _ik(scene, p_start, spec.home, rest=spec.home, rotation=R_c)
        p_above = np.append(square, rng.uniform(0.08, 0.14))
        p_mid = 0.5 * (p_start + p_above) + [0.0, 0.0, rng.uniform(0.0, 0.06)]
        p_place = np.append(square, 0.004 + _CUBE / 2 + rng.uniform(0.0, 0.01))
        p_retreat = p_place + [0.0, 0.0, rng.uniform(0.06, 0.1)]
        knots, q = [q0], q0
        for p in (p_mid, p_above, p_place, p_retreat):
            q = _ik(scene, p, q, rest=q0, rotation=R_c)
            knots.append(q)
        traj = _plan(scene, knots, rng, holds={3: rng.uniform(0.3, 0.6)})
        goal_name, goal_point = "square", np.append(square, 0.002)
    if scene.collides(traj, []):
        raise _Rejected("the plan touches the table")
    if not pick:
        pose0 = scene.kin.forward_kinematics(q0)
        cube_pos, cube_R = pose0.position, pose0.rotation
    scene.add("square", "box", (_SQUARE, _SQUARE, 0.004), np.append(square, 0.002), rgba=(0.1, 0.7, 0.2, 1.0))
    scene.add("cube", "box", (_CUBE,) * 3, cube_pos, R=cube_R, rgba=(0.9, 0.1, 0.1, 1.0))
    scene.sim.reset(q0)
    half = (_CUBE if goal_name == "cube" else _SQUARE) * 0.4
    top = goal_point + [0.0, 0.0, _CUBE / 2 if goal_name == "cube" else 0.002]
    pts = np.array([top + [dx, dy, 0.0] for dx in (-half, 0.0, half) for dy in (-half, 0.0, half)])
    if scene.visible(cams[0], goal_name, pts) < 0.99:
        raise _Rejected(f"the {goal_name} is hidden from the front camera")
    s = scene.image_size
    uv = project_point(cams[0], goal_point, s, s)
    images = scene.images(q0, cams[:1])
    radius = 0.045 if goal_name == "cube" else 0.075
    scene.add("marker", "cylinder", (radius, 0.002), np.append(goal_point[:2], 0.001),
              rgba=(1.0, 0.85, 0.0, 1.0))
    images += scene.images(q0, cams)
    contexts = {"object_px": uv, "subtask": np.array([1.0, 0.0] if pick else [0.0, 1.0])}
    return contexts, images, traj


TASKS: dict[str, TaskSpec] = {
    "reach": TaskSpec("reach", "wam", (("target", 3),), 5, (500, 100, 200), (20, 5, 10),
                      "WAM reaches a red sphere, passing a pillar on the left or right (bimodal)"),
    "close_box": TaskSpec("close_box", "wam", (("box", 4),), 5, (1000, 100, 200), (20, 5, 10),
                          "WAM pushes the open lid of a box shut"),
    "pour": TaskSpec("pour", "wam", (("pour", 5),), 5, (1000, 100, 200), (20, 5, 10),
                     "WAM grasps a cup, carries it over a pot and pours (tilt to either side)"),
    "kinova_pick_place": TaskSpec("kinova_pick_place", "gen3_lite", (("object_px", 2), ("subtask", 2)), 3,
                                  (80, 10, 10), (20, 5, 10),
                                  "Gen3 lite picks a cube (subtask pick) or places it on a square (place)"),
}

_DEMONSTRATORS = {"reach": _demo_reach, "close_box": _demo_close_box, "pour": _demo_pour,
                  "kinova_pick_place": _demo_kinova}
_TASK_CODE = {"reach": 1, "close_box": 2, "pour": 3, "kinova_pick_place": 4}
_MAX_DRAWS = 500


def make_task(name: str, split: str = "train", n: int | None = None, quick: bool = False, seed: int = 0, *,
              n_points: int = 100, image_size: int = 64, simulate: bool | None = None,
              progress: Callable[[int, int], None] | None = None) -> DemoDataset:
    """Generate the demonstrations of one split of a task.

    Parameters
    ----------
    name : str
        One of :data:`TASKS`.
    split : {"train", "val", "test"}
        Splits use independent random streams (the same seed never repeats a scene across splits).
    n : int, optional
        Number of demonstrations; default the split's size (:attr:`TaskSpec.sizes`, or
        :attr:`TaskSpec.quick_sizes` with ``quick``). Demo i is the same whatever n is.
    quick : bool
        Use the quick sizes (20 / 5 / 10).
    seed : int
        Seed (>= 0) of the whole dataset.
    n_points : int
        Samples per demonstration (2..500), equally spaced in time.
    image_size : int
        Width = height of the images (16..512 pixels).
    simulate : bool, optional
        True: execute the plan in PyBullet's position control and record the simulated joint
        states; False: record the plan itself (~5-15x faster). Default: True, False with ``quick``.
    progress : callable (done, total), optional
        Called after each demonstration.

    Returns
    -------
    DemoDataset
        ``n`` demonstrations: t (n_points,), q (n_points, d), contexts per :attr:`TaskSpec.contexts`,
        images (n_images, image_size, image_size, 3) uint8.

    Raises
    ------
    ValueError
        Unknown task or split, or an argument out of range (the message says what is expected).
    """
    if name not in TASKS:
        raise ValueError(f"unknown task '{name}'; available tasks: {', '.join(TASKS)}")
    if split not in SPLITS:
        raise ValueError(f"unknown split '{split}' of task '{name}'; expected one of {', '.join(SPLITS)}")
    task = TASKS[name]
    if n is None:
        n = task.size(split, quick)
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"number of demonstrations n must be an integer >= 1; got {n!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be an integer >= 0; got {seed!r}")
    if isinstance(n_points, bool) or not isinstance(n_points, (int, np.integer)) or not 2 <= n_points <= 500:
        raise ValueError(f"n_points must be an integer in 2..500 (samples per demonstration); got {n_points!r}")
    if isinstance(image_size, bool) or not isinstance(image_size, (int, np.integer)) or not 16 <= image_size <= 512:
        raise ValueError(f"image_size must be an integer in 16..512 (pixels per side); got {image_size!r}")
    simulate = (not quick) if simulate is None else bool(simulate)
    demonstrator = _DEMONSTRATORS[name]
    scene = _Scene(task.robot, int(image_size))
    demos = []
    try:
        for i in range(int(n)):
            key = (_TASK_CODE[name], SPLITS.index(split), i)  # demo i's own stream
            rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=key))
            last = ""
            for _ in range(_MAX_DRAWS):
                try:
                    contexts, images, traj = demonstrator(scene, rng, i)
                    break
                except _Rejected as exc:
                    last = str(exc)
                finally:
                    scene.clear()
            else:  # pragma: no cover - the samplers are tuned to succeed within a few draws
                raise RuntimeError(f"task '{name}': no feasible scene for demo {i} in {_MAX_DRAWS} draws ({last})")
            t, q = scene.execute(traj, int(n_points), bool(simulate))
            ctx = {k: np.asarray(v, dtype=np.float64)[None, :] for k, v in contexts.items()}
            demos.append(Demonstration(name=f"{name}_{split}_{i:05d}", t=t, q=q,
                                       joint_names=scene.spec.joint_names, contexts=ctx,
                                       images=np.stack(images).astype(np.uint8)))
            if progress is not None:
                progress(i + 1, int(n))
    finally:
        scene.close()
    source = f"tasks.make_task('{name}', split='{split}', n={n}, seed={seed}, simulate={bool(simulate)})"
    return DemoDataset(tuple(demos), source=source)


# ----------------------------------------------------------------------------------------------
# Command line
# ----------------------------------------------------------------------------------------------
def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m deepprompt_ros.sim.tasks.registry",
        description="Generate a task dataset (PyBullet, scripted demonstrator) in the .npz demonstration "
                    "format: OUT/train, OUT/val, OUT/test and OUT/task.json.")
    ap.add_argument("task", help=f"task name: {' | '.join(TASKS)}")
    ap.add_argument("--out", required=True, help="output folder (created)")
    ap.add_argument("--quick", action="store_true", help="quick sizes (20/5/10 demos) instead of the full ones")
    ap.add_argument("--split", default="all", help="train | val | test | all (default: all)")
    ap.add_argument("--n", type=int, help="demonstrations per split (overrides the sizes)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--n-points", type=int, default=100, help="samples per demonstration (default 100)")
    ap.add_argument("--image-size", type=int, default=64, help="image width = height (default 64)")
    sim = ap.add_mutually_exclusive_group()
    sim.add_argument("--sim", dest="simulate", action="store_const", const=True,
                     help="record the simulated execution (default without --quick)")
    sim.add_argument("--no-sim", dest="simulate", action="store_const", const=False,
                     help="record the plan (default with --quick)")
    args = ap.parse_args(argv)
    if args.task not in TASKS:
        ap.error(f"unknown task '{args.task}'; available tasks: {', '.join(TASKS)}")
    if args.split != "all" and args.split not in SPLITS:
        ap.error(f"unknown split '{args.split}'; expected one of {', '.join(SPLITS)} or all")
    splits = SPLITS if args.split == "all" else (args.split,)
    out = pathlib.Path(args.out)
    task = TASKS[args.task]
    simulate = (not args.quick) if args.simulate is None else args.simulate
    manifest = {"task": args.task, "robot": task.robot, "description": task.description, "seed": args.seed,
                "quick": args.quick, "simulate": simulate, "n_points": args.n_points,
                "image_size": args.image_size, "n_images": task.n_images,
                "contexts": dict(task.contexts), "splits": {}}
    t_all = time.perf_counter()
    for split in splits:
        n = args.n if args.n is not None else task.size(split, args.quick)
        t0 = time.perf_counter()
        step = max(1, n // 20)

        def report(done, total, split=split, t0=t0, step=step):
            if done % step == 0 or done == total:
                el = time.perf_counter() - t0
                print(f"[{args.task}/{split}] {done}/{total} demos  {el:.1f} s  ({el / done:.3f} s/demo)",
                      file=sys.stderr, flush=True)

        try:
            ds = make_task(args.task, split, n=n, quick=args.quick, seed=args.seed, n_points=args.n_points,
                           image_size=args.image_size, simulate=simulate, progress=report)
        except (ValueError, DatasetError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        folder = ds.save(out / split)
        el = time.perf_counter() - t0
        manifest["splits"][split] = {"n": len(ds), "folder": str(folder), "seconds": round(el, 2),
                                     "seconds_per_demo": round(el / len(ds), 4)}
        print(f"[{args.task}/{split}] wrote {len(ds)} demonstrations to {folder}", file=sys.stderr, flush=True)
    manifest["seconds"] = round(time.perf_counter() - t_all, 2)
    manifest["created"] = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    out.mkdir(parents=True, exist_ok=True)
    (out / "task.json").write_text(json.dumps(manifest, indent=2) + "\n")
    print(f"[{args.task}] done in {manifest['seconds']:.1f} s; dataset in {out.resolve()} "
          f"(description: {out / 'task.json'})", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
