"""Synthetic demonstration families that need no robot model: the paper's bimodal sine family
(Fig. "DeepProMPs used in different situations") and one-cycle shaking for rhythmic primitives."""
from __future__ import annotations

from typing import Iterator, Sequence

import numpy as np

from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.data.demonstration import Demonstration

__all__ = ["bimodal_sine", "rhythmic_shake", "iter_image_reach"]


def bimodal_sine(n_demos: int = 200, n_points: int = 100, n_joints: int = 1, seed: int = 0,
                 amplitude: tuple[float, float] = (0.8, 1.2), noise_std: float = 0.01,
                 duration: float = 2.0) -> DemoDataset:
    """Two modes of sinusoids: y_j(x) = s * A_j * sin(2π x) + small noise, s = ±1 with equal probability.

    Both modes cross zero at x = 0, 0.5, 1 (via-points there cannot tell the modes apart); at
    x = 0.25 they are ±A apart. Each demo carries a 1-D context ``mode`` = s (the low-dim context).

    Returns
    -------
    DemoDataset with ``n_demos`` demonstrations of ``n_points`` samples and ``n_joints`` joints.
    """
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, 1.0, n_points)
    t = x * duration
    names = tuple(f"joint_{j + 1}" for j in range(n_joints))
    demos = []
    for i in range(n_demos):
        s = 1.0 if rng.random() < 0.5 else -1.0
        amp = rng.uniform(*amplitude, size=n_joints)
        q = s * amp[None, :] * np.sin(2 * np.pi * x)[:, None] + noise_std * rng.standard_normal((n_points, n_joints))
        demos.append(Demonstration(name=f"sine_{i:04d}", t=t.copy(), q=q, joint_names=names,
                                   contexts={"mode": np.array([[s]])}))
    return DemoDataset(tuple(demos), source=f"bimodal_sine(seed={seed})")


def rhythmic_shake(n_demos: int = 30, n_points: int = 100, n_joints: int = 7, seed: int = 0,
                   period: float = 2.0, offset=None, joint_names: Sequence[str] | None = None) -> DemoDataset:
    """One-cycle shaking demonstrations for rhythmic primitives (phase = [sin 2πx, cos 2πx]).

    Each joint oscillates around ``offset`` (default: spread over ±0.3 rad) with a per-demo
    amplitude (0.08–0.2 rad), phase and a second harmonic (≤ 0.04 rad); the demo is exactly one
    period long, so its start and end coincide up to noise. Peak speed ≤ 0.9 rad/s at period 2 s.
    """
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, 1.0, n_points, endpoint=True)
    names = tuple(joint_names) if joint_names is not None else tuple(f"joint_{j + 1}" for j in range(n_joints))
    n_joints = len(names)
    offset = np.linspace(-0.3, 0.3, n_joints) if offset is None else np.asarray(offset, dtype=np.float64)
    demos = []
    for i in range(n_demos):
        a1 = rng.uniform(0.08, 0.2, n_joints)
        a2 = rng.uniform(0.0, 0.04, n_joints)
        ph = rng.uniform(-0.2, 0.2, n_joints)
        q = offset + a1 * np.sin(2 * np.pi * x[:, None] + ph) + a2 * np.sin(4 * np.pi * x[:, None])
        q = q + 0.002 * rng.standard_normal(q.shape)
        demos.append(Demonstration(name=f"shake_{i:04d}", t=x * period, q=q, joint_names=names,
                                   phase_type="rhythmic"))
    return DemoDataset(tuple(demos), source=f"rhythmic_shake(seed={seed})")


def iter_image_reach(n_demos: int, seed: int = 0, n_joints: int = 7, n_points: int = 100, n_images: int = 5,
                     image_size: int = 64, duration: float = 3.0) -> Iterator[Demonstration]:
    """``n_demos`` reaching demonstrations with a 3-D context ``target`` and ``n_images`` camera
    images each, generated one at a time (demo i from the generator seeded ``[seed, i]``, so the
    family needs no memory beyond one demo and any demo can be made on its own).

    The target is uniform in [0.3, 0.6] x [-0.3, 0.3] x [0, 0.3] m; each joint moves from its start
    (spread over ±0.5 rad) by minimum jerk to a goal linear in the target (a fixed random map) plus
    a per-demo bend (≤ 0.1 rad at mid-phase). Each image (``image_size`` square, uint8) is grey noise
    with a red square where the target projects from above, shifted by up to 2 pixels per image.
    """
    names = tuple(f"joint_{j + 1}" for j in range(n_joints))
    gain = np.random.default_rng([seed, 2**31]).normal(0.0, 1.5, size=(n_joints, 3))
    start = np.linspace(-0.5, 0.5, n_joints)
    x = np.linspace(0.0, 1.0, n_points)
    s = 10 * x ** 3 - 15 * x ** 4 + 6 * x ** 5  # minimum-jerk profile
    side = max(2, image_size // 8)
    for i in range(n_demos):
        rng = np.random.default_rng([seed, i])
        target = rng.uniform([0.3, -0.3, 0.0], [0.6, 0.3, 0.3])
        goal = start + gain @ (target - [0.45, 0.0, 0.15])
        bend = rng.uniform(-0.1, 0.1, n_joints)
        q = start + np.outer(s, goal - start) + np.outer(np.sin(np.pi * x), bend)
        images = rng.integers(90, 120, size=(n_images, image_size, image_size, 3), dtype=np.uint8)
        u = int((target[0] - 0.3) / 0.3 * (image_size - side - 4)) + 2
        v = int((target[1] + 0.3) / 0.6 * (image_size - side - 4)) + 2
        for k, (du, dv) in enumerate(rng.integers(-2, 3, size=(n_images, 2))):
            images[k, u + du: u + du + side, v + dv: v + dv + side] = (200, 30, 30)
        yield Demonstration(name=f"reach_{i:05d}", t=x * duration, q=q, joint_names=names,
                            contexts={"target": target[None, :]}, images=images)
