"""Shared fixtures and the test tiers.

Tiers (file names say the tier):

* ``test_<concept>.py`` — ROS-free: the maths, data, robots, simulation, execution and server logic,
  tools and documents. ``pytest -m "not ros"`` runs this tier alone (no rclpy needed).
* ``test_ros_<what>.py`` — needs ROS 2: message conversions, the fast-path pieces, and nodes started
  as real processes talking over DDS (random ``ROS_DOMAIN_ID``, discovery on localhost only; every
  process a test starts is stopped by it). These get the ``ros`` marker automatically.

Every file passes alone (``pytest test/<file>``) and in any order: fixtures build what a test needs,
nothing relies on another test having run first.
"""
from __future__ import annotations

import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def pytest_configure(config):
    config.addinivalue_line("markers", "ros: needs ROS 2 (rclpy, messages, or nodes over DDS); "
                                       "deselect with -m 'not ros'")


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.path.name.startswith("test_ros_"):
            item.add_marker(pytest.mark.ros)


@pytest.fixture(scope="session")
def repo_root() -> pathlib.Path:
    """The checkout's root folder."""
    return ROOT


@pytest.fixture(scope="session")
def models_dir() -> pathlib.Path:
    """The shipped trained primitives (models/)."""
    return ROOT / "models"


@pytest.fixture(scope="module")
def ros_env(tmp_path_factory) -> dict[str, str]:
    """An isolated ROS 2 environment for one test module: random domain id, localhost discovery,
    its own log folder."""
    from deepprompt_ros.ros.testing import isolated_ros_env

    return isolated_ros_env(tmp_path_factory.mktemp("ros_log"))


def train_tiny_reach(path: pathlib.Path) -> pathlib.Path:
    """A small trained Gen3 lite primitive: 40 six-joint reaching demos from home (minimum-jerk
    timing), the final offset linear in the 3-D 'object' context; written to ``path``."""
    import numpy as np

    from deepprompt_ros.data.demo_dataset import DemoDataset
    from deepprompt_ros.data.demonstration import Demonstration
    from deepprompt_ros.robots.spec import load_robot
    from deepprompt_ros.sim.tasks.min_jerk import min_jerk
    from deepprompt_ros.training.config import TrainConfig
    from deepprompt_ros.training.loop import train

    spec = load_robot("gen3_lite")
    rng = np.random.default_rng(0)
    x = np.linspace(0, 1, 50)
    s = min_jerk(x)
    a = rng.uniform(-1, 1, (6, 3))
    demos = [Demonstration(f"d{i}", x * 6.0, spec.home + s[:, None] * (a @ c)[None, :] * 0.6, spec.joint_names,
                           {"object": c[None]}) for i, c in enumerate(rng.uniform(-0.5, 0.5, (40, 3)))]
    train(DemoDataset(tuple(demos), source="tiny reach"),
          TrainConfig(steps=300, latent_dim=8, hidden=32, val_every=300, n_points=50, max_via_points=5, threads=1),
          out_path=path, log=lambda m: None)
    return path


@pytest.fixture(scope="session")
def tiny_reach_model(tmp_path_factory) -> pathlib.Path:
    """:func:`train_tiny_reach`, trained once per test session."""
    return train_tiny_reach(tmp_path_factory.mktemp("tiny_reach") / "reach.safetensors")
