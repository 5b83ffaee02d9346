"""ROS parameters of a node, declared from a configuration dataclass.

Every node of the package (primitive_server, sim_bridge, demo_recorder) keeps its parameters in a
frozen dataclass made with :func:`deepprompt_ros.common.params.param` and declares them here, so
that each parameter is declared the same way everywhere:

* read-only (read once at start), with a descriptor that ``ros2 param describe`` shows: the
  description, the range of a scalar number (``integer_range`` / ``floating_point_range``) and, as
  additional constraints, the allowed choices, the range of each element of a list and the unit;
* dynamically typed, so that a value of the wrong type reaches the check below instead of an
  rclpy exception;
* checked with :func:`deepprompt_ros.common.params.check`: every invalid value is reported at once
  in one :class:`~deepprompt_ros.common.params.ConfigError` that says what is expected (the nodes
  log it and exit with code 2).
"""
from __future__ import annotations

from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node

from deepprompt_ros.common.params import ConfigError, ParamSpec, check, coerce, from_mapping, specs_of

__all__ = ["descriptor", "declare_values", "declare_config"]

_ARRAYS = ("double[]", "string[]")


def descriptor(spec: ParamSpec) -> ParameterDescriptor:
    """The read-only, dynamically typed descriptor of ``spec``."""
    desc = ParameterDescriptor(description=spec.description, read_only=True, dynamic_typing=True)
    bounded = spec.min is not None and spec.max is not None
    if bounded and spec.type == "double":
        desc.floating_point_range = [FloatingPointRange(from_value=float(spec.min), to_value=float(spec.max))]
    elif bounded and spec.type == "int":
        desc.integer_range = [IntegerRange(from_value=int(spec.min), to_value=int(spec.max), step=1)]
    constraints = []
    if spec.choices:
        constraints.append("one of: " + ", ".join(spec.choices))
    if spec.type == "double[]" and (spec.min is not None or spec.max is not None):
        lo = "-inf" if spec.min is None else f"{spec.min:g}"
        hi = "inf" if spec.max is None else f"{spec.max:g}"
        constraints.append(f"each element in [{lo}, {hi}]")
    if spec.unit:
        constraints.append(f"unit: {spec.unit}")
    desc.additional_constraints = "; ".join(constraints)
    return desc


def _declare_one(node: Node, spec: ParamSpec, name: str) -> Any:
    """Declare ``name`` with the descriptor of ``spec``; its value (not yet checked)."""
    # an empty list has no ROS type: declared unset, read back as an empty list
    default = None if spec.type in _ARRAYS and not spec.default else spec.default
    if isinstance(default, tuple):
        default = list(default)
    try:
        value = node.declare_parameter(name, default, descriptor(spec)).value
    except Exception:  # rclpy refuses an out-of-range override: read it without the range, the check
        plain = ParameterDescriptor(description=spec.description, read_only=True, dynamic_typing=True)
        value = node.declare_parameter(name, default, plain).value  # below says what is expected
    if value is None and spec.type in _ARRAYS:
        value = ()
    return value


def declare_values(node: Node, specs, prefix: str = "") -> tuple[dict[str, Any], list[str]]:
    """Declare the parameters ``prefix + spec.name`` of every spec of ``specs``.

    Returns
    -------
    values : dict
        ``spec.name`` (without the prefix) -> the value in the spec's Python type, for the valid ones.
    errors : list of str
        One message per invalid parameter, naming it as the user set it (with the prefix).
    """
    values, errors = {}, []
    for spec in specs:
        name = prefix + spec.name
        try:
            value = _declare_one(node, spec, name)
        except Exception as exc:  # e.g. an invalid name
            errors.append(f"{name}: {exc}")
            continue
        err = check(spec._replace(name=name), value)
        if err:
            errors.append(err)
        else:
            values[spec.name] = coerce(spec, value)
    return values, errors


def declare_config(node: Node, cls, prefix: str = ""):
    """Declare the parameters of the configuration dataclass ``cls`` (made with
    :func:`~deepprompt_ros.common.params.param`) on ``node`` and return an instance built from
    their values.

    Raises
    ------
    ConfigError
        Naming every invalid parameter and what is expected. The checks of ``cls.__post_init__``
        beyond type and range (e.g. of several parameters together) run with the valid values
        (defaults in place of the invalid ones), so that their message joins the others.
    """
    values, errors = declare_values(node, specs_of(cls), prefix)
    try:
        config = from_mapping(cls, values)
    except ConfigError as exc:
        errors.append(str(exc))
    if errors:
        raise ConfigError("invalid parameters:\n  " + "\n  ".join(errors))
    return config
