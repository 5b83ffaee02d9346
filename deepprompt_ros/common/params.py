"""Parameters declared once (in the spirit of generate_parameter_library): name, type, default,
description, range (inclusive, or exclusive at the lower end) or allowed choices, unit.

Every configurable thing of the package is a frozen dataclass whose fields are made with
:func:`param`: the server's and the nodes' ROS parameters, and the training configuration. From the
same declaration come the validation (:func:`check`, :func:`from_mapping`), the ROS parameter
descriptors (``deepprompt_ros.ros.parameters``) and the documentation (:func:`markdown_table`,
``docs/parameters.md``). A parameter several configurations share is declared in one of them and
taken over by the others with :func:`param_from`.
"""
from __future__ import annotations

import dataclasses
import math
import numbers
from typing import Any, Callable, Iterable, Mapping, NamedTuple, Sequence, TypeVar

__all__ = ["ConfigError", "ParamSpec", "param", "param_from", "specs_of", "check", "coerce", "validate",
           "from_mapping", "markdown_table"]

TYPES = ("bool", "int", "double", "string", "double[]", "string[]")
_PY_TYPES = {"bool": "bool", "int": "int", "float": "double", "str": "string",
             "tuple[float, ...]": "double[]", "tuple[str, ...]": "string[]"}
_EXPECTED = {"bool": "true or false", "int": "an integer", "double": "a number", "string": "a string",
             "double[]": "a list of numbers", "string[]": "a list of strings"}


class ConfigError(ValueError):
    """Invalid parameters; the message names every bad one and what is expected."""


class ParamSpec(NamedTuple):
    """One parameter. ``type`` is one of ``bool int double string double[] string[]``; ``min`` /
    ``max`` bound numbers (and every element of a list) inclusively, ``None`` = unbounded, except
    that ``min_open`` makes the lower bound exclusive (value > min); ``choices`` are the allowed
    values of a string. ``default`` is ``None`` for a parameter without a default (a required
    field)."""

    name: str
    type: str
    default: Any
    description: str
    min: float | None = None
    max: float | None = None
    choices: tuple[str, ...] | None = None
    unit: str = ""
    min_open: bool = False


def param(default, description: str, *, min=None, max=None, gt=None, choices=None, unit: str = "",
          type: str = "", name: str = ""):
    """A dataclass field that is a parameter (see :func:`specs_of`). ``min`` / ``max`` are inclusive
    bounds, ``gt`` an exclusive lower bound (value > gt; instead of ``min``). ``default`` may be
    ``dataclasses.MISSING`` for a required field. ``type`` is needed only when the field's
    annotation does not say it (e.g. ``Any``); ``name`` only when the parameter's name is not the
    field's (ROS parameter names may hold dots: field ``camera_width``, parameter ``camera.width``)."""
    if gt is not None and min is not None:
        raise TypeError("param: give min (inclusive) or gt (exclusive), not both")
    meta = {"description": description, "min": min if gt is None else gt, "max": max, "min_open": gt is not None,
            "choices": None if choices is None else tuple(choices), "unit": unit, "type": type, "name": name}
    if default is dataclasses.MISSING:
        return dataclasses.field(metadata=meta)
    if isinstance(default, (list, tuple)):
        return dataclasses.field(default_factory=lambda d=tuple(default): d, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def param_from(cls, field: str):
    """A new dataclass field declared as the parameter ``field`` of the dataclass ``cls`` (same
    default, description, range or choices and unit): a parameter several configurations share
    is declared once."""
    f = next((f for f in dataclasses.fields(cls) if f.name == field and "description" in f.metadata), None)
    if f is None:
        raise TypeError(f"{cls.__name__}.{field} is not a parameter field")
    if f.default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=f.default_factory, metadata=f.metadata)
    if f.default is not dataclasses.MISSING:
        return dataclasses.field(default=f.default, metadata=f.metadata)
    return dataclasses.field(metadata=f.metadata)


T = TypeVar("T")


def specs_of(cls) -> tuple[ParamSpec, ...]:
    """The :class:`ParamSpec` of every field of the dataclass ``cls`` made with :func:`param`."""
    return tuple(spec for _, spec in _param_fields(cls))


def _param_fields(cls) -> list[tuple[str, ParamSpec]]:
    """(field name, :class:`ParamSpec`) of every parameter field of the dataclass ``cls``."""
    specs = []
    for f in dataclasses.fields(cls):
        if "description" not in f.metadata:
            continue
        m = f.metadata
        kind = m["type"] or _PY_TYPES.get(f.type if isinstance(f.type, str) else f.type.__name__)
        if kind not in TYPES:
            raise TypeError(f"{cls.__name__}.{f.name}: parameter type {f.type!r} is not one of {TYPES}")
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            default = None  # a required field
        specs.append((f.name, ParamSpec(m.get("name") or f.name, kind, default, m["description"], m["min"],
                                        m["max"], m["choices"], m["unit"], m.get("min_open", False))))
    return specs


def _interval(spec: ParamSpec) -> str:
    """The range of ``spec`` as text: ``[lo, hi]``, or ``(lo, hi]`` / ``(lo, inf)`` when ``min_open``."""
    lo = "-inf" if spec.min is None else f"{spec.min:g}"
    hi = "inf" if spec.max is None else f"{spec.max:g}"
    if not spec.min_open:
        return f"[{lo}, {hi}]"
    return f"({lo}, {hi}" + ("]" if spec.max is not None else ")")


def _is_number(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and type(v).__name__ != "bool_"


def check(spec: ParamSpec, value) -> str:
    """``''`` when ``value`` is valid for ``spec``, else a message saying what is expected."""
    unit = f" {spec.unit}" if spec.unit else ""
    bad = f"{spec.name} = {value!r}: expected {_EXPECTED[spec.type]}"
    if spec.type == "bool":
        ok = isinstance(value, bool) or type(value).__name__ == "bool_"
    elif spec.type == "int":
        ok = isinstance(value, numbers.Integral) and _is_number(value)
    elif spec.type == "double":
        ok = _is_number(value)
    elif spec.type == "string":
        ok = isinstance(value, str)
    else:
        elem = _is_number if spec.type == "double[]" else (lambda v: isinstance(v, str))
        ok = isinstance(value, (list, tuple)) and all(elem(v) for v in value)
    if not ok:
        return bad
    numbers_ = [value] if spec.type in ("int", "double") else list(value) if spec.type == "double[]" else []
    for v in numbers_:
        if not math.isfinite(float(v)):
            return f"{spec.name} = {value!r}: expected finite numbers"
        lo = -math.inf if spec.min is None else spec.min
        hi = math.inf if spec.max is None else spec.max
        if not (lo < float(v) if spec.min_open else lo <= float(v)) or not float(v) <= hi:
            return f"{spec.name} = {value!r}{unit}: expected a value in {_interval(spec)}{unit}"
    if spec.choices is not None and value not in spec.choices:
        return f"{spec.name} = {value!r}: expected one of {', '.join(repr(c) for c in spec.choices)}"
    return ""


def coerce(spec: ParamSpec, value):
    """``value`` (already :func:`check` ed) in the field's Python type."""
    if spec.type == "double":
        return float(value)
    if spec.type == "int":
        return int(value)
    if spec.type == "bool":
        return bool(value)
    if spec.type == "double[]":
        return tuple(float(v) for v in value)
    if spec.type == "string[]":
        return tuple(value)
    return value


def validate(obj, rules: Callable[[Any], Iterable[str]] | None = None) -> None:
    """Check every parameter field of the dataclass instance ``obj`` (call from ``__post_init__``);
    raises :class:`ConfigError` naming every invalid one.

    ``rules(obj)``, called once every field is valid, gives a message per rule that a field's range
    or choices cannot state (between fields, or a gap in a range), ``''`` for each rule that holds;
    the broken ones are reported the same way."""
    errors = [e for field, s in _param_fields(type(obj)) if (e := check(s, getattr(obj, field)))]
    if not errors and rules is not None:
        errors = [e for e in rules(obj) if e]
    if errors:
        raise ConfigError(f"invalid {type(obj).__name__} parameters:\n  " + "\n  ".join(errors))


def from_mapping(cls: type[T], values: Mapping[str, Any]) -> T:
    """An instance of the dataclass ``cls`` from {name: value}; unknown names and invalid values are
    all reported at once in one :class:`ConfigError`."""
    fields = {s.name: (field, s) for field, s in _param_fields(cls)}
    errors = [f"unknown parameter '{n}'; known: {', '.join(sorted(fields))}"
              for n in sorted(set(values) - set(fields))]
    ok = {}
    for name, value in values.items():
        if name in fields:
            field, spec = fields[name]
            err = check(spec, value)
            if err:
                errors.append(err)
            else:
                ok[field] = coerce(spec, value)
    if errors:
        raise ConfigError(f"invalid {cls.__name__} parameters:\n  " + "\n  ".join(errors))
    return cls(**ok)


def markdown_table(specs: Sequence[ParamSpec]) -> str:
    """Markdown table of ``specs`` (name, type, default, range or choices, description)."""
    rows = ["| parameter | type | default | range | description |", "|---|---|---|---|---|"]
    for p in specs:
        if p.choices:
            rng = " / ".join(f"`{c}`" for c in p.choices)
        elif p.min is not None or p.max is not None:
            rng = _interval(p) + (f" {p.unit}" if p.unit else "")
        else:
            rng = p.unit
        default = list(p.default) if isinstance(p.default, tuple) else p.default
        description = p.description.replace("|", "\\|")  # a '|' of the text would end the cell
        rows.append(f"| `{p.name}` | {p.type} | `{default!r}` | {rng} | {description} |")
    return "\n".join(rows)
