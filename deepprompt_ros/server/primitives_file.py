"""The primitives file (which models the server serves, under which names) and loading its
models against the robot.
"""
from __future__ import annotations

import dataclasses
import math
import pathlib
import re
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from deepprompt_ros.common.params import ConfigError

if TYPE_CHECKING:  # imported where models are loaded: the file is read without torch
    from deepprompt_ros.primitive.deep_promp import DeepProMP

__all__ = ["PrimitiveEntry", "read_primitives_file", "LoadedPrimitive", "load_primitive", "load_primitives"]

_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,63}$")


@dataclasses.dataclass(frozen=True)
class PrimitiveEntry:
    """One entry of the primitives file.

    Attributes
    ----------
    name : str
        Name clients use (letters, digits, '_'; starts with a letter).
    model : str
        Model file, absolute or relative to the models folder.
    description : str
    default_duration : float
        Execute duration when the goal sets none; 0 = the server's default_duration.
    """

    name: str
    model: str
    description: str = ""
    default_duration: float = 0.0


_ENTRY_KEYS = {f.name for f in dataclasses.fields(PrimitiveEntry)}


def read_primitives_file(path) -> tuple[list[PrimitiveEntry], list[str]]:
    """Parse the primitives YAML::

        primitives:
          - name: reach
            model: gen3_lite_reach.safetensors
            description: Reach an object (context 'object' = its position)
            default_duration: 5.0

    Returns
    -------
    entries : list of PrimitiveEntry
        The valid entries.
    errors : list of str
        One message per invalid entry (the entry is skipped).

    Raises
    ------
    ConfigError
        The file is missing, not YAML, or has no ``primitives`` list.
    """
    import yaml

    path = pathlib.Path(path)
    try:
        raw = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"primitives file '{path}' does not exist; set the parameter primitives_file") from None
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"primitives file '{path}' is not readable YAML: {exc}") from None
    if not isinstance(raw, dict) or not isinstance(raw.get("primitives"), list):
        raise ConfigError(f"primitives file '{path}' must be a mapping with a list 'primitives: [{{name, model, "
                          f"description, default_duration}}, ...]'; got {type(raw).__name__}")
    entries, errors, seen = [], [], set()
    for i, item in enumerate(raw["primitives"]):
        where = f"{path.name}: primitives[{i}]"
        if not isinstance(item, dict):
            errors.append(f"{where} must be a mapping with keys name, model; got {item!r}")
            continue
        unknown = sorted(set(item) - _ENTRY_KEYS)
        name = item.get("name")
        if unknown:
            errors.append(f"{where} ({name!r}) has unknown keys {unknown}; allowed: {sorted(_ENTRY_KEYS)}")
            continue
        if not isinstance(name, str) or not _NAME_RE.match(name):
            errors.append(f"{where}: name {name!r} is invalid; expected letters, digits and '_', starting "
                          "with a letter (at most 64 characters)")
            continue
        if name in seen:
            errors.append(f"{where}: primitive name '{name}' appears twice; names must be unique")
            continue
        model = item.get("model")
        if not isinstance(model, str) or not model:
            errors.append(f"{where} ('{name}'): model must be a file name or path; got {model!r}")
            continue
        desc = item.get("description", "")
        dur = item.get("default_duration", 0.0)
        if not isinstance(desc, str):
            errors.append(f"{where} ('{name}'): description must be a string")
            continue
        if isinstance(dur, bool) or not isinstance(dur, (int, float)) or not (math.isfinite(dur) and 0 <= dur <= 86400):
            errors.append(f"{where} ('{name}'): default_duration {dur!r} must be a number of seconds in "
                          "(0, 86400], or 0 for the server default")
            continue
        seen.add(name)
        entries.append(PrimitiveEntry(name, model, desc, float(dur)))
    return entries, errors


@dataclasses.dataclass(frozen=True)
class LoadedPrimitive:
    """A servable primitive.

    Attributes
    ----------
    entry : PrimitiveEntry
    model : DeepProMP
    path : pathlib.Path
    robot_index : array of int, shape (d,)
        Model joint j is robot joint ``robot_index[j]``.
    """

    entry: PrimitiveEntry
    model: DeepProMP
    path: pathlib.Path
    robot_index: np.ndarray

    @property
    def name(self) -> str:
        return self.entry.name

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.model.joint_names

    def to_robot_order(self, y: np.ndarray) -> np.ndarray:
        """Positions (..., d) in model joint order -> robot joint order."""
        out = np.empty_like(y)
        out[..., self.robot_index] = y
        return out


def load_primitive(entry: PrimitiveEntry, robot_joint_names: Sequence[str],
                   resolve: Callable[[str], pathlib.Path]) -> LoadedPrimitive:
    """Load one model and check it against the robot; ValueError/FileNotFoundError say why not."""
    from deepprompt_ros.primitive.deep_promp import DeepProMP

    path = resolve(entry.model)
    model = DeepProMP.from_checkpoint(str(path), name=entry.name)
    robot = tuple(robot_joint_names)
    if set(model.joint_names) != set(robot) or len(model.joint_names) != len(robot):
        missing = [j for j in robot if j not in model.joint_names]
        extra = [j for j in model.joint_names if j not in robot]
        raise ValueError(
            f"primitive '{entry.name}' ({path.name}) has {len(model.joint_names)} joints "
            f"[{', '.join(model.joint_names)}] but the robot has {len(robot)} joints [{', '.join(robot)}]"
            + (f"; missing: {', '.join(missing)}" if missing else "")
            + (f"; not on the robot: {', '.join(extra)}" if extra else "")
            + "; a primitive must drive exactly the robot's joints")
    index = np.array([robot.index(j) for j in model.joint_names], dtype=int)
    return LoadedPrimitive(entry, model, path, index)


def load_primitives(entries: Sequence[PrimitiveEntry], robot_joint_names: Sequence[str],
                    resolve: Callable[[str], pathlib.Path]) -> tuple[dict[str, LoadedPrimitive], list[str]]:
    """Load every entry that is valid; (primitives by name, one error message per refused entry)."""
    out, errors = {}, []
    for e in entries:
        try:
            out[e.name] = load_primitive(e, robot_joint_names, resolve)
        except (ValueError, FileNotFoundError, OSError) as exc:
            errors.append(f"primitive '{e.name}' refused: {exc}")
    return out, errors
