"""Rotations: elementary rotation matrices, quaternion conversions, the rotation vector (log map).

The one place of the package where rotation matrices and quaternions are converted. Quaternions
are (x, y, z, w), as in PyBullet and ROS; rotation matrices are 3×3 arrays whose columns are the
rotated frame's axes in the reference frame. Plain numpy, no Pinocchio or PyBullet.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["rot_y", "rot_z", "skew", "rodrigues", "log3", "quat_xyzw", "rotation_from_quat_xyzw"]


def rot_z(angle: float) -> np.ndarray:
    """Rotation by ``angle`` (rad) about z, shape (3, 3)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(angle: float) -> np.ndarray:
    """Rotation by ``angle`` (rad) about y, shape (3, 3)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix [v]ₓ, shape (3, 3): [v]ₓ u = v × u."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def rodrigues(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation by ``angle`` (rad) about ``axis`` (shape (3,), any length > 0), shape (3, 3):
    R = I + sin θ K + (1 − cos θ) K², K = [a/|a|]ₓ (Rodrigues' formula)."""
    K = skew(axis / np.linalg.norm(axis))
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * K @ K


def log3(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis × angle), shape (3,), of a rotation matrix (the SO(3) log map)."""
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    angle = math.acos(c)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if angle < 1e-9:
        return 0.5 * w
    if math.pi - angle < 1e-6:  # axis from the symmetric part
        i = int(np.argmax(np.diag(R)))
        axis = (R[:, i] + np.eye(3)[:, i]) / math.sqrt(2.0 * (1.0 + R[i, i]))
        return angle * axis
    return angle / (2.0 * math.sin(angle)) * w


def quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), shape (4,), of a rotation matrix (Shepperd's method: from the
    trace when it is positive, else from the largest diagonal element)."""
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0, 0.0, 0.0, (R[k, j] - R[j, k]) / s]
        q[i] = 0.25 * s
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
    q = np.array(q)
    return q / np.linalg.norm(q)


def rotation_from_quat_xyzw(q) -> np.ndarray:
    """Rotation matrix, shape (3, 3), of a quaternion (x, y, z, w) of any norm > 0.

    R = I + (2/|q|²) (w [v]ₓ + [v]ₓ²), v = (x, y, z), written out term by term in the order of
    Bullet's ``btMatrix3x3::setRotation``, so the result equals PyBullet's
    ``getMatrixFromQuaternion`` to the last bit.
    """
    x, y, z, w = (float(v) for v in q)
    s = 2.0 / (x * x + y * y + z * z + w * w)
    xs, ys, zs = x * s, y * s, z * s
    wx, wy, wz = w * xs, w * ys, w * zs
    xx, xy, xz = x * xs, x * ys, x * zs
    yy, yz, zz = y * ys, y * zs, z * zs
    return np.array([[1.0 - (yy + zz), xy - wz, xz + wy],
                     [xy + wz, 1.0 - (xx + zz), yz - wx],
                     [xz - wy, yz + wx, 1.0 - (xx + yy)]])
