"""The scene of a task and the steps every scripted demonstrator takes in it.

Every demonstrator computes via-poses of the end effector from the context, solves inverse
kinematics (:func:`~deepprompt_ros.robots.ik.solve_ik`: damped least squares on the Pinocchio model,
seeded with the previous via-configuration, joint limits kept with a 0.05 rad margin, null-space
pull to the start posture), and joins the via-configurations with minimum-jerk quintic segments
(:class:`~deepprompt_ros.sim.tasks.trajectory.ViaTrajectory`): zero acceleration at every
via-configuration, zero velocity at start / end / holds, monotone (Fritsch–Butland) velocities
elsewhere scaled by a per-demo "flow" factor, segment durations from the joint distance with
per-demo random factors, then the whole timing stretched until peak velocities and accelerations
are ≤ 85 % of the robot's limits. The trajectory is executed in the PyBullet position control of
:class:`~deepprompt_ros.sim.simulation.Simulation` (250 Hz, feed-forward velocity) and the
*simulated* joint states are recorded at ``n_points`` equally spaced times (``simulate=False``
records the plan instead; the quick configuration does that by default), including a 0.3 s
settling tail. Simulated and planned joint positions differ by ≤ ~0.01 rad. Each demo draws its
randomness from its own generator seeded with (seed, task, split, index), so demos are
reproducible one by one; a demo whose plan fails (IK error > 2 mm / 0.05 rad, or a collision in a
kinematic sweep of the plan against the scene) is redrawn from that same generator.

:class:`Scene` is one :class:`~deepprompt_ros.sim.simulation.Simulation` (a table, the task's
objects, the cameras of :func:`wam_cameras` / :func:`kinova_cameras`) reused for every demo of a
``make_task`` call; :func:`ik`, :func:`plan` and :func:`jitter_start` are the demonstrators' planning
steps, :class:`Rejected` their way of asking for a new draw.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import pybullet as pb

from deepprompt_ros.robots.geometry import quat_xyzw
from deepprompt_ros.robots.ik import solve_ik
from deepprompt_ros.robots.kinematics import FramePose
from deepprompt_ros.sim.camera import CameraPose
from deepprompt_ros.sim.simulation import Simulation
from deepprompt_ros.sim.tasks.trajectory import ViaTrajectory, segment_durations

__all__ = ["SIM_DT", "SETTLE", "DOWN", "Scene", "Rejected", "ik", "plan", "jitter_start", "wam_cameras",
           "wrist_camera", "kinova_cameras"]

#: Physics step (s) of the recorded execution; position targets are streamed at every step (250 Hz).
SIM_DT = 4e-3
#: Settling time (s) recorded after the end of the plan.
SETTLE = 0.3
#: Tool axis pointing straight down.
DOWN = np.array([0.0, 0.0, -1.0])


# ----------------------------------------------------------------------------------------------
# Cameras
# ----------------------------------------------------------------------------------------------
def wam_cameras() -> tuple[CameraPose, ...]:
    """The four fixed cameras of the WAM tasks: front, left shoulder, right shoulder, overhead."""
    return (
        CameraPose(eye=(1.7, 0.0, 1.0), target=(0.5, 0.0, 0.25), fov_deg=50.0),        # front
        CameraPose(eye=(0.9, 1.15, 1.1), target=(0.5, 0.0, 0.25), fov_deg=55.0),       # left shoulder
        CameraPose(eye=(0.9, -1.15, 1.1), target=(0.5, 0.0, 0.25), fov_deg=55.0),      # right shoulder
        CameraPose(eye=(0.55, 0.0, 1.9), target=(0.55, 0.0, 0.0), up=(1.0, 0.0, 0.0), fov_deg=50.0),  # overhead
    )


def wrist_camera(pose: FramePose) -> CameraPose:
    """Camera on the tool plate looking along the tool axis (the 5th, moving camera)."""
    z, x = pose.rotation[:, 2], pose.rotation[:, 0]
    eye = pose.position + 0.02 * z
    return CameraPose(eye=tuple(eye), target=tuple(eye + 0.5 * z), up=tuple(x), fov_deg=70.0, near=0.01)


def kinova_cameras() -> tuple[CameraPose, ...]:
    """The cameras of the Kinova task: front, side."""
    return (
        CameraPose(eye=(0.95, 0.0, 0.55), target=(0.34, 0.0, 0.0), fov_deg=42.0),       # front
        CameraPose(eye=(0.45, -0.75, 0.6), target=(0.34, 0.0, 0.0), fov_deg=48.0),      # side
    )


# ----------------------------------------------------------------------------------------------
# The scene: one Simulation reused for all demos of a make_task call
# ----------------------------------------------------------------------------------------------
class Scene:
    """A Simulation with a table, temporary objects, collision sweeps, images and execution."""

    def __init__(self, robot: str, image_size: int):
        self.sim = Simulation(robot, timestep=SIM_DT, ground=False)
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
            out.append(self.sim.camera_image(s, s, camera=wrist_camera(self.kin.forward_kinematics(q0))))
        return out

    def visible(self, camera, name: str, points: np.ndarray) -> float:
        """Fraction of the rays from the camera to ``points`` (on object ``name``) that hit it first."""
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
        total = traj.duration + SETTLE
        n_steps = int(math.ceil(total / SIM_DT))
        sample_steps = np.round(np.linspace(0, n_steps, n_points)).astype(int)
        t = sample_steps * SIM_DT
        if not simulate:
            q, _, _ = traj.evaluate(t)
            return t, self.spec.clip_positions(q)
        q_ref, qd_ref, _ = traj.evaluate(np.arange(n_steps + 1) * SIM_DT)
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


# ----------------------------------------------------------------------------------------------
# Planning steps of the demonstrators
# ----------------------------------------------------------------------------------------------
class Rejected(Exception):
    """The sampled scene cannot be demonstrated (IK failure or collision): draw again."""


def ik(scene: Scene, position, seed, *, rest=None, axis=None, rotation=None,
       tol_position: float = 2e-3, tol_angle: float = 0.05) -> np.ndarray:
    """:func:`~deepprompt_ros.robots.ik.solve_ik` from ``seed``; raises :class:`Rejected` when the
    position error exceeds ``tol_position`` (m) or the angle error ``tol_angle`` (rad)."""
    res = solve_ik(scene.kin, position, seed, axis=axis, rotation=rotation, rest=rest)
    if res.position_error > tol_position or res.angle_error > tol_angle:
        raise Rejected(f"IK error {res.position_error:.4f} m / {res.angle_error:.3f} rad")
    return res.q


def plan(scene: Scene, knots, rng, holds: dict[int, float] | None = None,
         flow: tuple[float, float] = (0.5, 1.0)) -> ViaTrajectory:
    """Min-jerk trajectory through ``knots``; ``holds`` maps a knot index to a hold time (s)
    (the knot is repeated, the segment between the copies lasts that long)."""
    knots = [np.asarray(k, dtype=np.float64) for k in knots]
    spec = scene.spec
    durations = list(segment_durations(np.array(knots), spec, rng))
    if holds:
        for idx in sorted(holds, reverse=True):
            knots.insert(idx + 1, knots[idx].copy())
            durations.insert(idx, holds[idx])
    traj = ViaTrajectory(np.array(knots), np.array(durations), flow=rng.uniform(*flow))
    return traj.within_limits(spec)


def jitter_start(spec, rng, scale: float) -> np.ndarray:
    """The home pose plus U(±scale) rad per joint, inside the limits."""
    return spec.clip_positions(spec.home + rng.uniform(-scale, scale, spec.n_joints))
