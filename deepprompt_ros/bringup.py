"""The nodes each launch file starts, described once: what ``ros2 launch deepprompt_ros <file>``
and ``make run`` start.

A launch (one of :data:`LAUNCHES`: ``demo``, ``dual_arm``, ``primitive_server``, ``record``) has arguments, a
frozen dataclass made with :func:`~deepprompt_ros.common.params.param` (name, default,
description, range), and a function from their values to the nodes to start
(:class:`NodeDescription`: package, executable, node name, namespace, parameter files, parameters,
remappings, arguments). The launch files in ``launch/`` declare the arguments and turn each
description into a ``launch_ros.actions.Node`` (:meth:`NodeDescription.launch_kwargs`); ``make run``
(:mod:`deepprompt_ros.run_main`) turns the demo's into command lines
(:meth:`NodeDescription.command`). Argument values arrive as strings (as a launch file gets them)
and are checked here. No rclpy or launch import.

Several robots: each robot's nodes run under a namespace of their own (every topic, service, the
Execute action and the JointTrajectory command topic follow it); ``dual_arm`` is the demo twice, in
two namespaces, and only its first arm's sim_bridge publishes ``/clock`` (the one global topic).

The primitives the server serves follow the robot (:data:`ROBOT_PRIMITIVES`), and the demo and
record launches add robot_state_publisher with the robot's URDF (TF for RViz) as an optional node:
a launch under a ROS 2 installation starts it, ``make run`` only where its executable is installed.
"""
from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import re
from typing import Any, Callable, Mapping, NamedTuple

from deepprompt_ros.common.params import ConfigError, ParamSpec, from_mapping, param, specs_of
from deepprompt_ros.paths import PACKAGE, find_data_file

__all__ = ["NodeDescription", "Launch", "LAUNCHES", "DemoArguments", "DualArmArguments", "PrimitiveServerArguments",
           "RecordArguments", "EXECUTABLES", "ROBOT_PRIMITIVES", "arguments", "argument_text",
           "launch_argument_kwargs", "parse_arguments", "nodes", "find_executable", "primitives_file"]

#: Executable (console script of setup.py) -> the module whose ``main()`` it runs.
EXECUTABLES = {
    "sim_bridge": "deepprompt_ros.ros.sim_bridge",
    "primitive_server": "deepprompt_ros.ros.primitive_server",
    "demo_recorder": "deepprompt_ros.ros.demo_recorder",
}

#: Robot -> the package's primitives file (in ``config/``) that serves on it without a refusal.
ROBOT_PRIMITIVES = {"gen3_lite": "primitives.yaml", "wam": "primitives_wam.yaml"}

#: Environment of every node of the package: one OpenBLAS thread (small matrices; no BLAS threads competing with
#: the 1 kHz loops).
NODE_ENVIRONMENT = (("OPENBLAS_NUM_THREADS", "1"),)


def _ros_value(value) -> str:
    """``value`` as the YAML of a ``-p name:=value`` argument."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, tuple):
        value = list(value)
    return json.dumps(value)  # JSON is YAML: quoted strings, lists, numbers


def find_executable(package: str, executable: str) -> pathlib.Path | None:
    """``<prefix>/lib/<package>/<executable>`` of the first prefix of ``AMENT_PREFIX_PATH`` that has it
    (where ``ros2 run`` finds a package's executables), or None."""
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        path = pathlib.Path(prefix) / "lib" / package / executable
        if prefix and path.is_file() and os.access(path, os.X_OK):
            return path
    return None


def _flatten(values: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested parameter mappings of a parameters file as dotted names (``camera: {topic: x}`` ->
    ``camera.topic``)."""
    out = {}
    for k, v in values.items():
        if isinstance(v, Mapping):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


@dataclasses.dataclass(frozen=True)
class NodeDescription:
    """One node to start.

    Attributes
    ----------
    executable : str
        Executable of ``package``: for this package a console script (a key of :data:`EXECUTABLES`).
    name : str
        Node name (the executable's own node name unless remapped).
    parameter_files : tuple of str
        Parameter YAML files, applied in order.
    parameters : dict
        Parameters set after the files (they win), name -> value.
    remappings : tuple of (str, str)
        Topic / service remappings (from, to).
    arguments : tuple of str
        Command-line arguments before ``--ros-args``.
    environment : tuple of (str, str)
        Environment variables set for the node.
    package : str
        ROS package of the executable.
    namespace : str
        Namespace of the node, relative (``arm1``, ``cell/arm1``); empty = none.
    optional : str
        Empty for a node that must run. Otherwise the node is optional and this says what is
        missing without it: ``make run`` starts it only where its executable is installed.
    """

    executable: str
    name: str
    parameter_files: tuple[str, ...] = ()
    parameters: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    remappings: tuple[tuple[str, str], ...] = ()
    arguments: tuple[str, ...] = ()
    environment: tuple[tuple[str, str], ...] = NODE_ENVIRONMENT
    package: str = PACKAGE
    namespace: str = ""
    optional: str = ""

    @property
    def module(self) -> str:
        """The Python module run by the executable (this package's executables)."""
        return EXECUTABLES[self.executable]

    @property
    def renamed(self) -> bool:
        """Whether the node needs a node-name remap: each executable names its node after itself, and
        a remap is passed only for another name (it applies to every node of the process)."""
        return self.name != self.executable

    def parameter_values(self) -> dict[str, Any]:
        """The parameters given after the files. Under a namespace, first the sections of the
        parameter files keyed by the node's plain name: rcl matches a section against the fully
        qualified name ``/<namespace>/<name>``, so there they would not apply (sections keyed
        ``/**`` and the like still come from the files). Then :attr:`parameters`."""
        values: dict[str, Any] = {}
        if self.namespace:
            import yaml

            for f in self.parameter_files:
                section = (yaml.safe_load(pathlib.Path(f).read_text()) or {}).get(self.name) or {}
                values.update(_flatten(section.get("ros__parameters") or {}))
        return {**values, **self.parameters}

    def launch_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of ``launch_ros.actions.Node`` for this node."""
        kw = dict(package=self.package, executable=self.executable)
        if self.renamed:
            kw["name"] = self.name
        if self.namespace:
            kw["namespace"] = self.namespace
        values = {k: list(v) if isinstance(v, tuple) else v for k, v in self.parameter_values().items()}  # YAML lists
        return dict(kw, parameters=[*self.parameter_files] + ([values] if values else []),
                    remappings=list(self.remappings), arguments=list(self.arguments),
                    additional_env=dict(self.environment), output="screen")

    def ros_arguments(self) -> list[str]:
        """``--ros-args ...`` of the same node as :meth:`launch_kwargs` gives ``launch_ros``."""
        out = ["--ros-args"]
        if self.renamed:
            out += ["-r", f"__node:={self.name}"]
        if self.namespace:
            out += ["-r", f"__ns:=/{self.namespace}"]
        for f in self.parameter_files:
            out += ["--params-file", f]
        for k, v in self.parameter_values().items():
            out += ["-p", f"{k}:={_ros_value(v)}"]
        for a, b in self.remappings:
            out += ["-r", f"{a}:={b}"]
        return out

    def command(self, python: str) -> list[str]:
        """Command line that starts the node: this package's executables with the interpreter
        ``python``, another package's by its installed executable (:func:`find_executable`).

        Raises
        ------
        FileNotFoundError
            Another package's executable is in no prefix of ``AMENT_PREFIX_PATH``.
        """
        if self.package == PACKAGE:
            return [python, "-m", self.module, *self.arguments, *self.ros_arguments()]
        path = find_executable(self.package, self.executable)
        if path is None:
            prefixes = os.environ.get("AMENT_PREFIX_PATH", "") or "not set"
            raise FileNotFoundError(f"lib/{self.package}/{self.executable} is in no prefix of AMENT_PREFIX_PATH "
                                    f"({prefixes}); source a ROS 2 installation that has {self.package}")
        return [str(path), *self.arguments, *self.ros_arguments()]


def _config(name: str) -> str:
    """Path of the package's ``config/<name>`` (installed share folder first, then the source tree)."""
    return str(find_data_file("config", name))


def primitives_file(robot: str) -> str:
    """Path of the package's primitives file for ``robot`` (:data:`ROBOT_PRIMITIVES`); ConfigError when
    the package has none for it."""
    if robot not in ROBOT_PRIMITIVES:
        shipped = ", ".join(f"{r} ({f})" for r, f in ROBOT_PRIMITIVES.items())
        raise ConfigError(f"robot = '{robot}': the package has primitives for {shipped} only; set primitives_file "
                          f"to a primitives file whose models drive the joints of '{robot}'")
    return _config(ROBOT_PRIMITIVES[robot])


_NAMESPACE_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$")


def _namespace(text: str) -> str:
    """The namespace argument as a relative namespace ('' = none; one leading '/' is accepted)."""
    ns = text[1:] if text.startswith("/") else text
    if ns and not _NAMESPACE_RE.match(ns):
        raise ConfigError(f"namespace = '{text}': expected names of letters, digits and '_' (not starting with a "
                          "digit) separated by '/', e.g. 'arm1' or 'cell/arm1'; empty = no namespace")
    return ns


def _robot_state_publisher(robot: str, namespace: str) -> NodeDescription:
    """robot_state_publisher with the URDF of ``robot`` (the file sim_bridge loads and publishes):
    /tf of the arm from joint_states, for RViz."""
    from deepprompt_ros.robots.spec import urdf_path  # late: pinocchio loads only for the launches that use it

    try:
        urdf = urdf_path(robot).read_text()
    except ValueError as exc:  # unknown robot: the message lists the known ones
        raise ConfigError(f"robot = '{robot}': {exc}") from None
    return NodeDescription("robot_state_publisher", "robot_state_publisher", (), {"robot_description": urdf},
                           environment=(), package="robot_state_publisher", namespace=namespace,
                           optional="RViz will have no TF (/tf) for the arm")


# ------------------------------------------------------------------------------------------------
# launch arguments
# ------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class DemoArguments:
    """Arguments of ``demo.launch.py`` and ``make run``."""

    robot: str = param("gen3_lite", "robot of the simulation and of the server: gen3_lite or wam (served with "
                       "the package's primitives for it), or a fixed-base arm of example-robot-data (with "
                       "primitives_file)")
    real_time_factor: float = param(1.0, "sim_bridge real_time_factor: simulated seconds per wall-clock second",
                                    min=0.0, max=100.0)
    stale_timeout: float = param(1.0, "primitive_server stale_timeout for the simulated robot (the server's "
                                 "default 0.2 s suits a real arm; the Python simulation can pause longer on a "
                                 "busy machine)", min=0.001, max=60.0, unit="s")
    primitives_file: str = param("", "primitives to serve; empty = the package's for the robot "
                                 "(config/primitives.yaml for gen3_lite, config/primitives_wam.yaml for wam)")
    namespace: str = param("", "namespace of every node (its topics, services and name); empty = none")


@dataclasses.dataclass(frozen=True)
class DualArmArguments:
    """Arguments of ``dual_arm.launch.py`` and ``make run-dual``: two simulated arms, each with the demo's
    nodes under its own namespace."""

    left_robot: str = param("gen3_lite", "robot of the first arm (as the demo's robot)")
    right_robot: str = param("wam", "robot of the second arm (as the demo's robot)")
    left_namespace: str = param("left_arm", "namespace of the first arm's nodes; its sim_bridge publishes /clock")
    right_namespace: str = param("right_arm", "namespace of the second arm's nodes (publish_clock false)")
    real_time_factor: float = param(1.0, "sim_bridge real_time_factor of both arms", min=0.0, max=100.0)
    stale_timeout: float = param(1.0, "primitive_server stale_timeout of both servers (as the demo's)",
                                 min=0.001, max=60.0, unit="s")


@dataclasses.dataclass(frozen=True)
class PrimitiveServerArguments:
    """Arguments of ``primitive_server.launch.py`` (the server alone, for a real arm)."""

    params_file: str = param("", "parameters file of primitive_server; empty = the package's "
                             "config/primitive_server.yaml")
    robot: str = param("", "robot whose joints and limits the server uses; empty = the parameters file's")
    controller: str = param("", "JointTrajectory output goes to <controller>/joint_trajectory; empty = the "
                            "parameters file's (joint_trajectory_controller by default)")
    primitives_file: str = param("", "primitives to serve; empty = the package's for robot when robot is set and "
                                 "params_file is not (config/primitives.yaml for gen3_lite, "
                                 "config/primitives_wam.yaml for wam), else the parameters file's")
    namespace: str = param("", "namespace of the node (its topics, services and name); empty = none")


@dataclasses.dataclass(frozen=True)
class RecordArguments:
    """Arguments of ``record.launch.py`` (kinesthetic recording in simulation)."""

    robot: str = param("gen3_lite", "robot of the simulation: gen3_lite, wam or a fixed-base arm of "
                       "example-robot-data")
    output_directory: str = param("", "dataset folder of the demonstrations; empty = demo_recorder.yaml's "
                                  "(~/deepprompt_demos)")
    namespace: str = param("", "namespace of every node (its topics, services and name); empty = none")


def _demo(a: DemoArguments) -> list[NodeDescription]:
    ns = _namespace(a.namespace)
    return [
        NodeDescription("sim_bridge", "sim_bridge", (_config("sim_bridge.yaml"),),
                        {"robot": a.robot, "real_time_factor": a.real_time_factor}, namespace=ns),
        NodeDescription("primitive_server", "primitive_server", (_config("primitive_server.yaml"),),
                        {"robot": a.robot, "stale_timeout": a.stale_timeout,
                         "primitives_file": a.primitives_file or primitives_file(a.robot)}, namespace=ns),
        _robot_state_publisher(a.robot, ns),
    ]


def _dual_arm(a: DualArmArguments) -> list[NodeDescription]:
    left, right = _namespace(a.left_namespace), _namespace(a.right_namespace)
    if not left or not right or left == right:
        raise ConfigError(f"left_namespace = '{a.left_namespace}', right_namespace = '{a.right_namespace}': "
                          "expected two different, non-empty namespaces (one per arm)")
    arms = [_demo(DemoArguments(robot=robot, real_time_factor=a.real_time_factor, stale_timeout=a.stale_timeout,
                                namespace=ns)) for robot, ns in ((a.left_robot, left), (a.right_robot, right))]
    # /clock is global: one publisher (the first arm's simulation), not two with different times
    sim, *others = arms[1]
    arms[1] = [dataclasses.replace(sim, parameters={**sim.parameters, "publish_clock": False}), *others]
    return arms[0] + arms[1]


def _primitive_server(a: PrimitiveServerArguments) -> list[NodeDescription]:
    prims = a.primitives_file or (primitives_file(a.robot) if a.robot and not a.params_file else "")
    overrides = {k: v for k, v in (("robot", a.robot), ("controller", a.controller),
                                   ("primitives_file", prims)) if v}
    return [NodeDescription("primitive_server", "primitive_server",
                            (a.params_file or _config("primitive_server.yaml"),), overrides,
                            namespace=_namespace(a.namespace))]


def _record(a: RecordArguments) -> list[NodeDescription]:
    ns = _namespace(a.namespace)
    recorder = {"output_directory": a.output_directory} if a.output_directory else {}
    return [
        NodeDescription("sim_bridge", "sim_bridge", (_config("sim_bridge.yaml"),),
                        {"robot": a.robot, "kinesthetic": True}, namespace=ns),
        NodeDescription("demo_recorder", "demo_recorder", (_config("demo_recorder.yaml"),), recorder, namespace=ns),
        _robot_state_publisher(a.robot, ns),
    ]


class Launch(NamedTuple):
    """A launch file: its arguments (a dataclass), its nodes from their values, what it is for."""

    arguments: type
    nodes: Callable[[Any], list[NodeDescription]]
    description: str


#: Launch name -> :class:`Launch`; ``launch/<name>.launch.py`` is the launch file.
LAUNCHES: dict[str, Launch] = {
    "demo": Launch(DemoArguments, _demo, "the simulated arm (sim_bridge) and primitive_server with the "
                   "shipped primitives of the robot, ready for service calls, and robot_state_publisher (TF "
                   "for RViz); what make run starts"),
    "dual_arm": Launch(DualArmArguments, _dual_arm, "two simulated arms side by side (the Gen3 lite and the WAM by "
                       "default), each with the demo's nodes under its own namespace; one planner serves both"),
    "primitive_server": Launch(PrimitiveServerArguments, _primitive_server, "primitive_server alone, for a "
                               "real arm: its driver publishes joint_states and runs the controller"),
    "record": Launch(RecordArguments, _record, "kinesthetic recording: sim_bridge in kinesthetic mode, "
                     "demo_recorder and robot_state_publisher (TF for RViz)"),
}


def _launch(name: str) -> Launch:
    if name not in LAUNCHES:
        raise ValueError(f"unknown launch '{name}'; expected one of {', '.join(LAUNCHES)}")
    return LAUNCHES[name]


def arguments(launch: str) -> tuple[ParamSpec, ...]:
    """The arguments of ``launch`` (name, default, description, range, choices)."""
    return specs_of(_launch(launch).arguments)


def argument_text(spec: ParamSpec, value=None) -> str:
    """``value`` (default: the argument's default) as the string a launch argument holds."""
    value = spec.default if value is None else value
    return _ros_value(value) if spec.type in ("bool", "double[]", "string[]") else str(value)


def launch_argument_kwargs(launch: str) -> list[dict[str, Any]]:
    """Keyword arguments of ``launch.actions.DeclareLaunchArgument`` for each argument of ``launch``."""
    out = []
    for spec in arguments(launch):
        unit = f" ({spec.unit})" if spec.unit else ""
        kw = dict(name=spec.name, default_value=argument_text(spec), description=spec.description + unit)
        if spec.choices:
            kw["choices"] = list(spec.choices)
        out.append(kw)
    return out


def _parse(spec: ParamSpec, text: str):
    if spec.type == "string":
        return text
    import yaml

    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text  # the check names it and what is expected


def parse_arguments(launch: str, values: Mapping[str, str] | None = None):
    """The arguments of ``launch`` from their string values (missing ones: defaults).

    Raises
    ------
    ConfigError
        Unknown or invalid arguments, each named with what is expected.
    """
    cls = _launch(launch).arguments
    specs = {s.name: s for s in specs_of(cls)}
    parsed = {k: _parse(specs[k], v) if k in specs and isinstance(v, str) else v
              for k, v in (values or {}).items()}
    try:
        return from_mapping(cls, parsed)
    except ConfigError as exc:  # "invalid <class> parameters:\n  <one line per problem>"
        raise ConfigError(f"invalid arguments of launch '{launch}':\n" + str(exc).partition("\n")[2]) from None


def nodes(launch: str, values: Mapping[str, str] | None = None) -> list[NodeDescription]:
    """The nodes ``launch`` starts with the argument values ``values`` (strings; missing ones:
    defaults). Raises :class:`ConfigError` for invalid arguments (also a robot without a URDF, or
    without primitives of the package when no primitives file is given) and FileNotFoundError when
    a parameter file of the package is missing."""
    args = parse_arguments(launch, values)
    try:
        return _launch(launch).nodes(args)
    except ConfigError as exc:  # one line: the argument and what is expected
        raise ConfigError(f"invalid arguments of launch '{launch}':\n  {exc}") from None
