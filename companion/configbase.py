"""Typed, strict YAML configuration: the building blocks every config section uses.

Numbers in YAML are either plain (in the field's canonical unit, named in the
field's description) or strings with a unit, e.g. ``gamma_bar: 21.05 deg`` or
``delay: 100 ms``. A unit of the wrong kind, an unknown key, a wrong type or an
out-of-range value is refused with one line naming the file, the key and the value.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any

import yaml
from pydantic import BaseModel, BeforeValidator, ConfigDict, ValidationError

# Unit tables: factor to the canonical unit of each kind.
_UNITS: dict[str, dict[str, float]] = {
    "angle": {"deg": 1.0, "rad": 180.0 / math.pi},  # canonical: deg
    "time": {"s": 1.0, "ms": 1e-3, "min": 60.0},  # canonical: s
    "speed": {"m/s": 1.0, "km/h": 1.0 / 3.6},  # canonical: m/s
    "length": {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "km": 1e3},  # canonical: m
    "frequency": {"hz": 1.0, "khz": 1e3},  # canonical: Hz
    "mass": {"kg": 1.0, "g": 1e-3},  # canonical: kg
    "acceleration": {"m/s^2": 1.0, "m/s2": 1.0, "g0": 9.80665},  # canonical: m/s^2
    "rate": {"deg/s": 1.0, "rad/s": 180.0 / math.pi},  # canonical: deg/s
    "pixel": {"px": 1.0},
}
_QUANTITY_RE = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([A-Za-z/^0-9]+)?\s*$")


class ConfigError(ValueError):
    """A configuration problem, already formatted as one line: file, key, value, what is wrong."""


def _quantity(kind: str):
    table = _UNITS[kind]

    def parse(value: Any) -> Any:
        if isinstance(value, bool):
            raise ValueError(f"expected a number ({kind}), got a boolean")
        if isinstance(value, int | float):
            return float(value)
        if isinstance(value, str):
            m = _QUANTITY_RE.match(value)
            if not m:
                raise ValueError(f"expected a number with an optional {kind} unit ({', '.join(table)})")
            number, unit = float(m.group(1)), m.group(2)
            if unit is None:
                return number
            factor = table.get(unit.lower()) if kind == "frequency" else table.get(unit)
            if factor is None:
                raise ValueError(f"unit '{unit}' is not a unit of {kind} (use one of: {', '.join(table)})")
            return number * factor
        return value  # let pydantic report the wrong type

    return BeforeValidator(parse)


def _finite(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError("must be finite")
    return value


_FINITE = BeforeValidator(_finite)

# Canonical-unit float types. Use with pydantic.Field(ge=..., le=...) for ranges.
Deg = Annotated[float, _FINITE, _quantity("angle")]
Seconds = Annotated[float, _FINITE, _quantity("time")]
MetersPerSecond = Annotated[float, _FINITE, _quantity("speed")]
Meters = Annotated[float, _FINITE, _quantity("length")]
Hertz = Annotated[float, _FINITE, _quantity("frequency")]
Kilograms = Annotated[float, _FINITE, _quantity("mass")]
MetersPerSecond2 = Annotated[float, _FINITE, _quantity("acceleration")]
DegPerSecond = Annotated[float, _FINITE, _quantity("rate")]
Pixels = Annotated[float, _FINITE, _quantity("pixel")]
Number = Annotated[float, _FINITE]


class Section(BaseModel):
    """Base of every config section: unknown keys refused, values immutable, types strict."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=False, validate_default=True)


def format_validation_error(err: ValidationError, source: str, data: Any = None) -> str:
    """The first problem of a pydantic ValidationError as one line: source: key: what (got value)."""
    first = err.errors(include_url=False)[0]
    key = ".".join(str(p) for p in first["loc"]) or "<top level>"
    msg = first["msg"]
    if first["type"] == "extra_forbidden":
        msg = "unknown key"
    elif first["type"] == "missing":
        return f"{source}: {key}: required key is missing"
    value = first.get("input")
    return f"{source}: {key}: {msg} (got {value!r})"


def deep_merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """Recursive dict merge: values of ``over`` win; nested mappings merge key by key."""
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = v
    return out


def read_yaml(path: Path) -> dict[str, Any]:
    """Read a YAML mapping; any problem is a ConfigError naming the file."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise ConfigError(f"{path}: cannot read config file ({e.strerror or e})") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else "?"
        raise ConfigError(f"{path}: not valid YAML at {where}: {getattr(e, 'problem', e)}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a mapping of sections, got {type(data).__name__}")
    return data


def parse_override(text: str) -> dict[str, Any]:
    """``section.key=value`` (value parsed as YAML) -> nested dict, for --set on the command line."""
    if "=" not in text:
        raise ConfigError(f"--set {text!r}: expected section.key=value")
    key, raw = text.split("=", 1)
    parts = [p for p in key.strip().split(".") if p]
    if not parts:
        raise ConfigError(f"--set {text!r}: empty key")
    try:
        value = yaml.safe_load(raw)
    except yaml.YAMLError:
        value = raw
    out: dict[str, Any] = {parts[-1]: value}
    for p in reversed(parts[:-1]):
        out = {p: out}
    return out
