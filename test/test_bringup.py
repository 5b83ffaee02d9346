"""The one description of what the launch files and ``make run`` start (deepprompt_ros.bringup):
node names, executables, namespaces, parameter files and parameters; each launch file in launch/
builds exactly the described nodes (run against small stand-ins of ``launch`` / ``launch_ros``, which
cannot be installed here: this checks the files' wiring, not launch itself); run_main starts the same
nodes with the same parameters, robot_state_publisher only where it is installed; the primitives file
chosen for each robot a launch advertises serves on it without a refusal."""
import importlib.metadata
import os
import pathlib
import re
import runpy
import sys
import types

import pytest
import yaml

from deepprompt_ros import bringup, run_main
from deepprompt_ros.common.params import ConfigError, check, specs_of
from deepprompt_ros.recording.config import RecorderConfig
from deepprompt_ros.server.config import ServerConfig
from deepprompt_ros.sim.bridge_config import SimBridgeConfig

ROOT = pathlib.Path(__file__).resolve().parents[1]
LAUNCH_DIR = ROOT / "launch"
NODE_CONFIG = {"sim_bridge": SimBridgeConfig, "primitive_server": ServerConfig, "demo_recorder": RecorderConfig}
#: Argument values other than the defaults, per launch (strings, as a launch file gets them).
OTHER_VALUES = {
    "demo": {"robot": "wam", "real_time_factor": "0.5", "stale_timeout": "2", "namespace": "arm1"},
    "dual_arm": {"left_robot": "wam", "right_robot": "gen3_lite", "left_namespace": "cell/a",
                 "right_namespace": "/cell/b", "real_time_factor": "0.5", "stale_timeout": "2"},
    "primitive_server": {"params_file": str(ROOT / "config" / "primitive_server.yaml"), "robot": "wam",
                         "controller": "arm_controller", "primitives_file": "/tmp/primitives.yaml",
                         "namespace": "/cell/arm1"},
    "record": {"robot": "wam", "output_directory": "/tmp/demos", "namespace": "arm1"},
}


# ------------------------------------------------------------------------------------------------
# the description
# ------------------------------------------------------------------------------------------------
def test_launch_files_are_the_described_launches():
    assert sorted(p.name for p in LAUNCH_DIR.glob("*.launch.py")) == sorted(f"{n}.launch.py" for n in bringup.LAUNCHES)
    assert set(OTHER_VALUES) == set(bringup.LAUNCHES)
    for path in LAUNCH_DIR.glob("*.launch.py"):
        compile(path.read_text(), str(path), "exec")


def test_executables_are_the_console_scripts_of_setup_py():
    scripts = {ep.name: ep.value for ep in importlib.metadata.distribution("deepprompt_ros").entry_points
               if ep.group == "console_scripts"}
    for exe, module in bringup.EXECUTABLES.items():
        assert scripts[exe] == f"{module}:main"


@pytest.mark.parametrize("launch", sorted(bringup.LAUNCHES))
@pytest.mark.parametrize("other", [False, True], ids=["defaults", "other_values"])
def test_described_nodes_have_existing_files_and_declared_parameters(launch, other):
    nodes = bringup.nodes(launch, OTHER_VALUES[launch] if other else None)
    assert len({(n.namespace, n.name) for n in nodes}) == len(nodes)
    for node in nodes:
        if node.package != "deepprompt_ros":  # robot_state_publisher: tested below
            assert node.optional and node.executable == "robot_state_publisher"
            continue
        assert node.executable in bringup.EXECUTABLES and not node.optional
        specs = {s.name: s for s in specs_of(NODE_CONFIG[node.executable])}
        for f in node.parameter_files:
            assert pathlib.Path(f).is_file(), f
            values = yaml.safe_load(pathlib.Path(f).read_text())[node.name]["ros__parameters"]
            assert set(values) - {"objects"} <= set(k.split(".")[0] for k in specs) | set(specs)
        for name, value in node.parameters.items():
            assert name in specs, f"{node.executable} has no parameter {name}"
            assert not check(specs[name], value), check(specs[name], value)


def _config_name(path) -> str:
    return pathlib.Path(path).name


def test_demo_is_the_simulated_arm_the_server_and_robot_state_publisher():
    sim, server, rsp = bringup.nodes("demo")
    assert (sim.executable, sim.name, server.executable, server.name, rsp.executable) == (
        "sim_bridge", "sim_bridge", "primitive_server", "primitive_server", "robot_state_publisher")
    assert [_config_name(f) for f in sim.parameter_files + server.parameter_files] == [
        "sim_bridge.yaml", "primitive_server.yaml"]
    assert sim.parameters == {"robot": "gen3_lite", "real_time_factor": 1.0}
    assert {k: v for k, v in server.parameters.items() if k != "primitives_file"} == {
        "robot": "gen3_lite", "stale_timeout": 1.0}
    assert _config_name(server.parameters["primitives_file"]) == "primitives.yaml"
    sim, server, rsp = bringup.nodes("demo", OTHER_VALUES["demo"])
    assert sim.parameters == {"robot": "wam", "real_time_factor": 0.5}
    assert {k: v for k, v in server.parameters.items() if k != "primitives_file"} == {
        "robot": "wam", "stale_timeout": 2.0}
    assert _config_name(server.parameters["primitives_file"]) == "primitives_wam.yaml"
    assert dict(sim.environment) == dict(server.environment) == {"OPENBLAS_NUM_THREADS": "1"}
    _, server, _ = bringup.nodes("demo", {"robot": "wam", "primitives_file": "/tmp/mine.yaml"})
    assert server.parameters["primitives_file"] == "/tmp/mine.yaml"  # given: it wins


def test_primitive_server_launch_overrides_only_what_is_given():
    server, = bringup.nodes("primitive_server")
    assert [_config_name(f) for f in server.parameter_files] == ["primitive_server.yaml"]
    assert server.parameters == {}
    server, = bringup.nodes("primitive_server", OTHER_VALUES["primitive_server"])
    assert server.parameter_files == (OTHER_VALUES["primitive_server"]["params_file"],)
    assert server.parameters == {"robot": "wam", "controller": "arm_controller",
                                 "primitives_file": "/tmp/primitives.yaml"}
    # a robot with the package's parameters file: the package's primitives of that robot
    server, = bringup.nodes("primitive_server", {"robot": "wam"})
    assert _config_name(server.parameters["primitives_file"]) == "primitives_wam.yaml"
    # the user's parameters file names its own primitives
    server, = bringup.nodes("primitive_server", {"robot": "wam", "params_file": "/tmp/server.yaml"})
    assert server.parameters == {"robot": "wam"}


def test_record_launch_starts_the_sim_in_kinesthetic_mode_the_recorder_and_robot_state_publisher():
    sim, recorder, rsp = bringup.nodes("record")
    assert sim.parameters == {"robot": "gen3_lite", "kinesthetic": True}
    assert (recorder.executable, recorder.parameters) == ("demo_recorder", {})
    assert [_config_name(f) for f in recorder.parameter_files] == ["demo_recorder.yaml"]
    assert rsp.executable == "robot_state_publisher"
    _, recorder, _ = bringup.nodes("record", OTHER_VALUES["record"])
    assert recorder.parameters == {"output_directory": "/tmp/demos"}


@pytest.mark.parametrize("launch", ["demo", "record"])
@pytest.mark.parametrize("robot", ["gen3_lite", "wam"])
def test_robot_state_publisher_gets_the_urdf_of_the_robot(launch, robot):
    rsp = bringup.nodes(launch, {"robot": robot})[-1]
    assert (rsp.package, rsp.executable, rsp.name) == ("robot_state_publisher",) * 3
    urdf = (ROOT / "deepprompt_ros" / "resources" / "urdf" / f"{robot}.urdf").read_text()
    assert rsp.parameters == {"robot_description": urdf}  # the file sim_bridge publishes as robot_description
    assert rsp.parameter_files == () and rsp.environment == () and "no TF" in rsp.optional
    assert rsp.launch_kwargs()["parameters"] == [{"robot_description": urdf}]
    # on the command line: the URDF as one YAML string that reads back as the very text
    cmd = rsp.ros_arguments()
    assert cmd[:2] == ["--ros-args", "-p"] and yaml.safe_load(cmd[2].split(":=", 1)[1]) == urdf


def test_namespace_reaches_every_node():
    for launch in ("demo", "primitive_server", "record"):
        for ns in ("arm1", "/arm1"):
            for node in bringup.nodes(launch, {"namespace": ns}):
                assert node.namespace == "arm1"
                assert node.launch_kwargs()["namespace"] == "arm1"
                assert node.ros_arguments()[1:3] == ["-r", "__ns:=/arm1"]
        for node in bringup.nodes(launch):
            assert node.namespace == "" and "namespace" not in node.launch_kwargs()
            assert not any(a.startswith("__ns:=") for a in node.ros_arguments())
    # a file's section keyed by the plain node name does not apply under a namespace (rcl matches
    # /arm1/primitive_server): its values are passed as parameters, the description's winning
    _, server, _ = bringup.nodes("demo", {"namespace": "arm1"})
    values = server.parameter_values()
    assert values["loop_mode"] == "thread" and values["stale_timeout"] == 1.0
    sim, _, _ = bringup.nodes("demo", {"namespace": "arm1"})
    assert sim.parameter_values()["camera.topic"] == "camera/image_raw"
    assert sim.parameter_values()["objects.cube.shape"] == "box"
    with pytest.raises(ConfigError, match="namespace = 'arm 1': expected names of letters"):
        bringup.nodes("demo", {"namespace": "arm 1"})


def test_dual_arm_is_the_demo_in_two_namespaces_with_one_clock():
    nodes = bringup.nodes("dual_arm", {"left_namespace": "/left_arm", "stale_timeout": "2"})
    left = bringup.nodes("demo", {"robot": "gen3_lite", "namespace": "left_arm", "stale_timeout": "2"})
    right = bringup.nodes("demo", {"robot": "wam", "namespace": "right_arm", "stale_timeout": "2"})
    assert nodes[:3] == left  # the first arm: the demo's nodes as they are (its sim_bridge publishes /clock)
    assert [n.namespace for n in nodes] == ["left_arm"] * 3 + ["right_arm"] * 3
    # the second: the same but for its sim_bridge's clock
    assert nodes[4:] == right[1:] and nodes[3].parameters == {**right[0].parameters, "publish_clock": False}
    assert nodes[3].parameter_values()["publish_clock"] is False  # over the file's section (true)
    assert left[0].parameter_values()["publish_clock"] is True
    assert ["-r", "__ns:=/right_arm"] == nodes[3].ros_arguments()[1:3]
    assert "publish_clock:=false" in nodes[3].ros_arguments()
    for left_ns, right_ns in (("arm", "arm"), ("arm", ""), ("", "/arm")):
        with pytest.raises(ConfigError, match=f"left_namespace = '{left_ns}', right_namespace = '{right_ns}': "
                                              "expected two different, non-empty namespaces"):
            bringup.nodes("dual_arm", {"left_namespace": left_ns, "right_namespace": right_ns})


def test_invalid_arguments_are_refused_with_what_is_expected():
    with pytest.raises(ConfigError) as info:
        bringup.nodes("demo", {"real_time_factor": "fast", "robto": "wam", "stale_timeout": "-1"})
    text = str(info.value)
    for part in ("launch 'demo'", "real_time_factor = 'fast': expected a number", "unknown parameter 'robto'",
                 "stale_timeout = -1 s: expected a value in [0.001, 60] s"):
        assert part in text, text
    with pytest.raises(ValueError, match="unknown launch 'nope'; expected one of demo, dual_arm, primitive_server, record"):
        bringup.nodes("nope")


def test_command_line_carries_the_same_node():
    node = bringup.NodeDescription("sim_bridge", "arm_sim", ("/a.yaml", "/b.yaml"),
                                   {"robot": "wam", "rate_hz": 500.0, "kinesthetic": True, "object_names": ("a", "b"),
                                    "camera.topic": "cam/image"}, remappings=(("joint_states", "/arm/joint_states"),))
    cmd = node.command("/py")
    assert cmd[:5] == ["/py", "-m", "deepprompt_ros.ros.sim_bridge", "--ros-args", "-r"]
    assert cmd[5] == "__node:=arm_sim"
    assert cmd[6:10] == ["--params-file", "/a.yaml", "--params-file", "/b.yaml"]
    params = dict(a.split(":=", 1) for a in cmd[11:-2:2])
    # the -p values are YAML (as rcl parses them) of the very values
    assert {k: yaml.safe_load(v) for k, v in params.items()} == {
        "robot": "wam", "rate_hz": 500.0, "kinesthetic": True, "object_names": ["a", "b"], "camera.topic": "cam/image"}
    assert cmd[-2:] == ["-r", "joint_states:=/arm/joint_states"]
    kw = node.launch_kwargs()
    assert kw["name"] == "arm_sim" and kw["parameters"][:2] == ["/a.yaml", "/b.yaml"]
    assert kw["parameters"][2]["object_names"] == ["a", "b"] and kw["remappings"] == [("joint_states", "/arm/joint_states")]
    for node in bringup.nodes("demo"):  # the executables' own node names: no remap
        assert "__node:=" not in " ".join(node.ros_arguments()) and "name" not in node.launch_kwargs()


# ------------------------------------------------------------------------------------------------
# the launch files, against stand-ins of launch / launch_ros
# ------------------------------------------------------------------------------------------------
class _Action:
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


class _LaunchDescription:
    def __init__(self, entities=()):
        self.entities = list(entities)


class _ParameterValue:
    def __init__(self, value, *, value_type=None):
        self.value, self.value_type = value, value_type


def _unwrap(kwargs: dict) -> dict:
    """A Node's keyword arguments with every ParameterValue(value, value_type=str) as its value."""
    params = []
    for p in kwargs["parameters"]:
        if isinstance(p, dict):
            assert all(v.value_type is str for v in p.values() if isinstance(v, _ParameterValue))
            assert not any(isinstance(v, str) for v in p.values())  # strings stay strings: no YAML reading
            p = {k: v.value if isinstance(v, _ParameterValue) else v for k, v in p.items()}
        params.append(p)
    return dict(kwargs, parameters=params)


class _LaunchConfiguration:
    def __init__(self, name):
        self.name = name

    def perform(self, context):
        return context.launch_configurations[self.name]


@pytest.fixture
def stand_in_launch(monkeypatch):
    """Minimal ``launch`` and ``launch_ros`` modules in sys.modules, for this test only."""
    launch = types.ModuleType("launch")
    launch.LaunchDescription = _LaunchDescription
    actions = types.ModuleType("launch.actions")
    actions.DeclareLaunchArgument = type("DeclareLaunchArgument", (_Action,), {})
    actions.OpaqueFunction = type("OpaqueFunction", (_Action,), {})
    substitutions = types.ModuleType("launch.substitutions")
    substitutions.LaunchConfiguration = _LaunchConfiguration
    launch.actions, launch.substitutions = actions, substitutions
    launch_ros = types.ModuleType("launch_ros")
    ros_actions = types.ModuleType("launch_ros.actions")
    ros_actions.Node = type("Node", (_Action,), {})
    descriptions = types.ModuleType("launch_ros.parameter_descriptions")
    descriptions.ParameterValue = _ParameterValue
    launch_ros.actions, launch_ros.parameter_descriptions = ros_actions, descriptions
    for name, module in {"launch": launch, "launch.actions": actions, "launch.substitutions": substitutions,
                         "launch_ros": launch_ros, "launch_ros.actions": ros_actions,
                         "launch_ros.parameter_descriptions": descriptions}.items():
        monkeypatch.setitem(sys.modules, name, module)
    return types.SimpleNamespace(DeclareLaunchArgument=actions.DeclareLaunchArgument,
                                 OpaqueFunction=actions.OpaqueFunction, Node=ros_actions.Node)


@pytest.mark.parametrize("launch", sorted(bringup.LAUNCHES))
@pytest.mark.parametrize("other", [False, True], ids=["defaults", "other_values"])
def test_launch_file_builds_the_described_nodes(stand_in_launch, launch, other):
    ns = runpy.run_path(str(LAUNCH_DIR / f"{launch}.launch.py"))
    ld = ns["generate_launch_description"]()
    *declared, opaque = ld.entities
    assert all(isinstance(d, stand_in_launch.DeclareLaunchArgument) for d in declared)
    assert [d.kwargs for d in declared] == bringup.launch_argument_kwargs(launch)
    assert isinstance(opaque, stand_in_launch.OpaqueFunction)
    values = {d.kwargs["name"]: d.kwargs["default_value"] for d in declared}  # what launch resolves
    if other:
        values.update(OTHER_VALUES[launch])
    context = types.SimpleNamespace(launch_configurations=values)
    nodes = opaque.kwargs["function"](context)
    assert all(isinstance(n, stand_in_launch.Node) and not n.args for n in nodes)
    assert [_unwrap(n.kwargs) for n in nodes] == [d.launch_kwargs() for d in bringup.nodes(launch, values)]


# ------------------------------------------------------------------------------------------------
# make run
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("launch", ["demo", "dual_arm"])
def test_run_main_options_are_the_launch_arguments(launch):
    actions = {a.dest: a for a in run_main.parser(launch)._actions if a.dest not in ("help", "launch")}
    assert list(actions) == [s.name for s in bringup.arguments(launch)]
    assert actions["real_time_factor"].option_strings == ["--real-time-factor"]
    assert {k: a.default for k, a in actions.items()} == {d["name"]: d["default_value"]
                                                           for d in bringup.launch_argument_kwargs(launch)}


@pytest.fixture
def fake_popen(monkeypatch):
    """subprocess.Popen of run_main replaced: the (command, environment) of every started node."""
    started = []

    class FakeProcess:
        pid, returncode = 12345, 0

        def __init__(self, cmd, env, start_new_session, preexec_fn):
            assert start_new_session and callable(preexec_fn)  # own group; stopped when run_main dies
            started.append((cmd, env))

        def poll(self):
            return 0

        def wait(self, timeout):
            return 0

    monkeypatch.setattr(run_main.subprocess, "Popen", FakeProcess)
    monkeypatch.setattr(run_main.signal, "signal", lambda *args: None)
    return started


@pytest.mark.parametrize("argv", [[], ["--robot", "wam", "--real-time-factor", "0.5", "--stale-timeout", "2",
                                       "--namespace", "arm1"],
                                  ["--launch", "dual_arm", "--right-robot", "gen3_lite", "--right-namespace", "b"]])
def test_run_main_starts_the_described_nodes_and_skips_a_missing_robot_state_publisher(
        fake_popen, monkeypatch, tmp_path, capsys, argv):
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tmp_path))  # a prefix without robot_state_publisher
    assert run_main.main(argv) == 1  # every fake node "exited" at once
    values = dict(zip(argv[::2], argv[1::2]))
    values = {k[2:].replace("-", "_"): v for k, v in values.items()}
    described = bringup.nodes(values.pop("launch", "demo"), values)
    ours = [n for n in described if not n.optional]
    assert [cmd for cmd, _ in fake_popen] == [n.command(sys.executable) for n in ours]
    assert all(env["OPENBLAS_NUM_THREADS"] == "1" for _, env in fake_popen)
    skipped = [line for line in capsys.readouterr().out.splitlines() if "robot_state_publisher" in line]
    assert skipped == [f"[run] robot_state_publisher skipped: lib/robot_state_publisher/robot_state_publisher is in "
                       f"no prefix of AMENT_PREFIX_PATH ({tmp_path}); source a ROS 2 installation that has "
                       f"robot_state_publisher; RViz will have no TF (/tf) for the arm"] * (len(described) - len(ours))


def test_run_main_starts_robot_state_publisher_found_through_ament_prefix_path(fake_popen, monkeypatch, tmp_path):
    exe = tmp_path / "ros" / "lib" / "robot_state_publisher" / "robot_state_publisher"
    exe.parent.mkdir(parents=True)
    exe.write_text("#!/bin/sh\n")
    exe.chmod(0o755)
    monkeypatch.setenv("AMENT_PREFIX_PATH", os.pathsep.join([str(tmp_path / "empty"), str(tmp_path / "ros")]))
    assert run_main.main(["--robot", "wam"]) == 1
    (cmd, env), = [(cmd, env) for cmd, env in fake_popen if cmd[0] == str(exe)]
    assert cmd == [str(exe), *bringup.nodes("demo", {"robot": "wam"})[-1].ros_arguments()]
    assert "robot_state_publisher" not in {c[2] for c, _ in fake_popen if c[0] == sys.executable}


def test_run_main_refuses_invalid_options(capsys):
    with pytest.raises(SystemExit) as info:
        run_main.main(["--real-time-factor", "fast"])
    assert info.value.code == 2
    assert "real_time_factor = 'fast': expected a number" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------
# the default primitives file
# ------------------------------------------------------------------------------------------------
def _advertised_robots() -> set[str]:
    """Robots the launch files' usage lines and the launches' argument defaults name."""
    text = " ".join(p.read_text() for p in LAUNCH_DIR.glob("*.launch.py"))
    defaults = {s.default for launch in bringup.LAUNCHES for s in bringup.arguments(launch) if s.name == "robot"}
    return set(re.findall(r"robot:=(\w+)", text)) | (defaults - {""})


def test_every_advertised_robot_has_primitives():
    assert _advertised_robots() == {"gen3_lite", "wam"}
    assert _advertised_robots() <= set(bringup.ROBOT_PRIMITIVES)


@pytest.mark.parametrize("robot", sorted(bringup.ROBOT_PRIMITIVES))
def test_chosen_primitives_file_serves_on_its_robot_without_refusal(robot):
    from deepprompt_ros import paths
    from deepprompt_ros.robots.spec import load_robot
    from deepprompt_ros.server.primitives_file import load_primitives, read_primitives_file

    for launch in ("demo", "primitive_server"):
        server, = [n for n in bringup.nodes(launch, {"robot": robot}) if n.executable == "primitive_server"]
        entries, errors = read_primitives_file(server.parameters["primitives_file"])
        assert entries and not errors
        prims, refused = load_primitives(entries, load_robot(robot).joint_names,
                                         lambda name: paths.find_data_file("models", name))
        assert refused == [] and sorted(prims) == sorted(e.name for e in entries)


def test_robot_without_primitives_of_the_package_needs_a_primitives_file():
    with pytest.raises(ConfigError, match="robot = 'ur5': the package has primitives for gen3_lite "
                                          r"\(primitives.yaml\), wam \(primitives_wam.yaml\) only; set primitives_file"):
        bringup.nodes("demo", {"robot": "ur5"})
    _, server, _ = bringup.nodes("demo", {"robot": "ur5", "primitives_file": "/tmp/ur5.yaml"})
    assert server.parameters["primitives_file"] == "/tmp/ur5.yaml"


def test_default_primitives_file_serves_on_the_default_robot_without_refusal():
    from deepprompt_ros import paths
    from deepprompt_ros.robots.spec import load_robot
    from deepprompt_ros.server.primitives_file import load_primitives, read_primitives_file

    entries, errors = read_primitives_file(ROOT / "config" / "primitives.yaml")
    assert not errors
    robot = load_robot(ServerConfig().robot)
    prims, refused = load_primitives(entries, robot.joint_names, lambda name: paths.find_data_file("models", name))
    assert refused == [] and sorted(prims) == sorted(e.name for e in entries) == ["reach"]
