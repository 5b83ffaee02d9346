"""package.xml names what the code needs: every ROS package imported anywhere in deepprompt_ros/ and
launch/ (late imports included) and every package whose node a launch starts as a dependency, the
system Python packages by rosdep key, the pip-only ones in a comment; LICENSE is the BSD-3-Clause
text package.xml and setup.py declare.

ROS tier: which imports are ROS packages is read from the installed ROS packages (the ament index
of every prefix of AMENT_PREFIX_PATH, as a sourced Jazzy or the Makefile sets it, then this
interpreter's prefix where the ROS wheels are installed)."""
import ast
import os
import pathlib
import re
import sys

from catkin_pkg.package import parse_package

ROOT = pathlib.Path(__file__).resolve().parents[1]
#: Import name -> rosdep key of the system Python packages the code uses.
ROSDEP_KEYS = {"numpy": "python3-numpy", "yaml": "python3-yaml"}
#: Import name -> pip distribution of the packages installed with pip only (requirements.txt).
PIP_ONLY = {"torch": "torch", "pinocchio": "pin", "example_robot_data": "example-robot-data-loaders",
            "ruckig": "ruckig", "pybullet": "pybullet", "safetensors": "safetensors", "mcap": "mcap"}
#: ROS packages not installable from the package index here (the launch files use them).
ROS_NOT_INSTALLED = {"launch", "launch_ros"}


def _imports() -> dict[str, set[str]]:
    """Top-level name of every absolute import in deepprompt_ros/ and launch/ -> the files."""
    found: dict[str, set[str]] = {}
    for path in sorted([*(ROOT / "deepprompt_ros").rglob("*.py"), *(ROOT / "launch").glob("*.py")]):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                found.setdefault(name.split(".")[0], set()).add(str(path.relative_to(ROOT)))
    return found


def _prefixes() -> list[pathlib.Path]:
    """The prefixes of AMENT_PREFIX_PATH (an apt Jazzy: /opt/ros/jazzy), then sys.prefix."""
    return [pathlib.Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p] + [
        pathlib.Path(sys.prefix)]


def _is_ros_package(name: str) -> bool:
    """An installed ROS package: in the ament index (or with a share/<name>/package.xml) of a prefix.
    The pip-only imports are not, even where an apt package of the name is installed (pinocchio and
    ruckig under /opt/ros/jazzy: other releases than the pins)."""
    if name in PIP_ONLY:
        return False
    return name in ROS_NOT_INSTALLED or any(
        (prefix / "share" / "ament_index" / "resource_index" / "packages" / name).is_file()
        or (prefix / "share" / name / "package.xml").is_file() for prefix in _prefixes())


def _package():
    return parse_package(str(ROOT / "package.xml"))


def test_every_imported_ros_package_is_a_dependency():
    imports = _imports()
    ros = {n for n in imports if n != "deepprompt_ros" and _is_ros_package(n)}
    assert {"rclpy", "rcl_interfaces", "builtin_interfaces", "deepprompt_msgs", "launch", "launch_ros"} <= ros
    declared = {d.name for d in _package().exec_depends}
    missing = {n: sorted(imports[n]) for n in sorted(ros - declared)}
    assert not missing, f"add <exec_depend> to package.xml for the ROS packages imported by: {missing}"


def test_packages_of_launched_nodes_are_dependencies():
    from deepprompt_ros import bringup

    launched = {n.package for launch in bringup.LAUNCHES for n in bringup.nodes(launch)} - {"deepprompt_ros"}
    assert "robot_state_publisher" in launched
    declared = {d.name for d in _package().exec_depends}
    assert launched <= declared, f"add <exec_depend> to package.xml for {sorted(launched - declared)}"


def test_python_dependencies_are_rosdep_keys_or_named_pip_only():
    imports = _imports()
    third_party = {n for n in imports if n not in sys.stdlib_module_names and n != "deepprompt_ros"
                   and not _is_ros_package(n) and n != "__future__"}
    unknown = {n: sorted(imports[n]) for n in sorted(third_party - set(ROSDEP_KEYS) - set(PIP_ONLY))}
    assert not unknown, (f"imports neither in ROSDEP_KEYS nor PIP_ONLY of this test: {unknown}; add the rosdep "
                         f"key to package.xml or name the pip distribution in its pip-only comment")
    declared = {d.name for d in _package().exec_depends}
    assert {ROSDEP_KEYS[n] for n in third_party & set(ROSDEP_KEYS)} <= declared
    text = (ROOT / "package.xml").read_text()
    comment = " ".join(re.findall(r"<!--(.*?)-->", text, re.S))
    for name in third_party & set(PIP_ONLY):
        assert re.search(rf"\b{re.escape(PIP_ONLY[name])}\b", comment), f"package.xml: name {PIP_ONLY[name]} as pip-only"
        requirement = re.search(rf"^{re.escape(PIP_ONLY[name])}==", (ROOT / "requirements.txt").read_text(), re.M)
        assert requirement, f"requirements.txt pins no {PIP_ONLY[name]}"


def test_license_file_matches_the_declared_license():
    pkg = _package()
    assert [str(lic) for lic in pkg.licenses] == ["BSD-3-Clause"]
    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("BSD 3-Clause License\n") and "Copyright (c) deepprompt_ros maintainers" in text
    assert "Neither the name of the copyright holder nor the names of its" in text
    setup_text = (ROOT / "setup.py").read_text()
    assert 'license="BSD-3-Clause"' in setup_text
