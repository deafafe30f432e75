"""Typed, strict YAML configuration: the building blocks every config section uses.

Numbers in YAML are either plain (in the field's canonical unit, named in the
field's description) or strings with a unit, e.g. ``gamma_bar: 21.05 deg`` or
``delay: 100 ms``. A unit of the wrong kind, an unknown key, a wrong type or an
out-of-range value is refused with one line naming the file, the key and the value.

Hostile files are refused before they can cost time or memory: only regular files up to
``MAX_CONFIG_BYTES``, UTF-8 text without NUL bytes, no YAML aliases (an alias "bomb" expands a
few hundred bytes into gigabytes), no duplicate keys (YAML would silently keep the last), at most
``MAX_DEPTH`` levels of nesting. Numbers are strict: finite, and never a boolean (YAML 1.1 reads
``yes``/``on``/``true`` as booleans, which pydantic would otherwise turn into 1.0).
"""

from __future__ import annotations

import math
import os
import re
import stat
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any

import yaml
from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, ValidationError, field_validator

MAX_CONFIG_BYTES = 1 << 20  # a config file is a few KB; anything this large is not one
MAX_DEPTH = 12  # nesting levels (the deepest section is 3 levels)
MAX_SET_CHARS = 4096  # one --set value

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
_NUMBER_RE = re.compile(r"^\s*[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?\s*$")


def printable(text: str) -> str:
    """Control characters (ANSI escapes, newlines, NUL, DEL, C1) as visible escapes: a value echoed back from
    a command line or a file can neither drive the terminal nor break the one-line error into several."""
    return "".join(ch if ch.isprintable() or ch == " " else ascii(ch)[1:-1] for ch in text)


class ConfigError(ValueError):
    """A configuration problem, already formatted as one line: file, key, value, what is wrong (any control
    character in it escaped)."""

    def __init__(self, message: object = "") -> None:
        super().__init__(printable(str(message)))


def _quantity(kind: str):
    table = _UNITS[kind]

    def parse(value: Any) -> Any:
        if isinstance(value, bool):
            raise ValueError(f"expected a number ({kind}), got a boolean")
        if isinstance(value, int | float):
            return _finite(float(value))
        if isinstance(value, str):
            m = _QUANTITY_RE.match(value)
            if not m:
                raise ValueError(f"expected a number with an optional {kind} unit ({', '.join(table)})")
            number, unit = float(m.group(1)), m.group(2)
            if unit is None:
                return _finite(number)
            factor = table.get(unit.lower()) if kind == "frequency" else table.get(unit)
            if factor is None:
                raise ValueError(f"unit '{unit}' is not a unit of {kind} (use one of: {', '.join(table)})")
            return _finite(number * factor)
        return _finite(value)  # (a wrong type: pydantic reports it)

    return BeforeValidator(parse)


def _finite(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError("must be finite")
    return value


def _plain_number(value: Any) -> Any:
    """A number, or a string that spells one; never a boolean, never 'nan'/'inf' spelled out."""
    if isinstance(value, bool):
        raise ValueError("expected a number, got a boolean")
    if isinstance(value, str):
        if not _NUMBER_RE.match(value):
            raise ValueError("expected a number")
        return _finite(float(value))
    return _finite(value)


# After the float conversion, whatever the input spelled ('1e999', a unit string, .inf): finite or refused.
_FINITE = AfterValidator(_finite)

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
Number = Annotated[float, _FINITE, BeforeValidator(_plain_number)]


def _is_bool_field(annotation: Any) -> bool:
    return annotation is bool or bool in typing.get_args(annotation)


class Section(BaseModel):
    """Base of every config section: unknown keys refused, values immutable, types strict."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=False, validate_default=True)

    @field_validator("*", mode="before")
    @classmethod
    def _no_boolean_for_non_booleans(cls, value: Any, info: Any) -> Any:
        # pydantic's lax mode reads True as 1 / 1.0: `k_pn: yes` must be refused, not fly with k_PN = 1.
        if isinstance(value, bool) and not _is_bool_field(cls.model_fields[info.field_name].annotation):
            raise ValueError("expected a value of this key's type, got a boolean")
        return value


def short_repr(value: Any, limit: int = 60) -> str:
    """A value for an error line: never the whole of a large list or mapping, never longer than ``limit``."""
    if isinstance(value, Mapping):
        return f"a mapping of {len(value)} key(s)"
    if isinstance(value, list | tuple) and len(value) > 8:
        return f"a list of {len(value)} items"
    if isinstance(value, str | bytes) and len(value) > limit:
        value = value[:limit]
    text = repr(value) if not isinstance(value, list | tuple) else "[" + ", ".join(
        short_repr(v, 12) for v in value) + "]"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def format_validation_error(err: ValidationError, source: str, data: Any = None) -> str:
    """The first problem of a pydantic ValidationError as one line: source: key: what (got value)."""
    first = err.errors(include_url=False)[0]
    key = ".".join(str(p) for p in first["loc"]) or "<top level>"
    msg = first["msg"]
    if first["type"] == "extra_forbidden":
        msg = "unknown key"
    elif first["type"] == "missing":
        return f"{source}: {key}: required key is missing"
    if first["type"] == "value_error":
        msg = msg.removeprefix("Value error, ")
    msg = " ".join(str(msg).split())
    if not first["loc"]:  # a cross-section check: its message names the keys; the input is the whole config
        return f"{source}: {msg}"
    value = first.get("input")
    if isinstance(value, Mapping):  # a section's own check: its message names the keys
        return f"{source}: {key}: {msg}"
    return f"{source}: {key}: {msg} (got {short_repr(value)})"


def deep_merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """Recursive dict merge: values of ``over`` win; nested mappings merge key by key."""
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = v
    return out


class _RefusedYAML(yaml.MarkedYAMLError):
    """YAML that parses but is refused in a config (alias, duplicate key, deep nesting)."""


class _StrictLoader(yaml.SafeLoader):
    """PyYAML's SafeLoader without aliases, duplicate keys or deep nesting."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            ev = self.peek_event()
            raise _RefusedYAML(problem=f"YAML aliases (*{ev.anchor}) are not allowed in a config",
                               problem_mark=ev.start_mark)
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                raise _RefusedYAML(problem=f"nested deeper than {MAX_DEPTH} levels",
                                   problem_mark=self.peek_event().start_mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        seen: set[tuple[str, str]] = set()
        for key_node, _ in node.value:
            if isinstance(key_node, yaml.ScalarNode):
                k = (key_node.tag, key_node.value)
                if k in seen:
                    raise _RefusedYAML(problem=f"duplicate key {short_repr(key_node.value)}",
                                       problem_mark=key_node.start_mark)
                seen.add(k)
        return super().construct_mapping(node, deep=deep)


def _yaml_problem(e: yaml.YAMLError) -> str:
    """One line for a YAML error (PyYAML's own text spans several lines)."""
    if isinstance(e, yaml.reader.ReaderError):
        return f"not valid YAML text: {' '.join(str(e.reason).split())} (character {e.character!r})"
    mark = getattr(e, "problem_mark", None)
    where = f"line {mark.line + 1}" if mark is not None else "?"
    problem = " ".join(str(getattr(e, "problem", None) or e).split())
    if isinstance(e, _RefusedYAML):
        return f"{where}: {problem}"
    return f"not valid YAML at {where}: {problem}"


def load_yaml_text(text: str) -> Any:
    """Parse YAML with the config's rules (no aliases, no duplicate keys, bounded nesting)."""
    return yaml.load(text, Loader=_StrictLoader)


def read_text_file(path: Path, what: str = "config file", limit: int = MAX_CONFIG_BYTES) -> str:
    """A regular UTF-8 text file of at most ``limit`` bytes; anything else is a one-line ConfigError.

    Checked before reading: ``/dev/zero``, a FIFO or a folder would otherwise hang or fill memory.
    """
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            raise ConfigError(f"{path}: not a regular file, cannot be a {what}")
        if st.st_size > limit:
            raise ConfigError(f"{path}: {st.st_size} bytes, too large for a {what} (limit {limit})")
        with open(path, "rb") as f:
            raw = f.read(limit + 1)
    except OSError as e:
        raise ConfigError(f"{path}: cannot read {what} ({e.strerror or e})") from None
    if len(raw) > limit:
        raise ConfigError(f"{path}: too large for a {what} (limit {limit} bytes)")
    if b"\0" in raw:
        raise ConfigError(f"{path}: binary file (NUL bytes), not a {what}")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not UTF-8 text (byte 0x{raw[e.start]:02x} at offset {e.start})") from None


def read_yaml(path: Path) -> dict[str, Any]:
    """Read a YAML mapping; any problem is a ConfigError naming the file."""
    text = read_text_file(path)
    try:
        data = load_yaml_text(text)
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: {_yaml_problem(e)}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a mapping of sections, got {type(data).__name__}")
    check_finite(data, str(path))
    return data


def check_finite(data: Any, source: str, key: str = "") -> None:
    """Every float anywhere in the data is finite (a safety net under the typed fields)."""
    if isinstance(data, float) and not math.isfinite(data):
        raise ConfigError(f"{source}: {key or '<top level>'}: must be finite (got {data})")
    if isinstance(data, Mapping):
        for k, v in data.items():
            check_finite(v, source, f"{key}.{k}" if key else str(k))
    elif isinstance(data, list):
        for i, v in enumerate(data):
            check_finite(v, source, f"{key}.{i}")


def parse_override(text: str) -> dict[str, Any]:
    """``section.key=value`` (value parsed as YAML) -> nested dict, for --set on the command line."""
    if len(text) > MAX_SET_CHARS:
        raise ConfigError(f"--set {text[:40]}...: {len(text)} characters, too long (limit {MAX_SET_CHARS})")
    if "=" not in text:
        raise ConfigError(f"--set {text!r}: expected section.key=value")
    key, raw = text.split("=", 1)
    parts = [p for p in key.strip().split(".") if p]
    if not parts:
        raise ConfigError(f"--set {text!r}: empty key")
    if len(parts) > MAX_DEPTH:
        raise ConfigError(f"--set {text[:60]}: key nested deeper than {MAX_DEPTH} levels")
    try:
        value = load_yaml_text(raw)
    except _RefusedYAML as e:
        raise ConfigError(f"--set {text[:60]}: {_yaml_problem(e)}") from None
    except yaml.YAMLError:
        value = raw
    check_finite(value, f"--set {text}", ".".join(parts))
    out: dict[str, Any] = {parts[-1]: value}
    for p in reversed(parts[:-1]):
        out = {p: out}
    return out
