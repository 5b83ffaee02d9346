"""Write docs/parameters.md from the parameter declarations (deepprompt_ros.common.params).

Every configurable thing of the package is a frozen dataclass made with ``common.params.param``:
the nodes' ROS parameters, the launch files' arguments and the training configuration. This tool
renders each one's table (name, type, default, range or choices, description); a test
(``test/test_parameters_doc.py``) fails when the file in the repository differs from what it
renders now.

Usage: ``python tools/gen_parameters_doc.py [--check]`` (``--check``: write nothing, exit 1 when
docs/parameters.md is out of date).
"""
from __future__ import annotations

import argparse
import importlib
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
OUTPUT = ROOT / "docs" / "parameters.md"
COMMAND = "python tools/gen_parameters_doc.py"

#: (node, "module:Class" of its parameters, parameters file in config/).
NODES = (
    ("primitive_server", "deepprompt_ros.server.config:ServerConfig", "primitive_server.yaml"),
    ("sim_bridge", "deepprompt_ros.sim.bridge_config:SimBridgeConfig", "sim_bridge.yaml"),
    ("demo_recorder", "deepprompt_ros.recording.config:RecorderConfig", "demo_recorder.yaml"),
)
#: Per-object parameters of sim_bridge, ``objects.<name>.<field>``.
SIM_OBJECTS = "deepprompt_ros.sim.bridge_config:ObjectConfig"
#: The training configuration: the package's export of ``TrainConfig`` (``deepprompt_ros._EXPORTS``
#: says where it lives).
TRAINING = "deepprompt_ros:TrainConfig"

HEADER = f"""# Parameters

Generated from the parameter declarations (`deepprompt_ros.common.params`) by `{COMMAND}`;
do not edit by hand (`test/test_parameters_doc.py` fails when this file is out of date).
Ranges are inclusive, except that a parenthesis excludes its bound ((0, inf): above 0); a list's
range applies to each of its elements.

ROS parameters are read once at start (read-only). An invalid value stops the node with exit
code 2 and a message that names every invalid parameter and what is expected.
`ros2 param describe /<node> <parameter>` shows the same description and range.
"""


def _load(target: str):
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)


def _where(cls) -> str:
    """Where ``cls`` and each dataclass it inherits parameters from are declared."""
    parts = []
    for c in cls.__mro__:
        if c is object or not hasattr(c, "__dataclass_fields__"):
            continue
        path = pathlib.Path(sys.modules[c.__module__].__file__).resolve().relative_to(ROOT)
        parts.append(f"`{c.__name__}` in `{path.as_posix()}`")
    return parts[0] + (" (with the fields of " + ", ".join(parts[1:]) + ")" if parts[1:] else "")


def render() -> str:
    """The text of docs/parameters.md."""
    from deepprompt_ros import bringup
    from deepprompt_ros.common.params import markdown_table, specs_of

    out = [HEADER, "## Nodes\n"]
    for node, target, config in NODES:
        cls = _load(target)
        out.append(f"### {node}\n\nDeclared as {_where(cls)}; `config/{config}` shows the defaults "
                   f"(`ros2 run deepprompt_ros {node} --ros-args --params-file config/{config}`).\n")
        out.append(markdown_table(specs_of(cls)) + "\n")
        if node == "sim_bridge":
            objects = _load(SIM_OBJECTS)
            out.append(f"Each object of `object_names` is described by the parameters `objects.<name>.<field>` "
                       f"({_where(objects)}):\n")
            out.append(markdown_table(specs_of(objects)) + "\n")
    out.append("## Launch files\n\n"
               "`ros2 launch deepprompt_ros <file> [<argument>:=<value> ...]`; the nodes each one starts are "
               "described once in `deepprompt_ros/bringup.py`. `make run` starts the nodes of `demo.launch.py` "
               "with the same arguments as options (`--robot`, `--real-time-factor`, ...).\n")
    for name, launch in bringup.LAUNCHES.items():
        started = ", ".join(sorted({n.executable for n in bringup.nodes(name)}))
        out.append(f"### {name}.launch.py\n\n{launch.description[0].upper()}{launch.description[1:]}; "
                   f"starts {started}.\n")
        out.append(markdown_table(bringup.arguments(name)) + "\n")
    train = _load(TRAINING)
    specs = specs_of(train)
    out.append("## Training configuration\n")
    if specs:
        out.append(f"Keys of the training YAML files (`config/train_*.yaml`, `python -m deepprompt_ros.training.cli "
                   f"--config <file>`); declared as {_where(train)}.\n")
        out.append(markdown_table(specs) + "\n")
    else:
        out.append(f"`{train.__name__}` ({train.__module__}) does not declare its fields with "
                   f"`common.params.param` yet; its section appears here once it does.\n")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 when the file is out of date")
    args = ap.parse_args(argv)
    text = render()
    current = OUTPUT.read_text() if OUTPUT.is_file() else None
    if args.check:
        if current != text:
            print(f"{OUTPUT.relative_to(ROOT)} is out of date; run: {COMMAND}")
            return 1
        return 0
    if current != text:
        OUTPUT.parent.mkdir(parents=True, exist_ok=True)
        OUTPUT.write_text(text)
        print(f"wrote {OUTPUT.relative_to(ROOT)}")
    else:
        print(f"{OUTPUT.relative_to(ROOT)} is up to date")
    return 0


if __name__ == "__main__":
    sys.exit(main())
