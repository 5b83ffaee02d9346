"""Node parameters declared once: name, type, default, description, range (one table per node,
from which the YAML files and README tables are checked). Shared by sim_bridge and demo_recorder."""
from __future__ import annotations

import math
from typing import Any, Mapping, NamedTuple, Sequence

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node

__all__ = ["ParamSpec", "ConfigError", "declare", "declare_all"]


class ParamSpec(NamedTuple):
    """One parameter: name, kind ('str' 'float' 'int' 'bool' 'float[]' 'str[]'), default,
    description, optional inclusive range and allowed values."""

    name: str
    kind: str
    default: Any
    description: str
    lo: float | None = None
    hi: float | None = None


class ConfigError(ValueError):
    """A parameter has an invalid value; the node logs it and exits with code 2."""


def declare(node: Node, spec: ParamSpec, name: str | None = None, choices: Sequence[Any] | None = None):
    """Declare one parameter (read-only, documented) and return its checked value.

    ``name`` overrides ``spec.name`` (e.g. per-object parameters); ``choices`` are the allowed
    values. Raises :class:`ConfigError` saying what was wrong and what is expected.
    """
    name = name or spec.name
    desc = ParameterDescriptor(description=spec.description, read_only=True, dynamic_typing=True)
    if spec.lo is not None and spec.kind == "float":
        desc.floating_point_range = [FloatingPointRange(from_value=float(spec.lo), to_value=float(spec.hi))]
    elif spec.lo is not None and spec.kind == "int":
        desc.integer_range = [IntegerRange(from_value=int(spec.lo), to_value=int(spec.hi), step=1)]
    default = None if isinstance(spec.default, list) and not spec.default else spec.default
    try:
        value = node.declare_parameter(name, default, desc).value
    except Exception as exc:  # rclpy raises several types for bad overrides
        raise ConfigError(f"parameter '{name}': {exc}") from None
    expected = {"str": "a string", "float": "a number", "int": "an integer", "bool": "true or false",
                "float[]": "a list of numbers", "str[]": "a list of strings"}[spec.kind]
    bad = ConfigError(f"parameter '{name}' = {value!r} is not {expected} ({spec.description})")
    if spec.kind.endswith("[]"):
        value = [] if value is None else value
        if not isinstance(value, (list, tuple)):
            raise bad
        if spec.kind == "float[]":
            if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
                raise bad
            value = [float(v) for v in value]
            if not all(math.isfinite(v) for v in value):
                raise ConfigError(f"parameter '{name}' = {value} must be finite numbers")
        elif not all(isinstance(v, str) for v in value):
            raise bad
        return list(value)
    if spec.kind == "float":
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
            raise bad
        value = float(value)
    elif spec.kind == "int":
        if not isinstance(value, int) or isinstance(value, bool):
            raise bad
    elif spec.kind == "bool" and not isinstance(value, bool):
        raise bad
    elif spec.kind == "str" and not isinstance(value, str):
        raise bad
    if spec.lo is not None and not (spec.lo <= value <= spec.hi):
        raise ConfigError(f"parameter '{name}' = {value} is outside [{spec.lo}, {spec.hi}] "
                          f"({spec.description})")
    if choices is not None and value not in choices:
        raise ConfigError(f"parameter '{name}' = {value!r}; expected one of {tuple(choices)}")
    return value


def declare_all(node: Node, specs: Sequence[ParamSpec],
                choices: Mapping[str, Sequence[Any]] | None = None) -> tuple[dict, list[str]]:
    """Declare every parameter of ``specs`` (``choices``: allowed values by parameter name); returns
    (name -> value of the valid ones, the error message of each bad one), so that a node reports
    every bad value at once."""
    values, errors = {}, []
    for spec in specs:
        try:
            values[spec.name] = declare(node, spec, choices=(choices or {}).get(spec.name))
        except ConfigError as exc:
            errors.append(str(exc))
    return values, errors
