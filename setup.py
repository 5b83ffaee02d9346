"""ament_python package deepprompt_ros (also installable with plain pip)."""
import glob
import os

from setuptools import find_packages, setup

PACKAGE = "deepprompt_ros"


def _files(pattern):
    return [f for f in glob.glob(pattern) if os.path.isfile(f)]


setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={PACKAGE: ["resources/urdf/*.urdf", "py.typed"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + PACKAGE]),
        ("share/" + PACKAGE, ["package.xml"]),
        ("share/" + PACKAGE + "/config", _files("config/*.yaml")),
        ("share/" + PACKAGE + "/models", _files("models/*")),
        ("share/" + PACKAGE + "/launch", _files("launch/*.launch.py")),
        ("share/" + PACKAGE + "/urdf", _files(PACKAGE + "/resources/urdf/*.urdf")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="deepprompt_ros maintainers",
    maintainer_email="maintainers@deepprompt-ros.org",
    description="Deep Probabilistic Movement Primitives served to ROS 2 controllers.",
    license="BSD-3-Clause",
    entry_points={
        "console_scripts": [
            "primitive_server = deepprompt_ros.ros.primitive_server:main",
            "sim_bridge = deepprompt_ros.ros.sim_bridge:main",
            "demo_recorder = deepprompt_ros.ros.demo_recorder:main",
            "train = deepprompt_ros.training.cli:main",
            "shard_dataset = deepprompt_ros.data.sharded:main",
        ],
    },
)
