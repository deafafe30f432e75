"""Write docs/config-reference.md: every config key with its type, unit, default and description.

Generated from the schema itself (``companion.config.Config`` and the sections it holds), so the reference
cannot drift from the code; ``tests/test_config_reference.py`` fails when the committed file is stale.

* key: the dotted path ``section.key`` (``--set section.key=value``, or the nesting in a YAML file);
* type: what the YAML value must be;
* unit: the canonical unit the value is stored in, and the units a YAML string may carry
  (``companion/configbase.py``: ``Deg``, ``Seconds``, ...); "-" for a plain number;
* default: the value ``companion.config.load_config()`` gives with no overlay (config/default.yaml and the
  files it includes, else the schema's default), in the canonical unit;
* description: the schema's Field description, else the key's trailing comment in the YAML files under config/.

    .venv/bin/python tools/config_reference.py [--out docs/config-reference.md]
"""

from __future__ import annotations

import argparse
import re
import sys
import types
import typing
from pathlib import Path
from typing import Any, Literal

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pydantic import BaseModel  # noqa: E402
from pydantic.fields import FieldInfo  # noqa: E402

import companion.configbase as configbase  # noqa: E402
from companion.config import Config, default_config_dir, load_config  # noqa: E402

DEFAULT_OUT = REPO / "docs" / "config-reference.md"

# The unit-carrying float types of companion/configbase.py, by the kind name its unit table uses.
_UNIT_TYPES = {
    "Deg": "angle", "Seconds": "time", "MetersPerSecond": "speed", "Meters": "length", "Hertz": "frequency",
    "Kilograms": "mass", "MetersPerSecond2": "acceleration", "DegPerSecond": "rate", "Pixels": "pixel",
}
_SPELLED = {"hz": "Hz", "khz": "kHz"}  # the frequency table's keys are lower case (matched case-insensitively)


def _unit_markers() -> dict[int, str]:
    """id of each unit type's validator object -> its unit text ("deg (deg, rad)")."""
    # Validators shared between types (the finite check, also on the unit-less Number) mark no unit.
    shared = {id(m) for m in typing.get_args(configbase.Number)[1:]}
    out: dict[int, str] = {}
    for name, kind in _UNIT_TYPES.items():
        table = configbase._UNITS[kind]
        canonical = _SPELLED.get(c := next(u for u, f in table.items() if f == 1.0), c)
        others = [_SPELLED.get(u, u) for u in table if _SPELLED.get(u, u) != canonical]
        text = canonical + (f" (or {', '.join(others)})" if others else "")
        for meta in typing.get_args(getattr(configbase, name))[1:]:
            if id(meta) not in shared:
                out[id(meta)] = text
    return out


_MARKERS = _unit_markers()


def _unit(field: FieldInfo) -> str:
    """The unit of a field: from its metadata (a top-level Annotated) or an Annotated inside its type."""
    for meta in field.metadata:
        if id(meta) in _MARKERS:
            return _MARKERS[id(meta)]
    found = _unit_in(field.annotation)
    return found or "-"


def _unit_in(annotation: Any) -> str | None:
    if typing.get_origin(annotation) is typing.Annotated:
        for meta in typing.get_args(annotation)[1:]:
            if id(meta) in _MARKERS:
                return _MARKERS[id(meta)]
    for arg in typing.get_args(annotation):
        found = _unit_in(arg)
        if found:
            return found
    return None


def _type_name(annotation: Any) -> str:
    """A short, YAML-oriented name of a field's type."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is typing.Annotated:
        return _type_name(args[0])
    if origin is Literal:
        return "one of: " + ", ".join(str(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        text = " or ".join(_type_name(a) for a in inner)
        return text + " or empty" if len(inner) < len(args) else text
    if origin in (list, tuple):
        return f"list of {_type_name(args[0])}" if args else "list"
    if origin is dict:
        return f"mapping {_type_name(args[0])} -> {_type_name(args[1])}" if args else "mapping"
    return getattr(annotation, "__name__", str(annotation))


def _fmt(value: Any) -> str:
    if value is None:
        return "empty"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, str):
        return f'"{value}"' if value else '""'
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {_fmt(v)}" for k, v in value.items()) + "}"
    return str(value)


_KEY_LINE = re.compile(r"^(\s*)([A-Za-z_][A-Za-z0-9_]*):(.*)$")


def yaml_comments(config_dir: Path) -> dict[str, str]:
    """Trailing comments of keys in the YAML files under config/, by dotted path (default.yaml's files first)."""
    files = sorted(config_dir.glob("*.yaml")) + sorted(config_dir.glob("*/*.yaml"))
    out: dict[str, str] = {}
    for path in files:
        stack: list[tuple[int, str]] = []  # (indent, key) of the open mappings
        for line in path.read_text(encoding="utf-8").splitlines():
            m = _KEY_LINE.match(line)
            if not m:
                continue
            indent, key, rest = len(m.group(1)), m.group(2), m.group(3)
            while stack and stack[-1][0] >= indent:
                stack.pop()
            dotted = ".".join([k for _, k in stack] + [key])
            value, hash_, comment = rest.partition(" #")
            if hash_ and comment.strip() and dotted not in out and '"' not in value and "'" not in value:
                out[dotted] = comment.strip()
            if not value.strip():
                stack.append((indent, key))
    return out


def rows(model: type[BaseModel], loaded: BaseModel, prefix: str, comments: dict[str, str]) -> list[list[str]]:
    """One row per leaf key of ``model`` (nested sections walked), with the loaded value as the default."""
    out: list[list[str]] = []
    for name, field in model.model_fields.items():
        dotted = f"{prefix}.{name}" if prefix else name
        value = getattr(loaded, name)
        sub = field.annotation
        if isinstance(sub, type) and issubclass(sub, BaseModel):
            out.extend(rows(sub, value, dotted, comments))
            continue
        description = " ".join((field.description or comments.get(dotted, "")).split())
        out.append([f"`{dotted}`", _type_name(field.annotation), _unit(field), f"`{_fmt(value)}`", description])
    return out


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def render() -> str:
    cfg = load_config()
    comments = yaml_comments(default_config_dir())
    lines = [
        "# Configuration reference",
        "",
        "Generated by `tools/config_reference.py` from the schema (`companion/config.py` and the sections it",
        "holds); `tests/test_config_reference.py` fails when this file is out of date. Do not edit it by hand:",
        "run `.venv/bin/python tools/config_reference.py`.",
        "",
        "Default: the value `load_config()` gives with no overlay (`config/default.yaml` and the files it",
        "includes), in the canonical unit. A YAML value or `--set` value may be a plain number (canonical unit)",
        "or a string with one of the units listed (`gamma_bar: 0.367 rad`, `--set sim.camera.delay='100 ms'`);",
        "\"-\" is a plain number (its unit, if any, is in the description). \"empty\" is YAML `null` / no value.",
        "How overlays and `--set` combine: README \"Configuration\".",
        "",
    ]
    for name, field in Config.model_fields.items():
        section = field.annotation
        doc = (section.__doc__ or "").strip().split("\n\n")[0]
        lines += [f"## `{name}`", ""]
        if doc and not doc.startswith("A base class") and section.__doc__ != BaseModel.__doc__:
            lines += [" ".join(doc.split()), ""]
        lines += ["| key | type | unit | default | description |", "|---|---|---|---|---|"]
        for row in rows(section, getattr(cfg, name), name, comments):
            lines.append("| " + " | ".join(_cell(c) for c in row) + " |")
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help="where to write (default: docs/config-reference.md)")
    args = ap.parse_args(argv)
    args.out.write_text(render(), encoding="utf-8")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
