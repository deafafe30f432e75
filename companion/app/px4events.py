"""PX4 events (MAVLink EVENT, id 410) to one line of text, from PX4's own event metadata.

PX4 1.15 reports arming refusals, failsafes, take-off and landing through the events protocol, not
STATUSTEXT. mavsdk's ``events`` plugin needs the metadata over MAVLink FTP, which PX4 SITL here does
not serve (its FTP answers "file not found" for ``mftp://etc/extras/component_general.json.xz``), so
the plugin queues every event forever. The app therefore reads the raw EVENT messages
(mavsdk ``mavlink_direct``) and decodes them here with the metadata file of the PX4 release it flies:
``companion/app/px4_events.json.xz`` ships PX4 v1.15's ``all_events.json.xz`` (BSD 3-Clause, from
the PX4-Autopilot build in ../shared/px4-sitl); ``link.events_metadata`` names another one.

An EVENT carries a 32-bit id (component << 24 | event), a log level and up to 40 bytes of packed
little-endian arguments; the message text has ``{1}``, ``{2:.1m}`` ... placeholders for them.
"""

from __future__ import annotations

import json
import lzma
import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

DEFAULT_METADATA = Path(__file__).with_name("px4_events.json.xz")

_FMT = {"uint8_t": "<B", "int8_t": "<b", "uint16_t": "<H", "int16_t": "<h", "uint32_t": "<I", "int32_t": "<i",
        "uint64_t": "<Q", "int64_t": "<q", "float": "<f"}
# MAVLink's external log level (low nibble of log_levels) -> name; 0..3 are failures, 4 warnings.
LEVELS = ("emergency", "alert", "critical", "error", "warning", "notice", "info", "debug")
_PLACEHOLDER = re.compile(r"\{(\d+)(?::([^}]*))?\}")
_TAG = re.compile(r"</?[a-z]+[^>]*>")


@dataclass(frozen=True)
class Px4Event:
    id: int
    name: str  # e.g. "commander_armed_by"; "event_<id>" when the metadata does not know it
    level: str  # one of LEVELS
    text: str  # the message with its arguments filled in
    sequence: int
    group: str = "default"  # "arming_check" and "health": PX4's periodic check reports (not news)

    @property
    def severe(self) -> bool:
        """Warnings and worse that are news (not a line of PX4's periodic check report)."""
        return LEVELS.index(self.level) <= LEVELS.index("warning") and self.group not in ("arming_check", "health")


class EventDecoder:
    """Event metadata (PX4's all_events.json) -> ``decode(fields)`` for EVENT messages."""

    def __init__(self, metadata: dict[str, Any]) -> None:
        self._events: dict[int, dict[str, Any]] = {}
        self._enums: dict[str, dict[str, Any]] = {}
        for cid, comp in metadata.get("components", {}).items():
            ns = comp.get("namespace", "")
            for ename, enum in comp.get("enums", {}).items():
                self._enums[f"{ns}::{ename}"] = enum
            for gname, group in comp.get("event_groups", {}).items():
                for sid, ev in group.get("events", {}).items():
                    self._events[(int(cid) << 24) | int(sid)] = {**ev, "group": gname}

    @classmethod
    def load(cls, path: str | Path | None = None) -> EventDecoder:
        p = Path(path) if path else DEFAULT_METADATA
        if p.suffix == ".xz":
            with lzma.open(p) as f:
                raw = f.read()
        else:
            raw = p.read_bytes()
        return cls(json.loads(raw))

    def __len__(self) -> int:
        return len(self._events)

    def _args(self, ev: dict[str, Any], data: bytes) -> list[str]:
        out: list[str] = []
        off = 0
        for a in ev.get("arguments", []):
            typ = a["type"]
            enum = self._enums.get(typ)
            base = enum["type"] if enum is not None else typ
            fmt = _FMT.get(base)
            if fmt is None or off + struct.calcsize(fmt) > len(data):
                out.append("?")
                continue
            (v,) = struct.unpack_from(fmt, data, off)
            off += struct.calcsize(fmt)
            if enum is not None:
                entry = enum.get("entries", {}).get(str(v))
                out.append(entry.get("description") or entry.get("name", str(v)) if entry else str(v))
            else:
                out.append(v)
        return out

    def decode(self, fields: dict[str, Any]) -> Px4Event:
        """``fields``: the EVENT message as a dict (mavsdk mavlink_direct's fields_json, parsed)."""
        eid = int(fields.get("id", 0))
        lvl = int(fields.get("log_levels", 6)) & 0x0F
        level = LEVELS[lvl] if lvl < len(LEVELS) else "debug"
        seq = int(fields.get("sequence", 0))
        ev = self._events.get(eid)
        if ev is None:
            return Px4Event(eid, f"event_{eid}", level, f"event {eid} (not in the metadata)", seq)
        args = self._args(ev, bytes(int(b) & 0xFF for b in fields.get("arguments", [])))

        def fill(m: re.Match[str]) -> str:
            i, spec = int(m.group(1)) - 1, m.group(2) or ""
            if not 0 <= i < len(args):
                return m.group(0)
            v = args[i]
            prec = re.match(r"\.(\d+)", spec)
            if prec and isinstance(v, float):
                return f"{v:.{prec.group(1)}f}"
            return str(v)

        text = _TAG.sub("", _PLACEHOLDER.sub(fill, ev.get("message", ""))).replace("\\", "")
        return Px4Event(eid, ev.get("name", f"event_{eid}"), level, text, seq, ev.get("group", "default"))

    def event_id(self, name: str) -> int:
        """The id of the event called ``name`` (the simulated PX4 sends PX4's own ids)."""
        for eid, ev in self._events.items():
            if ev.get("name") == name:
                return eid
        raise KeyError(f"PX4 event {name!r} is not in the metadata")

    def encode_args(self, name: str, *values: float) -> bytes:
        """Pack ``values`` as the event's arguments (for the simulated PX4)."""
        ev = self._events[self.event_id(name)]
        out = b""
        for a, v in zip(ev.get("arguments", []), values, strict=False):
            enum = self._enums.get(a["type"])
            fmt = _FMT[enum["type"] if enum is not None else a["type"]]
            out += struct.pack(fmt, float(v) if fmt == "<f" else int(v))
        return out
