"""The venv set up by tools/setup.sh is a ROS install prefix for deepprompt_ros.

Checks what ``ros2 run deepprompt_ros <exe>`` and ``get_package_share_directory``
rely on (ament_python layout inside ``sys.prefix``), that the package imports
from anywhere out of this checkout, and the idempotence of the setup tools.
"""
import importlib.metadata
import json
import importlib.util
import os
import subprocess
import sys

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(REPO, "tools"))

import fix_cmake_paths  # noqa: E402
import install_ros_layout  # noqa: E402

PREFIX = sys.prefix
REQUIRED_EXECUTABLES = {"primitive_server", "sim_bridge", "demo_recorder", "train"}


def _entry_points():
    return dict(install_ros_layout.console_scripts("deepprompt_ros"))


def _ros2_run_executables(package):
    """Executables of ``package`` found the way ros2pkg's get_executable_paths
    does: ``<prefix from the ament index>/lib/<package>``, files with X_OK."""
    from ament_index_python.packages import get_package_prefix

    base = os.path.join(get_package_prefix(package), "lib", package)
    found = {}
    for dirpath, dirnames, filenames in os.walk(base):
        dirnames[:] = [d for d in dirnames if not d.startswith(".")]
        for name in filenames:
            path = os.path.join(dirpath, name)
            if os.access(path, os.X_OK):
                found[name] = path
    return found


@pytest.fixture
def ament_env(monkeypatch):
    monkeypatch.setenv("AMENT_PREFIX_PATH", PREFIX)


def test_ament_index_lists_both_packages_in_this_prefix(ament_env):
    from ament_index_python.packages import get_packages_with_prefixes

    packages = get_packages_with_prefixes()
    assert packages.get("deepprompt_ros") == PREFIX
    assert packages.get("deepprompt_msgs") == PREFIX
    marker = os.path.join(PREFIX, "share", "ament_index", "resource_index", "packages",
                          "deepprompt_ros")
    assert os.path.isfile(marker)


def test_share_holds_a_valid_package_xml(ament_env):
    from ament_index_python.packages import get_package_share_directory
    from catkin_pkg.package import parse_package

    share = get_package_share_directory("deepprompt_ros")
    assert share == os.path.join(PREFIX, "share", "deepprompt_ros")
    pkg = parse_package(os.path.join(share, "package.xml"))  # strict validation
    assert pkg.name == "deepprompt_ros"
    assert pkg.get_build_type() == "ament_python"
    assert "deepprompt_msgs" in {d.name for d in pkg.exec_depends}


def test_ros2_run_finds_every_console_script(ament_env):
    entry_points = _entry_points()
    assert REQUIRED_EXECUTABLES <= set(entry_points), "setup.py console_scripts"
    found = _ros2_run_executables("deepprompt_ros")
    assert set(found) == set(entry_points)
    python = os.path.realpath(os.path.join(PREFIX, "bin", "python"))
    for name, value in entry_points.items():
        with open(found[name], encoding="utf-8") as f:
            shebang, tag, comment = f.readline(), f.readline(), f.readline()
        assert os.path.realpath(shebang[2:].strip()) == python, f"{name}: {shebang!r}"
        assert tag.strip() == install_ros_layout.LAUNCHER_TAG
        assert comment.strip() == f"# entry point: {value}"


@pytest.mark.parametrize("name", sorted(REQUIRED_EXECUTABLES))
def test_launcher_loads_its_entry_point(name):
    """Load the launcher without calling main() (it is __main__-guarded) and
    check it resolved the very function setup.py names, from outside the repo."""
    value = _entry_points()[name]
    module, attr = value.split(":")
    try:
        written = importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:  # parent package missing
        written = False
    if not written:
        pytest.skip(f"{module} is not written yet")
    launcher = os.path.join(PREFIX, "lib", "deepprompt_ros", name)
    head = attr.split(".")[0]
    code = ("import runpy, sys\n"
            f"ns = runpy.run_path({launcher!r}, run_name='launcher_check')\n"
            f"fn = ns[{head!r}]\n"
            "print(f'{fn.__module__}:{fn.__qualname__}')\n")
    out = subprocess.run([os.path.join(PREFIX, "bin", "python"), "-c", code], cwd="/",
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == value


def test_import_from_anywhere_uses_this_checkout(tmp_path):
    out = subprocess.run(
        [os.path.join(PREFIX, "bin", "python"), "-c",
         "import os, deepprompt_ros, deepprompt_msgs.srv; "
         "print(os.path.realpath(deepprompt_ros.__file__))"],
        cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == os.path.realpath(os.path.join(REPO, "deepprompt_ros",
                                                               "__init__.py"))
    direct_url = json.loads(importlib.metadata.distribution("deepprompt_ros")
                            .read_text("direct_url.json"))
    assert direct_url["dir_info"].get("editable") is True  # source edits are picked up


def test_layout_and_stamps_are_up_to_date():
    """Nothing to do for setup.sh: share/ copies match the sources, launchers
    match setup.py, interfaces are built from the current msg_defs/."""
    report = install_ros_layout.install_layout(PREFIX, REPO, os.path.join(PREFIX, "bin", "python"),
                                               check=True)
    assert report.changes == [], "run make setup"
    out = subprocess.run(["bash", os.path.join(REPO, "tools", "setup.sh"), "--check", PREFIX],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "everything is up to date" in out.stdout


# --------------------------------------------------------------- tool units
OPT_PY = "/opt/python/cp311-cp311/include/python3.11"
OPT_NP = "/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include"
CMAKE_TEXT = (
    'set_target_properties(std_msgs::std_msgs__rosidl_generator_py PROPERTIES\n'
    f'  INTERFACE_INCLUDE_DIRECTORIES "{OPT_PY};{OPT_NP}"\n'
    '  INTERFACE_LINK_LIBRARIES "/opt/python/cp311-cp311/lib/libpython3.11.so"\n)\n'
    'set_target_properties(x PROPERTIES\n'
    '  INTERFACE_INCLUDE_DIRECTORIES "${_IMPORT_PREFIX}/include/std_msgs")\n'
)


def test_cmake_path_rewrite_is_exact_and_idempotent(tmp_path):
    py_inc, np_inc = str(tmp_path / "pyinc"), str(tmp_path / "npinc")
    fixed = fix_cmake_paths.rewrite_text(CMAKE_TEXT, py_inc, np_inc)
    assert f'INTERFACE_INCLUDE_DIRECTORIES "{py_inc};{np_inc}"' in fixed
    assert "/opt/python/cp311-cp311/lib/libpython3.11.so" in fixed  # not an include dir
    assert '"${_IMPORT_PREFIX}/include/std_msgs"' in fixed
    assert fix_cmake_paths.rewrite_text(fixed, py_inc, np_inc) == fixed
    # numpy 1.x <-> 2.x: an earlier local numpy path is replaced too
    np1 = fixed.replace(np_inc, "/venv/lib/python3.11/site-packages/numpy/core/include")
    assert fix_cmake_paths.rewrite_text(np1, py_inc, np_inc) == fixed


def test_cmake_path_fix_on_a_prefix(tmp_path):
    (tmp_path / "pyinc").mkdir()
    (tmp_path / "npinc").mkdir()
    cmake_dir = tmp_path / "prefix" / "share" / "std_msgs" / "cmake"
    cmake_dir.mkdir(parents=True)
    target = cmake_dir / "export_std_msgs__rosidl_generator_pyExport.cmake"
    target.write_text(CMAKE_TEXT)
    kwargs = dict(python_include=str(tmp_path / "pyinc"), numpy_include=str(tmp_path / "npinc"))
    dry = fix_cmake_paths.fix_prefix(str(tmp_path / "prefix"), check=True, **kwargs)
    assert dry.changed == [str(target)] and target.read_text() == CMAKE_TEXT
    first = fix_cmake_paths.fix_prefix(str(tmp_path / "prefix"), **kwargs)
    assert first.changed == [str(target)] and OPT_PY not in target.read_text()
    assert fix_cmake_paths.fix_prefix(str(tmp_path / "prefix"), **kwargs).changed == []
    with pytest.raises(FileNotFoundError, match="does not exist"):
        fix_cmake_paths.fix_prefix(str(tmp_path / "prefix"), python_include="/nonexistent",
                                   numpy_include=str(tmp_path / "npinc"))


def test_installed_wheels_have_no_build_machine_include_paths():
    report = fix_cmake_paths.fix_prefix(PREFIX, check=True)
    assert report.scanned > 0 and report.changed == []


def _fake_source(root):
    (root / "resource").mkdir(parents=True)
    (root / "resource" / "deepprompt_ros").write_text("")
    (root / "package.xml").write_text("<package/>\n")
    (root / "config").mkdir()
    (root / "config" / "a.yaml").write_text("a: 1\n")
    (root / "config" / "b.yaml").write_text("b: 2\n")
    return root


def test_ros_layout_install_sync_and_cleanup(tmp_path):
    src, prefix = _fake_source(tmp_path / "src"), tmp_path / "prefix"
    scripts = [("pretty_json", "json.tool:main"), ("old_tool", "json.tool:main")]
    dry = install_ros_layout.install_layout(str(prefix), str(src), sys.executable, check=True,
                                            scripts=scripts)
    assert dry.changes and not prefix.exists()
    first = install_ros_layout.install_layout(str(prefix), str(src), sys.executable,
                                              scripts=scripts)
    lib = prefix / "lib" / "deepprompt_ros"
    assert sorted(os.listdir(lib)) == ["old_tool", "pretty_json"]
    assert (prefix / "share" / "deepprompt_ros" / "config" / "b.yaml").read_text() == "b: 2\n"
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages"
            / "deepprompt_ros").is_file()
    assert first.changes
    # second run: nothing to do
    again = install_ros_layout.install_layout(str(prefix), str(src), sys.executable,
                                              scripts=scripts)
    assert again.changes == []
    # the launcher really runs its entry point
    out = subprocess.run([str(lib / "pretty_json")], input='{"b": 1, "a": [2]}',
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[0] == "{" and '"a": [' in out.stdout
    # removed entry point and deleted config file disappear; foreign files stay
    (lib / "handmade").write_text("#!/bin/sh\n")
    (src / "config" / "b.yaml").unlink()
    (src / "config" / "a.yaml").write_text("a: 3\n")
    install_ros_layout.install_layout(str(prefix), str(src), sys.executable,
                                      scripts=scripts[:1])
    assert sorted(os.listdir(lib)) == ["handmade", "pretty_json"]
    cfg = prefix / "share" / "deepprompt_ros" / "config"
    assert sorted(os.listdir(cfg)) == ["a.yaml"] and (cfg / "a.yaml").read_text() == "a: 3\n"
    assert not (cfg / "a.yaml").is_symlink()


def _setup_kwargs():
    """The keyword arguments setup.py passes to setuptools.setup (run in the checkout, nothing installed)."""
    import runpy
    import setuptools

    captured = {}
    cwd = os.getcwd()
    real_setup = setuptools.setup
    setuptools.setup = lambda **kw: captured.update(kw)
    try:
        os.chdir(REPO)
        runpy.run_path(os.path.join(REPO, "setup.py"), run_name="__main__")
    finally:
        setuptools.setup = real_setup
        os.chdir(cwd)
    return captured


def test_setup_py_data_files_are_what_the_ros_layout_installs():
    """setup.py's data_files (a colcon build) and tools/install_ros_layout.py (the venv) put the same
    files into share/deepprompt_ros: package.xml, config, models, launch files and URDFs."""
    data_files = {}
    for dest, files in _setup_kwargs()["data_files"]:
        if dest.startswith("share/ament_index"):
            continue
        for f in files:
            data_files[os.path.join(dest, os.path.basename(f))] = os.path.join(REPO, f)
    assert data_files == install_ros_layout.share_files(REPO)
    names = {os.path.relpath(p, "share/deepprompt_ros") for p in data_files}
    assert {"launch/demo.launch.py", "launch/primitive_server.launch.py", "launch/record.launch.py",
            "urdf/gen3_lite.urdf", "urdf/wam.urdf", "config/primitives.yaml", "package.xml"} <= names


def test_share_holds_the_launch_files_and_urdfs(ament_env):
    """What ros2 launch and a robot_description consumer look up: share/deepprompt_ros/{launch,urdf}."""
    from ament_index_python.packages import get_package_share_directory

    share = get_package_share_directory("deepprompt_ros")
    for rel in ("launch/demo.launch.py", "launch/primitive_server.launch.py", "launch/record.launch.py",
                "urdf/gen3_lite.urdf", "urdf/wam.urdf"):
        assert os.path.isfile(os.path.join(share, rel)), f"{rel} missing in {share}: run make setup"
    with open(os.path.join(share, "urdf", "gen3_lite.urdf"), encoding="utf-8") as f:
        assert '<robot name="' in f.read()
