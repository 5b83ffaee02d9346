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


@pytest.fixture(scope="session")
def tiny_reach_model(tmp_path_factory) -> pathlib.Path:
    """A small trained Gen3 lite primitive with context 'object' (3), trained once per test session
    on :func:`~deepprompt_ros.sim.tasks.kinematic_reach.context_reach_demos` (40 six-joint reaches
    from home); the path of its model file. Tests that serve it copy it to a folder of their own."""
    from deepprompt_ros.sim.tasks.kinematic_reach import context_reach_demos
    from deepprompt_ros.training.config import TrainConfig
    from deepprompt_ros.training.loop import train

    path = tmp_path_factory.mktemp("tiny_reach") / "reach.safetensors"
    train(context_reach_demos(n_demos=40, n_points=50, seed=0),
          TrainConfig(steps=300, latent_dim=8, hidden=32, val_every=300, n_points=50, max_via_points=5, threads=1,
                      auto_select=False),  # the architecture as given: a plain decoder, latent 8
          out_path=path, log=lambda m: None)
    return path
