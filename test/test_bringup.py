"""The one description of what the launch files and ``make run`` start (deepprompt_ros.bringup):
node names, executables, parameter files and parameters; each launch file in launch/ builds exactly
the described nodes (run against small stand-ins of ``launch`` / ``launch_ros``, which cannot be
installed here: this checks the files' wiring, not launch itself); run_main starts the same nodes
with the same parameters; the default primitives file serves on the default robot."""
import importlib.metadata
import pathlib
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
    "demo": {"robot": "wam", "real_time_factor": "0.5", "stale_timeout": "2"},
    "primitive_server": {"params_file": str(ROOT / "config" / "primitive_server.yaml"), "robot": "wam",
                         "controller": "arm_controller", "primitives_file": "/tmp/primitives.yaml"},
    "record": {"robot": "wam", "output_directory": "/tmp/demos"},
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
    assert len({n.name for n in nodes}) == len(nodes)
    for node in nodes:
        assert node.executable in bringup.EXECUTABLES and node.package == "deepprompt_ros"
        specs = {s.name: s for s in specs_of(NODE_CONFIG[node.executable])}
        for f in node.parameter_files:
            assert pathlib.Path(f).is_file(), f
            values = yaml.safe_load(pathlib.Path(f).read_text())[node.name]["ros__parameters"]
            assert set(values) - {"objects"} <= set(k.split(".")[0] for k in specs) | set(specs)
        for name, value in node.parameters.items():
            assert name in specs, f"{node.executable} has no parameter {name}"
            assert not check(specs[name], value), check(specs[name], value)


def test_demo_is_the_simulated_arm_and_the_server():
    sim, server = bringup.nodes("demo")
    assert (sim.executable, sim.name, server.executable, server.name) == (
        "sim_bridge", "sim_bridge", "primitive_server", "primitive_server")
    assert [pathlib.Path(f).name for f in sim.parameter_files + server.parameter_files] == [
        "sim_bridge.yaml", "primitive_server.yaml"]
    assert sim.parameters == {"robot": "gen3_lite", "real_time_factor": 1.0}
    assert server.parameters == {"robot": "gen3_lite", "stale_timeout": 1.0}
    sim, server = bringup.nodes("demo", OTHER_VALUES["demo"])
    assert sim.parameters == {"robot": "wam", "real_time_factor": 0.5}
    assert server.parameters == {"robot": "wam", "stale_timeout": 2.0}
    assert dict(sim.environment) == dict(server.environment) == {"OPENBLAS_NUM_THREADS": "1"}


def test_primitive_server_launch_overrides_only_what_is_given():
    server, = bringup.nodes("primitive_server")
    assert [pathlib.Path(f).name for f in server.parameter_files] == ["primitive_server.yaml"]
    assert server.parameters == {}
    server, = bringup.nodes("primitive_server", OTHER_VALUES["primitive_server"])
    assert server.parameter_files == (OTHER_VALUES["primitive_server"]["params_file"],)
    assert server.parameters == {"robot": "wam", "controller": "arm_controller",
                                 "primitives_file": "/tmp/primitives.yaml"}


def test_record_launch_starts_the_sim_in_kinesthetic_mode_and_the_recorder():
    sim, recorder = bringup.nodes("record")
    assert sim.parameters == {"robot": "gen3_lite", "kinesthetic": True}
    assert (recorder.executable, recorder.parameters) == ("demo_recorder", {})
    assert [pathlib.Path(f).name for f in recorder.parameter_files] == ["demo_recorder.yaml"]
    _, recorder = bringup.nodes("record", OTHER_VALUES["record"])
    assert recorder.parameters == {"output_directory": "/tmp/demos"}


def test_invalid_arguments_are_refused_with_what_is_expected():
    with pytest.raises(ConfigError) as info:
        bringup.nodes("demo", {"real_time_factor": "fast", "robto": "wam", "stale_timeout": "-1"})
    text = str(info.value)
    for part in ("launch 'demo'", "real_time_factor = 'fast': expected a number", "unknown parameter 'robto'",
                 "stale_timeout = -1 s: expected a value in [0.001, 60] s"):
        assert part in text, text
    with pytest.raises(ValueError, match="unknown launch 'nope'; expected one of demo, primitive_server, record"):
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
        assert "__node:=" not in " ".join(node.command("/py")) and "name" not in node.launch_kwargs()


# ------------------------------------------------------------------------------------------------
# the launch files, against stand-ins of launch / launch_ros
# ------------------------------------------------------------------------------------------------
class _Action:
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


class _LaunchDescription:
    def __init__(self, entities=()):
        self.entities = list(entities)


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
    launch_ros.actions = ros_actions
    for name, module in {"launch": launch, "launch.actions": actions, "launch.substitutions": substitutions,
                         "launch_ros": launch_ros, "launch_ros.actions": ros_actions}.items():
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
    assert [n.kwargs for n in nodes] == [d.launch_kwargs() for d in bringup.nodes(launch, values)]


# ------------------------------------------------------------------------------------------------
# make run
# ------------------------------------------------------------------------------------------------
def test_run_main_options_are_the_demo_arguments():
    actions = {a.dest: a for a in run_main.parser()._actions if a.dest != "help"}
    assert list(actions) == [s.name for s in bringup.arguments("demo")]
    assert actions["real_time_factor"].option_strings == ["--real-time-factor"]
    assert {k: a.default for k, a in actions.items()} == {d["name"]: d["default_value"]
                                                           for d in bringup.launch_argument_kwargs("demo")}


@pytest.mark.parametrize("argv", [[], ["--robot", "wam", "--real-time-factor", "0.5", "--stale-timeout", "2"]])
def test_run_main_starts_the_described_nodes(monkeypatch, argv):
    started = []

    class FakeProcess:
        pid, returncode = 12345, 0

        def __init__(self, cmd, env, start_new_session):
            started.append((cmd, env))

        def poll(self):
            return 0

        def wait(self, timeout):
            return 0

    monkeypatch.setattr(run_main.subprocess, "Popen", FakeProcess)
    monkeypatch.setattr(run_main.signal, "signal", lambda *args: None)
    assert run_main.main(argv) == 1  # every fake node "exited" at once
    values = dict(zip(argv[::2], argv[1::2]))
    values = {k[2:].replace("-", "_"): v for k, v in values.items()}
    expected = [n.command(sys.executable) for n in bringup.nodes("demo", values)]
    assert [cmd for cmd, _ in started] == expected
    assert all(env["OPENBLAS_NUM_THREADS"] == "1" for _, env in started)


def test_run_main_refuses_invalid_options(capsys):
    with pytest.raises(SystemExit) as info:
        run_main.main(["--real-time-factor", "fast"])
    assert info.value.code == 2
    assert "real_time_factor = 'fast': expected a number" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------
# the default primitives file
# ------------------------------------------------------------------------------------------------
def test_default_primitives_file_serves_on_the_default_robot_without_refusal():
    from deepprompt_ros import paths
    from deepprompt_ros.robots.spec import load_robot
    from deepprompt_ros.server.primitives_file import load_primitives, read_primitives_file

    entries, errors = read_primitives_file(ROOT / "config" / "primitives.yaml")
    assert not errors
    robot = load_robot(ServerConfig().robot)
    prims, refused = load_primitives(entries, robot.joint_names, lambda name: paths.find_data_file("models", name))
    assert refused == [] and sorted(prims) == sorted(e.name for e in entries) == ["reach"]
