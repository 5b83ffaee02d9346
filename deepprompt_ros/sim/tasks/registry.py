"""The task registry: :data:`TASKS` (what each task is) and :func:`make_task` (its demonstrations).

The tasks, their contexts and sizes: :mod:`deepprompt_ros.sim.tasks`; each task's demonstrator: the
module of its name.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.data.demonstration import Demonstration
from deepprompt_ros.sim.tasks import close_box, kinova_pick_place, pour, reach
from deepprompt_ros.sim.tasks.scene import Rejected, Scene

__all__ = ["TASKS", "SPLITS", "TaskSpec", "make_task"]

SPLITS = ("train", "val", "test")


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

_DEMONSTRATORS = {"reach": reach.demonstrate, "close_box": close_box.demonstrate, "pour": pour.demonstrate,
                  "kinova_pick_place": kinova_pick_place.demonstrate}
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
    scene = Scene(task.robot, int(image_size))
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
                except Rejected as exc:
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
