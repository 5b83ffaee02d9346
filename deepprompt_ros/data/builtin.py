"""The built-in datasets by name: :data:`BUILTIN` and :func:`builtin_dataset` (``--builtin NAME`` of
training).

The registry sits above every generator it names: the synthetic families of
:mod:`deepprompt_ros.data.synthetic`, the kinematic reach generator
(:mod:`deepprompt_ros.sim.tasks.kinematic_reach`) and the PyBullet tasks
(:mod:`deepprompt_ros.sim.tasks.registry`). The generators that need a robot model are imported when
their dataset is asked for, so that importing this module (and the training loop that uses it)
loads neither Pinocchio nor PyBullet.
"""
from __future__ import annotations

from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.data.demonstration import DatasetError
from deepprompt_ros.data.synthetic import bimodal_sine, rhythmic_shake

__all__ = ["BUILTIN", "builtin_dataset", "wam_shake", "gen3_lite_reach"]


def wam_shake(seed: int = 0, **kwargs) -> DemoDataset:
    """Shaking ("make a mojito") cycles on the Barrett WAM around its ready pose (the joint names
    and home pose of ``load_robot("wam")``); keyword arguments go to
    :func:`~deepprompt_ros.data.synthetic.rhythmic_shake`."""
    from deepprompt_ros.robots.spec import load_robot

    wam = load_robot("wam")
    return rhythmic_shake(seed=seed, joint_names=wam.joint_names, offset=wam.home, **kwargs)


def gen3_lite_reach(seed: int = 0, **kwargs) -> DemoDataset:
    """Reaching demonstrations on the Kinova Gen3 lite with the object position as context
    (:func:`~deepprompt_ros.sim.tasks.kinematic_reach.reach_demos`)."""
    from deepprompt_ros.sim.tasks.kinematic_reach import reach_demos

    return reach_demos("gen3_lite", seed=seed, **kwargs)


def _task_builtin(name: str):
    """Entry for a task of :mod:`deepprompt_ros.sim.tasks.registry`: its train split,
    ``make_task(name, seed=seed, **kwargs)``."""
    def generate(seed: int = 0, **kwargs) -> DemoDataset:
        from deepprompt_ros.sim.tasks.registry import make_task

        return make_task(name, seed=seed, **kwargs)

    generate.__doc__ = f"Train split of the PyBullet task '{name}' (see deepprompt_ros.sim.tasks.registry)."
    return generate


BUILTIN = {"bimodal_sine": bimodal_sine, "rhythmic_shake": rhythmic_shake, "wam_shake": wam_shake,
           "gen3_lite_reach": gen3_lite_reach,
           **{name: _task_builtin(name) for name in ("reach", "close_box", "pour", "kinova_pick_place")}}


def builtin_dataset(name: str, **kwargs) -> DemoDataset:
    """Dataset ``name`` of :data:`BUILTIN`, generated with ``kwargs`` (e.g. ``seed``, ``n_demos``)."""
    if name not in BUILTIN:
        raise DatasetError(f"unknown built-in dataset '{name}'; available: {sorted(BUILTIN)}")
    return BUILTIN[name](**kwargs)
