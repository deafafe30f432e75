"""``companion log summary`` and ``companion log export``: a flight folder as numbers and as one table.

Summary (text or ``--json``): the outcome, every state entered with its time and how long it lasted,
gate crossings with the distance from the centre where the log has truth (simulated flights), frames
and dropped frames, and the frame -> setpoint latency percentiles.

Export: one merged CSV (``flight.csv``) with a common time column ``t`` (seconds on the flight clock)
and one column per ``topic/column``; a cell is empty where that topic has no sample at that time (no
interpolation, no hold: every value is one that was logged). PlotJuggler's CSV loader takes ``t`` as
the time axis and builds a tree from the ``/`` in the names; a spreadsheet opens it as it is. Text
columns (state names, flight mode) stay text; ``states/state_index`` is the state as a number so it can
be plotted. ``--fill hold`` repeats each topic's last value instead of leaving cells empty, for tools
that cannot take sparse rows (PlotJuggler 3.14.3 typed a column from its first row only; fixed after).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.flightlog import Flight, check_output, flight_crossings, latest_flight, read_flight, write_output

LATENCY_PERCENTILES = (50, 90, 95, 99)
# A frame interval longer than this many nominal periods means frames were lost in between.
GAP_PERIODS = 1.5


@dataclass
class StateSpan:
    state: str
    t_enter: float
    duration: float | None  # None: the last state (the flight ended in it)
    reason: str


@dataclass
class GateRow:
    t: float
    d_center: float
    radius: float
    through: bool


@dataclass
class LogSummary:
    folder: str
    outcome: str
    reason: str | None
    exit_code: int | None
    detail: str
    duration_s: float | None
    states: list[StateSpan] = field(default_factory=list)
    gates: list[GateRow] = field(default_factory=list)
    frames: int = 0
    dropped_frames: int = 0  # missed frames: frame-index gaps, or frame intervals > GAP_PERIODS periods
    frame_rate_hz: float | None = None  # measured from the frame times
    setpoints: int = 0
    shadow: bool = False  # setpoints were computed and logged, never sent
    has_truth: bool = False  # truth and gate topics hold rows (simulated flights)
    latency_ms: dict[str, float | None] = field(default_factory=dict)
    hover_thrust: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def resolve_folder(path: str | Path) -> Path:
    """A flight folder, or a log directory (its latest flight)."""
    folder = Path(path)
    if (folder / "meta.json").exists():
        return folder
    latest = latest_flight(folder)
    if latest is None:
        raise FileNotFoundError(f"{folder}: no flight log here (no meta.json)")
    return latest


def _finite(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    return a[np.isfinite(a)]


def state_spans(flight: Flight) -> list[StateSpan]:
    rows = flight.states
    out: list[StateSpan] = []
    for i, r in enumerate(rows):
        t = float(r["t"])
        nxt = float(rows[i + 1]["t"]) if i + 1 < len(rows) else None
        out.append(StateSpan(str(r["to_state"]), t, None if nxt is None else nxt - t, str(r["reason"])))
    return out


def frame_stats(flight: Flight, rate_hz: float | None) -> tuple[int, int, float | None]:
    """(frames, dropped frames, measured frame rate) from the detections topic."""
    det = flight.tables.get("detections")
    if det is None or len(det) == 0:
        return 0, 0, None
    idx = _finite(det["frame"])
    tf = _finite(det["t_frame"])
    dropped_idx = int(np.sum(np.clip(np.diff(idx) - 1, 0, None))) if idx.size > 1 else 0
    dropped_t = 0
    measured = None
    if tf.size > 1:
        dt = np.diff(tf)
        span = tf[-1] - tf[0]
        measured = float((tf.size - 1) / span) if span > 0 else None
        if rate_hz:
            period = 1.0 / rate_hz
            gaps = dt[dt > GAP_PERIODS * period]
            dropped_t = int(np.sum(np.round(gaps / period) - 1))
    return len(det), max(dropped_idx, dropped_t), measured


def latency_stats(flight: Flight) -> dict[str, float | None]:
    """Percentiles of frame -> setpoint latency. The first setpoint is not a sample: it includes
    PX4's switch to OFFBOARD (the app logs it but leaves it out of its own figures too)."""
    sp = flight.tables.get("setpoints")
    lat = _finite(sp["latency_ms"])[1:] if sp is not None and len(sp) > 1 else np.array([])
    out: dict[str, float | None] = {f"p{p}": (float(np.percentile(lat, p)) if lat.size else None)
                                    for p in LATENCY_PERCENTILES}
    out["max"] = float(lat.max()) if lat.size else None
    out["n"] = float(lat.size)
    return out


def hover_info(flight: Flight) -> dict[str, Any]:
    """The hover thrust the flight used and where it came from (events written by the app)."""
    ev = flight.tables.get("events")
    out: dict[str, Any] = {}
    if ev is None:
        return out
    for t, text in zip(ev["t"], ev["text"], strict=True):
        s = str(text)
        if s.startswith("hover thrust"):
            out = {"t": float(t), "text": s}
    return out


def summarise(folder: str | Path) -> LogSummary:
    folder = resolve_folder(folder)
    flight = read_flight(folder)
    s = flight.summary
    rate = (flight.config.get("camera") or {}).get("rate")
    frames, dropped, measured = frame_stats(flight, float(rate) if rate else None)
    sp = flight.tables.get("setpoints")
    shadow = bool(sp is not None and len(sp) and np.any(np.asarray(sp["state"], dtype=str) == "SHADOW"))
    gates = [GateRow(c.t, c.d_center, c.radius, c.through) for c in flight_crossings(flight)]
    return LogSummary(
        folder=str(folder), outcome=str(s.get("outcome", "unknown")), reason=s.get("reason"),
        exit_code=s.get("exit_code"), detail=str(s.get("detail", "")), duration_s=s.get("duration_s"),
        states=state_spans(flight), gates=gates, frames=frames, dropped_frames=dropped, frame_rate_hz=measured,
        setpoints=len(sp) if sp is not None else 0, shadow=shadow, latency_ms=latency_stats(flight),
        hover_thrust=hover_info(flight),
        has_truth=all(len(flight.tables.get(k, ())) > 0 for k in ("truth", "gate")),
    )


def format_summary(s: LogSummary) -> str:
    def num(v: Any, f: str = ".1f") -> str:
        return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, f)

    lines = [f"flight {s.folder}",
             f"outcome: {s.outcome} ({s.reason}, exit {s.exit_code}): {s.detail}",
             f"duration: {num(s.duration_s)} s" + ("   SHADOW (setpoints never sent)" if s.shadow else ""),
             "states:"]
    for st in s.states:
        lines.append(f"  {st.t_enter:7.2f} s  {st.state:<18} {num(st.duration, '6.2f'):>6} s  {st.reason}")
    if s.gates:
        lines.append("gates:")
        for i, g in enumerate(s.gates, 1):
            lines.append(f"  gate {i}: t = {g.t:.2f} s, {g.d_center:.2f} m from the centre "
                         f"({'through' if g.through else 'missed'}, radius {g.radius:.2f} m)")
    elif s.has_truth:
        lines.append("gates: no gate plane crossed")
    else:
        lines.append("gates: no truth in this log (distances need the truth and gate topics)")
    lines.append(f"frames: {s.frames} (dropped {s.dropped_frames}), measured rate {num(s.frame_rate_hz)} Hz; "
                 f"setpoints: {s.setpoints}")
    lat = s.latency_ms
    lines.append("frame -> setpoint latency: " + ", ".join(f"p{p} {num(lat.get(f'p{p}'))}" for p in
                                                          LATENCY_PERCENTILES)
                 + f", max {num(lat.get('max'))} ms (n = {int(lat.get('n') or 0)})")
    if s.hover_thrust:
        lines.append(f"{s.hover_thrust['text']} (t = {s.hover_thrust['t']:.2f} s)")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------ export


def _state_index() -> dict[str, int]:
    from companion.app.states import State

    return {s.value: i for i, s in enumerate(State)}


def export_merged(folder: str | Path, out: str | Path | None = None, fill: str = "none",
                  skipped: dict[str, int] | None = None) -> Path:
    """One CSV, common time column ``t``, columns ``topic/column``; empty cells where a topic has no sample
    (``fill="none"``), or each topic's last logged value held until its next sample (``fill="hold"``).
    Rows whose t is not a finite number have no place on the time axis: left out, counted per topic in
    ``skipped``. The output may not be one of the flight log's own files (flightlog.check_output)."""
    folder = resolve_folder(folder)
    path = check_output(Path(out) if out is not None else folder / "flight.csv", folder, "flight.csv")
    flight = read_flight(folder)
    index = _state_index()
    cols: list[str] = []
    per_time: dict[float, dict[str, Any]] = {}
    for topic in sorted(flight.tables):
        tab = flight.tables[topic]
        names = [c for c in tab.columns if c != "t"]
        cols += [f"{topic}/{c}" for c in names]
        if topic == "states":
            cols.append("states/state_index")
        for i in range(len(tab)):
            try:
                t = float(tab["t"][i])
            except (TypeError, ValueError):
                t = math.nan
            if not math.isfinite(t):
                if skipped is not None:
                    skipped[topic] = skipped.get(topic, 0) + 1
                continue
            row = per_time.setdefault(t, {})
            # Two rows of one topic at the same instant: keep both (second on a row of its own).
            while any(k.startswith(topic + "/") for k in row):
                t = math.nextafter(t, math.inf)
                row = per_time.setdefault(t, {})
            for c in names:
                row[f"{topic}/{c}"] = tab[c][i]
            if topic == "states":
                row["states/state_index"] = index.get(str(tab["to_state"][i]), -1)
    path.parent.mkdir(parents=True, exist_ok=True)
    # Written in one go and flushed inside the with: a full disk or /dev/full is an OSError, not a silent 0.
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["t", *cols])
    held: dict[str, Any] = {}
    for t in sorted(per_time):
        row = per_time[t]
        if fill == "hold":
            held.update({c: v for c, v in row.items() if _cell(v) != ""})
            row = held
        w.writerow([format(t, ".9g"), *(_cell(row.get(c)) for c in cols)])
    write_output(path, buf.getvalue().encode("utf-8"))
    return path


def _cell(v: Any) -> Any:
    if v is None:
        return ""
    if isinstance(v, float | np.floating):
        return "" if not math.isfinite(float(v)) else format(float(v), ".9g")
    return v


# ------------------------------------------------------------------------------------------------ CLI


def register_log_actions(lsub: Any) -> None:
    """Add ``summary`` and ``export`` to the ``companion log`` group (created by companion/app/main.py)."""
    sp = lsub.add_parser("summary", help="outcome, states with times, gates, dropped frames, latency")
    sp.add_argument("folder", help="flight folder (or a log directory: its latest flight)")
    sp.add_argument("--json", action="store_true", help="machine-readable JSON on stdout")
    sp.set_defaults(func=_cmd_summary)
    ep = lsub.add_parser("export", help="one merged CSV (common time column t) for PlotJuggler / spreadsheets")
    ep.add_argument("folder", help="flight folder (or a log directory: its latest flight)")
    ep.add_argument("-o", "--output", help="CSV path (default FOLDER/flight.csv)")
    ep.add_argument("--fill", choices=("none", "hold"), default="none",
                    help="none: empty cell where a topic has no sample (default); hold: repeat each topic's last "
                         "value (for tools that need every cell filled)")
    ep.set_defaults(func=_cmd_export)
    from companion.logclutter import register as register_clutter

    register_clutter(lsub)  # log clutter: gate or clutter, per engaged frame, from a synthetic-camera log's truth
    from companion.logrerun import register as register_rerun

    register_rerun(lsub)  # log rerun: the flight core again on a log's frames, as flown or with another config


def _cmd_summary(args: argparse.Namespace) -> int:
    try:
        s = summarise(args.folder)
    except (FileNotFoundError, ValueError) as e:
        print(f"companion log summary: {e}", file=sys.stderr)
        return 2
    except MemoryError:
        print(f"companion log summary: {args.folder}: too large to read in memory", file=sys.stderr)
        return 2
    print(json.dumps(s.as_dict(), indent=1) if args.json else format_summary(s))
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    skipped: dict[str, int] = {}
    try:
        out = export_merged(args.folder, args.output, args.fill, skipped)
    except (FileNotFoundError, ValueError) as e:
        print(f"companion log export: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # the output cannot be written (disk full, /dev/full, no permission)
        print(f"companion log export: {e.filename or args.output}: cannot write ({e.strerror or e})", file=sys.stderr)
        return 2
    except MemoryError:
        print(f"companion log export: {args.folder}: too large to export in memory", file=sys.stderr)
        return 2
    if skipped:
        print(f"companion log export: left out {sum(skipped.values())} row(s) whose t is not a finite number ("
              + ", ".join(f"{k}: {v}" for k, v in sorted(skipped.items())) + ")", file=sys.stderr)
    print(out)
    return 0
