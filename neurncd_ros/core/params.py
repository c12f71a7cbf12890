"""Typed, documented parameters shared by every configurable part.

Each core component declares its settings as a frozen dataclass whose fields
are made with :func:`param`. The configuration schema (``neurncd_ros.config``) is
assembled from these dataclasses, so a parameter's type, default, range and
one-line doc live next to the code that uses it and nowhere else.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from typing import Any, Callable, Sequence

_META = "neurncd"


class ConfigError(ValueError):
    """A configuration value is unknown, of the wrong type or out of range."""


def param(default: Any, doc: str, *, lo: float | None = None, hi: float | None = None,
          choices: Sequence[Any] | Callable[[], Sequence[Any]] | None = None,
          unit: str = "") -> Any:
    """Declare one parameter: default, one-line doc, and the allowed values.

    ``lo``/``hi`` are inclusive bounds for numbers (and for every element of a
    numeric list); ``choices`` lists the allowed values of a string, or is a
    function returning them when they are registered at run time (backends).
    """
    if choices is not None and not callable(choices):
        choices = tuple(choices)
    meta = {"doc": doc, "lo": lo, "hi": hi, "choices": choices, "unit": unit}
    if isinstance(default, list):
        return dataclasses.field(default_factory=lambda d=tuple(default): list(d),
                                 metadata={_META: meta})
    return dataclasses.field(default=default, metadata={_META: meta})


@dataclasses.dataclass(frozen=True)
class ParamSpec:
    """Everything the schema knows of one parameter."""

    name: str
    type: type
    elem_type: type | None
    default: Any
    doc: str
    lo: float | None
    hi: float | None
    choices: tuple | None
    unit: str

    def allowed(self) -> str:
        """Human-readable description of the allowed values."""
        if self.choices is not None:
            return "one of " + ", ".join(repr(c) for c in self.choices)
        tname = self.type.__name__ if self.elem_type is None else \
            f"list of {self.elem_type.__name__}"
        if self.lo is not None and self.hi is not None:
            return f"{tname} in [{self.lo}, {self.hi}]"
        if self.lo is not None:
            return f"{tname} >= {self.lo}"
        if self.hi is not None:
            return f"{tname} <= {self.hi}"
        return tname


def specs(cls: type) -> list[ParamSpec]:
    """The parameters of a dataclass declared with :func:`param`, in order."""
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        meta = f.metadata.get(_META)
        if meta is None:
            continue
        hint = hints[f.name]
        origin = typing.get_origin(hint)
        if origin in (list, Sequence):
            (elem,) = typing.get_args(hint)
            ftype, elem_type = list, elem
        else:
            ftype, elem_type = hint, None
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        choices = meta["choices"]
        if callable(choices):
            choices = tuple(choices())
        out.append(ParamSpec(f.name, ftype, elem_type, default, meta["doc"], meta["lo"],
                             meta["hi"], choices, meta["unit"]))
    return out


def _coerce_scalar(value: Any, want: type, key: str, spec: ParamSpec) -> Any:
    if want is bool:
        if isinstance(value, bool):
            return value
    elif want is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif want is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            v = float(value)
            if not math.isfinite(v):
                raise ConfigError(f"{key}: {value!r} is not finite; allowed: {spec.allowed()}")
            return v
    elif want is str:
        if isinstance(value, str):
            return value
    raise ConfigError(f"{key}: {value!r} has type {type(value).__name__}; "
                      f"allowed: {spec.allowed()}")


def check_value(spec: ParamSpec, value: Any, key: str) -> Any:
    """Return ``value`` converted to the parameter's type, or raise ConfigError."""
    if spec.type is list:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}: {value!r} is not a list; allowed: {spec.allowed()}")
        vals = [_coerce_scalar(v, spec.elem_type, key, spec) for v in value]
    else:
        vals = [_coerce_scalar(value, spec.type, key, spec)]
    for v in vals:
        if spec.choices is not None and v not in spec.choices:
            raise ConfigError(f"{key}: {v!r} is not allowed; allowed: {spec.allowed()}")
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            if (spec.lo is not None and v < spec.lo) or (spec.hi is not None and v > spec.hi):
                raise ConfigError(f"{key}: {v!r} is out of range; allowed: {spec.allowed()}")
    return list(vals) if spec.type is list else vals[0]


def build(cls: type, values: dict[str, Any] | None = None, prefix: str = "") -> Any:
    """Make ``cls`` from a dict, rejecting unknown keys and bad values by name."""
    values = dict(values or {})
    kwargs = {}
    by_name = {s.name: s for s in specs(cls)}
    for name in values:
        if name not in by_name:
            raise ConfigError(f"{prefix}{name}: unknown parameter; known: "
                              + ", ".join(sorted(by_name)))
    for name, spec in by_name.items():
        if name in values:
            kwargs[name] = check_value(spec, values[name], prefix + name)
    return cls(**kwargs)


def to_dict(obj: Any) -> dict[str, Any]:
    """The parameter values of a config dataclass as a plain dict."""
    return {s.name: getattr(obj, s.name) for s in specs(type(obj))}
