"""The package's shape: every subpackage outside ``ros/`` imports with rclpy blocked, ``ros/`` is the
only rclpy importer, the module import graph (late imports inside functions included) has no
cycle, and the subpackages import one way, in the layer order of :data:`LAYERS`."""
import ast
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PKG = ROOT / "deepprompt_ros"
ROS_ONLY = ("rclpy", "rosidl_runtime_py", "deepprompt_msgs", "rcl_interfaces", "builtin_interfaces",
            "sensor_msgs", "std_msgs", "std_srvs", "geometry_msgs", "trajectory_msgs", "rosgraph_msgs",
            "launch", "launch_ros")


def _module_name(path: pathlib.Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, pathlib.Path]:
    return {_module_name(p): p for p in sorted(PKG.rglob("*.py"))}


def _imports(name: str, path: pathlib.Path, known: set[str], aliases: dict[str, str] | None = None) -> set[str]:
    """Every package module ``name`` imports, at top level or inside functions (TYPE_CHECKING blocks
    excluded: they never run). ``aliases``: {dotted name: module} for names that stand for a module
    elsewhere (the top-level package's lazy exports)."""
    tree = ast.parse(path.read_text(), str(path))
    is_pkg = path.name == "__init__.py"
    package = name if is_pkg else name.rpartition(".")[0]
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.dump(node.test):
            skip.update(id(n) for b in node.body for n in ast.walk(b))
    found: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                parts = parts[: len(parts) - (node.level - 1)]
                base = ".".join(parts + ([base] if base else []))
            targets = [base] + [f"{base}.{a.name}" for a in node.names]
        for t in targets:
            t = (aliases or {}).get(t, t)
            # the longest known module that the target names (a submodule, or the module itself)
            while t and t not in known:
                t = t.rpartition(".")[0]
            if t and t != name:
                found.add(t)
    return found


def test_import_graph_has_no_cycle():
    mods = _modules()
    known = set(mods)
    graph = {m: _imports(m, p, known) for m, p in mods.items()}
    # a package __init__ that re-exports lazily imports nothing at run time; edges to an __init__
    # (a parent package) are implicit in Python and not a dependency between concepts
    graph = {m: {t for t in ts if not (mods[t].name == "__init__.py" and m.startswith(t + "."))}
             for m, ts in graph.items()}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str):
        state[m] = 1
        stack.append(m)
        for t in sorted(graph[m]):
            if state.get(t) == 1:
                cycle = stack[stack.index(t):] + [t]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if t not in state:
                visit(t)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)
    # the test sees edges at all (a parser that finds nothing would pass vacuously)
    assert "deepprompt_ros.model.network" in graph["deepprompt_ros.primitive.deep_promp"]


#: The layers of the package: each group (a subpackage, or a top-level module) and the groups right
#: below it. A module may import its own group, the groups below its group and, transitively,
#: everything below those; never a group above or beside its own. Imports inside functions count;
#: TYPE_CHECKING imports (annotations only) and the top-level package (its version and lazy
#: exports, which are resolved to the module they name) do not.
LAYERS: dict[str, tuple[str, ...]] = {
    "common": (),
    # the method
    "model": ("common",),
    "primitive": ("model",),
    "training": ("primitive", "data.builtin"),
    "evaluation": ("data",),  # the reconstruction metric needs only data (and the models' interface)
    "baselines": ("training", "evaluation"),
    # data, robots and simulation
    "data": ("common",),
    "robots": ("data",),
    "sim": ("robots",),
    "sim.tasks": ("sim",),
    # The one group that is not a whole subpackage: the registry of the built-in data sets lives in
    # data/ but lists the task generators of sim.tasks (which write data's format), so it is a
    # layer of its own above them; the rest of data/ may not import it.
    "data.builtin": ("sim.tasks",),
    # serving
    "execution": ("common",),
    "server": ("execution", "primitive"),
    "recording": ("data",),
    # the top-level modules and the ROS nodes on top of everything they run
    "paths": (),
    "bringup": ("common", "paths", "robots"),  # robots: the URDF robot_state_publisher gets
    "run_main": ("bringup",),
    "ros": ("server", "recording", "sim", "bringup"),
}


def _group(module: str) -> str | None:
    """The group of :data:`LAYERS` a package module belongs to (the longest that names it)."""
    rest = module.partition(".")[2]
    matches = [g for g in LAYERS if rest == g or rest.startswith(g + ".")]
    return max(matches, key=len) if matches else None


def _below(group: str) -> set[str]:
    """Every group that ``group`` may import: those right below it and, transitively, below those."""
    seen: set[str] = set()
    todo = list(LAYERS[group])
    while todo:
        g = todo.pop()
        if g not in seen:
            seen.add(g)
            todo.extend(LAYERS[g])
    return seen


def test_layers_are_a_one_way_order():
    assert all(set(below) <= set(LAYERS) for below in LAYERS.values()), "LAYERS names an unknown group"
    circular = sorted(g for g in LAYERS if g in _below(g))
    assert not circular, f"LAYERS puts these groups below themselves: {circular}"


def test_subpackages_import_one_way_in_layer_order():
    import deepprompt_ros

    mods = _modules()
    known = set(mods)
    exports = {f"deepprompt_ros.{name}": f"deepprompt_ros.{module}.{name}"
               for name, module in deepprompt_ros._EXPORTS.items()}
    undeclared = sorted(m for m in mods if m != "deepprompt_ros" and _group(m) is None)
    assert not undeclared, (f"modules in no group of LAYERS: {undeclared}; add their subpackage to LAYERS "
                            "with the groups it stands on")
    upward, checked = [], set()
    for m, path in sorted(mods.items()):
        if m == "deepprompt_ros":
            continue
        group = _group(m)
        allowed = _below(group)
        for t in sorted(_imports(m, path, known, exports)):
            target = _group(t)
            if t == "deepprompt_ros" or target == group:
                continue
            checked.add((group, target))
            if target not in allowed:
                upward.append(f"{m} imports {t}: {group} may import only {sorted(allowed) or 'nothing'}")
    assert not upward, ("imports against the layer order of LAYERS (move the code to the layer that needs "
                        "it, or pass it in from above):\n  " + "\n  ".join(upward))
    # the test sees edges at all (a parser that finds nothing would pass vacuously)
    assert {("server", "execution"), ("primitive", "model"), ("data.builtin", "sim.tasks")} <= checked


def test_only_ros_package_imports_rclpy():
    offenders = []
    for name, path in _modules().items():
        if name.startswith("deepprompt_ros.ros"):
            continue
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            mods = ([a.name for a in node.names] if isinstance(node, ast.Import)
                    else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
            offenders += [f"{name}: {m}" for m in mods if m.split(".")[0] in ROS_ONLY]
    assert not offenders, offenders


def test_every_package_outside_ros_imports_with_rclpy_blocked():
    names = sorted(m for m in _modules() if not m.startswith("deepprompt_ros.ros"))
    code = (
        "import sys, importlib, importlib.abc\n"
        f"BLOCK = {ROS_ONLY!r}\n"
        "class Block(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, name, path, target=None):\n"
        "        if name.split('.')[0] in BLOCK:\n"
        "            raise ImportError('blocked ' + name)\n"
        "sys.meta_path.insert(0, Block())\n"
        f"for m in {names!r}:\n"
        "    importlib.import_module(m)\n"
        "assert not any(k.split('.')[0] in BLOCK for k in sys.modules), sorted(sys.modules)\n"
        "print('\\n'.join(sorted(k for k in sys.modules if k.split('.')[0] == 'deepprompt_ros')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    # exactly the named modules were loaded: every one of them, and no module of ros/ on the way
    assert out.stdout.split() == names
