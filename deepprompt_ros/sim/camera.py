"""Pinhole cameras of the PyBullet scene: pose, view / projection matrices, projection of points.

:meth:`~deepprompt_ros.sim.simulation.Simulation.camera_image` renders with the matrices of
:func:`view_matrix` and :func:`projection_matrix` (PyBullet's ``computeViewMatrix`` /
``computeProjectionMatrixFOV``: column-major 4×4, OpenGL conventions); :func:`project_point` maps a
world point into the same image.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pybullet as pb

__all__ = ["CameraPose", "view_matrix", "projection_matrix", "project_point"]


@dataclasses.dataclass(frozen=True)
class CameraPose:
    """Pinhole camera looking from ``eye`` at ``target``.

    Attributes
    ----------
    eye, target : tuple of 3 floats
        Camera position and the point it looks at (world frame, m).
    up : tuple of 3 floats
        Direction that appears upwards in the image.
    fov_deg : float
        Vertical field of view (degrees).
    near, far : float
        Clipping distances (m).
    """

    eye: tuple[float, float, float] = (0.75, 0.35, 0.55)
    target: tuple[float, float, float] = (0.15, 0.0, 0.25)
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    fov_deg: float = 60.0
    near: float = 0.01
    far: float = 5.0

    def __post_init__(self) -> None:
        for name in ("eye", "target", "up"):
            v = tuple(float(x) for x in getattr(self, name))
            if len(v) != 3 or not all(math.isfinite(x) for x in v):
                raise ValueError(f"camera {name} must be 3 finite numbers; got {getattr(self, name)!r}")
            object.__setattr__(self, name, v)
        if np.allclose(self.eye, self.target):
            raise ValueError("camera eye and target must differ")
        if not 0.0 < self.fov_deg < 180.0:
            raise ValueError(f"camera fov_deg must be in (0, 180); got {self.fov_deg}")
        if not 0.0 < self.near < self.far:
            raise ValueError(f"camera clipping needs 0 < near < far; got near={self.near}, far={self.far}")


def view_matrix(camera: CameraPose) -> tuple[float, ...]:
    """PyBullet view matrix of ``camera`` (16 floats, column-major)."""
    return pb.computeViewMatrix(camera.eye, camera.target, camera.up)


def projection_matrix(camera: CameraPose, width: int, height: int) -> tuple[float, ...]:
    """PyBullet projection matrix of ``camera`` for a ``width`` × ``height`` image (16 floats,
    column-major)."""
    return pb.computeProjectionMatrixFOV(camera.fov_deg, width / height, camera.near, camera.far)


def project_point(camera, point, width: int, height: int) -> np.ndarray:
    """Normalized pixel position (u, v) of a world point in ``camera``'s image.

    Uses the view / projection matrices that
    :meth:`~deepprompt_ros.sim.simulation.Simulation.camera_image` renders with
    (:func:`view_matrix`, :func:`projection_matrix`; OpenGL conventions): u = (x_ndc + 1)/2
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
    view = np.array(view_matrix(camera)).reshape(4, 4).T
    proj = np.array(projection_matrix(camera, width, height)).reshape(4, 4).T
    clip = proj @ view @ np.append(np.asarray(point, dtype=np.float64), 1.0)
    ndc = clip[:3] / clip[3]
    return np.array([(ndc[0] + 1.0) / 2.0, (1.0 - ndc[1]) / 2.0])
