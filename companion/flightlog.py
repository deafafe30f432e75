"""Flight log: one folder per flight, one CSV file per topic, written as it happens.

Why CSV per topic (and not MCAP): every field engineer's tool reads it (numpy, pandas,
a spreadsheet, ``column -s,``), each topic has a fixed header, and an append-only text
file stays readable after a SIGKILL or a power cut: at worst the last line is cut
short, and the reader drops it. An MCAP file killed mid-write has no summary section
and a possibly truncated chunk, which needs a recovery step first.

Layout of a flight folder::

    meta.json      start wall time, host, command line, format version
    config.json    the full config used (canonical units)
    states.csv     every state transition with its reason (flushed at once)
    <topic>.csv    telemetry, truth, detections, los, setpoints, ... (flushed every flush_interval)
    summary.json   the outcome (safe state, reason, exit code), written at the end
    plot.png       optional, ``plot_flight``

Times are seconds on the flight clock (monotonic, 0 at log start).

Failing safe: a log that cannot be started (folder not writable, disk full or nearly full) is a
``FlightLogError`` before anything flies, and a half-made folder is removed. A write that fails in
flight never raises into the flight: that topic stops (what it holds stays valid, nothing false is
added), one line goes to stderr, and the summary says ``log_complete: false`` with the error. A
reserve file (``RESERVE_BYTES``) taken at the start is given back at the end, so the last buffered
rows and ``summary.json`` still fit on a disk that filled up during the flight.
"""

from __future__ import annotations

import contextlib
import csv
import datetime as dt
import json
import math
import os
import shutil
import socket
import stat
import sys
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.scoring import plane_crossings

FORMAT_VERSION = 1

# Topics with their columns. Fixed here so a reader (and a test) knows what to expect.
TOPICS: dict[str, tuple[str, ...]] = {
    "states": ("t", "from_state", "to_state", "reason"),
    "events": ("t", "level", "text"),
    "telemetry": (
        "t", "t_att", "qw", "qx", "qy", "qz", "roll_deg", "pitch_deg", "yaw_deg",
        "baro_alt_m", "flight_mode", "armed", "landed_state",
        "acc_f", "acc_r", "acc_d", "gyro_f", "gyro_r", "gyro_d",  # IMU, body FRD (specific force m/s^2, rad/s)
    ),
    # Ground truth / EKF position & velocity: for scoring and plots only, never a controller input.
    # With the simulator's attitude (NED/FRD wxyz) at its own time t_truth where the source has one: the synthetic
    # camera drew with it, and companion/logclutter.py recomputes the gate's true box from it.
    "truth": ("t", "n", "e", "d", "vn", "ve", "vd", "t_truth", "qw", "qx", "qy", "qz"),
    # rival_*: the frame's most confident other candidate (perception/types.py BoundingBox.rival), empty: none
    "detections": ("t", "t_frame", "frame", "cx", "cy", "w", "h", "confidence", "valid",
                   "rival_cx", "rival_cy", "rival_w", "rival_h", "rival_confidence"),
    "los": ("t", "t_frame", "los_n", "los_e", "los_d", "lambda_dot", "a_n", "demand_scale", "rejected"),
    "setpoints": (
        "t", "t_frame", "state", "ctrl_mode", "roll_deg", "pitch_deg", "yaw_deg", "thrust", "latency_ms",
    ),
    # Synthetic camera only: the virtual gate in view (centre, plane normal, radius), NED.
    # One row per gate per frame; k = gate number (1 = nearest at the start), visible = the one in view.
    "gate": ("t", "k", "gate_n", "gate_e", "gate_d", "normal_n", "normal_e", "normal_d", "radius", "visible"),
    # hover.estimate: the hover-thrust estimate (companion/hover.py) and the sample that updated it.
    "hover": ("t", "u_cmd", "a_up", "hover_thrust", "std", "samples"),
    # What the loop gave FlightCore.step for each frame besides its box (detections, same t_frame): the attitude
    # at capture, baro above the reference, the accelerometer sample and its time, the time processed, the
    # operator's confirmation (1/0, empty: auto) and the hover thrust the core held before the step.
    # ``companion log rerun`` (companion/logrerun.py) steps a core with these again.
    "inputs": ("t", "t_frame", "qw", "qx", "qy", "qz", "baro_rel_m", "acc_f", "acc_r", "acc_d", "t_imu", "t_now",
               "confirm", "hover_thrust"),
}
IMMEDIATE = frozenset({"states", "events"})  # rare and precious: straight to the OS
RESERVE_BYTES = 256 * 1024  # > the topics' write buffers (8 KB each) + summary.json
DEFAULT_FLUSH_INTERVAL = 0.25  # s; a SIGKILL loses at most this + one gap between writes (see FlightLog)


class FlightLogError(RuntimeError):
    """The flight log cannot be started (one line: folder, what is wrong). Nothing has flown."""


def _fmt(v: Any) -> Any:
    if isinstance(v, bool | np.bool_):
        return int(v)
    if isinstance(v, float | np.floating):
        return format(float(v), ".9g")
    if v is None:
        return ""
    return v


class _Topic:
    def __init__(self, path: Path, columns: Sequence[str]) -> None:
        self.columns = tuple(columns)
        # Line buffering is not used: a write per row would cost a syscall per row at 30 Hz x topics.
        self._f = open(path, "w", encoding="utf-8", newline="")  # noqa: SIM115 (lives as long as the log)
        self._w = csv.writer(self._f, lineterminator="\n")
        self._w.writerow(self.columns)
        self._f.flush()  # the header is on disk from the start: a killed flight still has parseable files
        self.rows = 0

    def write(self, values: Sequence[Any]) -> None:
        if len(values) != len(self.columns):
            raise ValueError(f"flight log: {len(values)} values for {len(self.columns)} columns {self.columns}")
        self._w.writerow([_fmt(v) for v in values])
        self.rows += 1

    def flush(self) -> None:
        self._f.flush()

    def close(self, sync: bool) -> None:
        if self._f.closed:
            return
        try:
            self._f.flush()
            if sync:
                os.fsync(self._f.fileno())
        finally:
            with contextlib.suppress(OSError):  # (the flush above already reported the error)
                self._f.close()


class FlightLog:
    """Writer. ``write(topic, **values)``; ``flush()`` is called by ``tick()`` at least every flush_interval.

    What a SIGKILL can lose: rows are handed to the OS when a write finds ``flush_interval`` passed
    since the last flush, so at most ``flush_interval`` plus the gap between two writes (the flight
    app logs telemetry every 50 ms): 0.3 s with the default 0.25 s.
    """

    def __init__(
        self,
        folder: Path,
        config: Mapping[str, Any] | None = None,
        flush_interval: float = DEFAULT_FLUSH_INTERVAL,
        clock: Any = time.monotonic,
        argv: Sequence[str] | None = None,
        stderr: Any = None,
    ) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=False)
        self._clock = clock
        self.t0 = clock()
        self.flush_interval = float(flush_interval)
        self._last_flush = self.t0
        self._topics: dict[str, _Topic] = {}
        self._failed: dict[str, str] = {}  # topic -> first write error (that topic writes no more)
        self.dropped = 0  # rows not written because their topic had failed
        self._stderr = stderr
        self.closed = False
        meta = {
            "format": "companion-flightlog-csv",
            "version": FORMAT_VERSION,
            "start_utc": dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds"),
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "t0_monotonic": self.t0,  # flight time 0 on the host's monotonic clock
            "argv": list(argv if argv is not None else sys.argv),
            "topics": {k: list(v) for k, v in TOPICS.items()},
        }
        _write_json(self.folder / "meta.json", meta)
        if config is not None:
            _write_json(self.folder / "config.json", dict(config))
        # A summary exists from the start: after a SIGKILL it still says "running" (the flight did not end).
        _write_json(self.folder / "summary.json", {"outcome": "running"})
        for name in TOPICS:
            self._topics[name] = _Topic(self.folder / f"{name}.csv", TOPICS[name])
        # Real blocks (zeros are written, not a sparse hole), given back in close().
        with open(self.folder / ".reserve", "wb") as f:
            f.write(bytes(RESERVE_BYTES))
            f.flush()
            os.fsync(f.fileno())

    @classmethod
    def create(cls, directory: str | Path, config: Mapping[str, Any] | None = None, min_free_mb: float = 0.0,
               **kw: Any) -> FlightLog:
        """A new folder ``directory/YYYYmmdd-HHMMSS[-n]`` (never reuses an existing one).

        Any problem (not writable, not a folder, less than ``min_free_mb`` free, a write failing) is a
        one-line FlightLogError, and nothing half-made is left behind.
        """
        base = Path(directory)
        try:
            base.mkdir(parents=True, exist_ok=True)
            st = os.statvfs(base)
        except OSError as e:
            raise FlightLogError(f"{base}: cannot make the flight-log folder ({e.strerror or e})") from None
        free_mb = st.f_bavail * st.f_frsize / 1e6
        if free_mb < min_free_mb:
            raise FlightLogError(f"{base}: {free_mb:.1f} MB free, the flight log needs {min_free_mb:g} MB "
                                 "(log.min_free_mb)")
        stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
        for n in range(1000):
            folder = base / (stamp if n == 0 else f"{stamp}-{n}")
            try:
                return cls(folder, config, **kw)
            except FileExistsError:
                continue
            except OSError as e:
                if folder.is_dir():  # ours (exist_ok=False above): half-made, never a flight log
                    shutil.rmtree(folder, ignore_errors=True)
                raise FlightLogError(f"{base}: cannot write the flight log ({e.strerror or e})") from None
        raise FlightLogError(f"{base}: cannot create a new flight-log folder (1000 exist for {stamp})")

    @property
    def complete(self) -> bool:
        """Every row written reached its file (no write failed)."""
        return not self._failed

    def now(self) -> float:
        return self._clock() - self.t0

    def write(self, topic: str, **values: Any) -> None:
        if self.closed:
            return
        tp = self._topics.get(topic)
        if tp is None:
            raise KeyError(f"flight log: unknown topic {topic!r} (known: {', '.join(TOPICS)})")
        values.setdefault("t", self.now())
        unknown = set(values) - set(tp.columns)
        if unknown:
            raise KeyError(f"flight log: topic {topic!r} has no column(s) {sorted(unknown)}")
        if topic in self._failed:
            self.dropped += 1
            return
        try:
            tp.write([values.get(c) for c in tp.columns])
            if topic in IMMEDIATE:
                tp.flush()
        except OSError as e:
            self._fail(topic, e)
        self.tick()

    def state(self, from_state: str, to_state: str, reason: str, t: float | None = None) -> None:
        self.write("states", t=self.now() if t is None else t, from_state=from_state, to_state=to_state,
                   reason=reason)

    def event(self, text: str, level: str = "info") -> None:
        self.write("events", level=level, text=text)

    def tick(self) -> None:
        """Flush buffered topics if flush_interval has passed (cheap; call often)."""
        now = self._clock()
        if now - self._last_flush >= self.flush_interval:
            self.flush()

    def flush(self) -> None:
        for name, tp in self._topics.items():
            if name in self._failed:
                continue
            try:
                tp.flush()
            except OSError as e:
                self._fail(name, e)
        self._last_flush = self._clock()

    def _fail(self, topic: str, err: OSError) -> None:
        """A write failed: that topic writes no more (its file stays valid up to here); the flight goes on."""
        why = err.strerror or str(err)
        first = not self._failed
        self._failed[topic] = why
        if first:
            file = topic if "." in topic else f"{topic}.csv"
            self._say(f"companion: flight log write failed ({file}: {why}) at t={self.now():.2f} s: "
                      "the flight goes on, the log is incomplete from here")

    def _say(self, line: str) -> None:
        with contextlib.suppress(Exception):  # stderr itself may be gone: never raise into the flight
            out = self._stderr if self._stderr is not None else sys.stderr
            out.write(line + "\n")
            out.flush()

    def rows(self, topic: str) -> int:
        return self._topics[topic].rows

    def write_json(self, name: str, data: Any) -> bool:
        """An extra JSON file in the flight folder (e.g. preflight.json); like every log write, a failure
        never raises into the flight: it marks the log incomplete and returns False."""
        if self.closed:
            return False
        try:
            _write_json(self.folder / name, data)
            return True
        except OSError as e:
            self._fail(name, e)
            return False

    def close(self, summary: Mapping[str, Any] | None = None) -> None:
        """Close every topic and write the final summary; never raises for a write error."""
        if self.closed:
            return
        self.closed = True
        with contextlib.suppress(OSError):
            (self.folder / ".reserve").unlink()  # the room the last rows and the summary need
        for name, tp in self._topics.items():
            try:
                tp.close(sync=True)
            except OSError as e:
                self._fail(name, e)
        if summary is not None:
            s = dict(summary)
            s.setdefault("duration_s", self.now())
            s["rows"] = {k: v.rows for k, v in self._topics.items()}
            s["log_complete"] = self.complete
            if not self.complete:
                s["log_errors"] = dict(self._failed)
                s["log_rows_dropped"] = self.dropped
            try:
                _write_json(self.folder / "summary.json", s)
            except OSError as e:
                self._say(f"companion: flight log: cannot write summary.json ({e.strerror or e})")


def _write_json(path: Path, data: Any) -> None:
    # Write-then-rename: a reader never sees half a JSON file; a failed write leaves no .tmp behind.
    tmp = path.with_suffix(path.suffix + ".tmp")
    try:
        tmp.write_text(json.dumps(data, indent=1, default=_json_default) + "\n", encoding="utf-8")
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


# ----------------------------------------------------------------------------------------------- reading


@dataclass
class Table:
    """One topic: column name -> numpy array (float where every value parses, else str)."""

    columns: tuple[str, ...]
    data: dict[str, np.ndarray]
    truncated_rows: int = 0  # rows dropped because the file was cut mid-line

    def __len__(self) -> int:
        return len(next(iter(self.data.values()))) if self.data else 0

    def __getitem__(self, col: str) -> np.ndarray:
        return self.data[col]

    def rows(self) -> list[dict[str, Any]]:
        return [{c: self.data[c][i] for c in self.columns} for i in range(len(self))]


@dataclass
class Flight:
    folder: Path
    meta: dict[str, Any]
    config: dict[str, Any]
    summary: dict[str, Any]
    tables: dict[str, Table] = field(default_factory=dict)

    def __getitem__(self, topic: str) -> Table:
        return self.tables[topic]

    @property
    def states(self) -> list[dict[str, Any]]:
        return self.tables["states"].rows() if "states" in self.tables else []

    def state_path(self) -> list[str]:
        """The sequence of states entered, in order."""
        return [str(r["to_state"]) for r in self.states]


def _column(values: list[str]) -> np.ndarray:
    try:
        return np.array([float(v) if v != "" else math.nan for v in values], dtype=float)
    except ValueError:
        return np.array(values, dtype=object)


# Bounds for reading: a flight's own topics stay far below (telemetry at 20 Hz is ~40 MB per hour); a bigger
# file, a device (/dev/zero), a FIFO (blocks forever) or a folder is not a flight log and is refused unread.
MAX_TOPIC_BYTES = 256 * 1024 * 1024
MAX_JSON_BYTES = 16 * 1024 * 1024
MAX_FIELD_BYTES = 128 * 1024  # csv's own limit: a longer field is refused with its line, not a traceback
# Files the log tools themselves write into a flight folder (everything else there is the raw log).
TOOL_PRODUCTS = frozenset({"flight.csv", "plot.png"})


def _readable(path: Path, limit: int) -> None:
    """Refuse, unread, what is not a regular file of at most ``limit`` bytes (ValueError, one line)."""
    try:
        st = os.stat(path)
    except OSError as e:
        raise ValueError(f"{path}: cannot read ({e.strerror or e})") from None
    if not stat.S_ISREG(st.st_mode):
        raise ValueError(f"{path}: not a regular file (a FIFO, device or folder is not a flight-log file)")
    if st.st_size > limit:
        raise ValueError(f"{path}: {st.st_size / 1e6:.0f} MB, more than the {limit / 1e6:.0f} MB a flight-log file "
                         "may have")


def read_table(path: str | Path) -> Table:
    """Read one topic CSV, dropping a last line cut short by a kill."""
    path = Path(path)
    _readable(path, MAX_TOPIC_BYTES)
    with open(path, "rb") as fb:
        size = fb.seek(0, os.SEEK_END)
        cut = False
        if size:
            fb.seek(-1, os.SEEK_END)
            cut = fb.read(1) != b"\n"
    # Streamed, column by column: the file is never held as text and as a list of every row's cells at once.
    with open(path, encoding="utf-8", errors="replace", newline="") as f:
        reader = csv.reader(f)
        try:
            header = tuple(next(reader))
        except StopIteration:
            raise ValueError(f"{path}: empty flight-log file (no header)") from None
        except csv.Error as e:
            raise ValueError(f"{path}: line 1: not a flight-log CSV ({e})") from None
        cols: list[list[str]] = [[] for _ in header]
        seen, last_kept = 0, False
        while True:
            try:
                r = next(reader)
            except StopIteration:
                break
            except csv.Error as e:
                raise ValueError(f"{path}: line {reader.line_num}: not a flight-log CSV ({e})") from None
            seen += 1
            last_kept = len(r) == len(header)
            if last_kept:
                for c, v in zip(cols, r, strict=True):
                    c.append(v)
    if cut and seen and last_kept:  # the unfinished last line, complete in cell count but cut short
        for c in cols:
            c.pop()
    n = len(cols[0]) if cols else 0
    data = {c: _column(v) for c, v in zip(header, cols, strict=True)}
    return Table(header, data, seen - n)


def read_flight(folder: str | Path, topics: Iterable[str] | None = None) -> Flight:
    """Read a flight folder (also one whose writer was killed). Missing JSON files read as {}."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: not a flight-log folder")

    def js(name: str) -> dict[str, Any]:
        p = folder / name
        if not p.exists():
            return {}
        _readable(p, MAX_JSON_BYTES)
        try:
            data = json.loads(p.read_text(encoding="utf-8"))
        except (ValueError, UnicodeDecodeError) as e:
            raise ValueError(f"{p}: not valid JSON ({' '.join(str(e).split())[:80]})") from None
        if not isinstance(data, dict):
            raise ValueError(f"{p}: expected a JSON object, got {type(data).__name__}")
        return data

    flight = Flight(folder, js("meta.json"), js("config.json"), js("summary.json"))
    names = list(topics) if topics is not None else [p.stem for p in sorted(folder.glob("*.csv"))]
    for name in names:
        p = folder / f"{name}.csv"
        if p.exists() and p.name not in TOOL_PRODUCTS:  # flight.csv is the export, not a topic
            flight.tables[name] = read_table(p)
    return flight


def is_flight_folder(path: str | Path) -> bool:
    return (Path(path) / "meta.json").is_file()


def check_output(out: str | Path, source: str | Path | None = None, product: str = "") -> Path:
    """Refuse an output path that would overwrite a flight's raw log (ValueError, one line).

    Resolved to its real path first (symlinks, ``..``): in a flight folder (one with meta.json) a log tool
    may write only its own product (``product``, one of ``TOOL_PRODUCTS``) or a new file that is not a name
    the flight log uses; anywhere, it may not be (a hard link to) any file of the flight it reads."""
    out = Path(out)
    real = Path(os.path.realpath(out))
    parent = real.parent
    if real.is_dir():
        raise ValueError(f"{out}: is a folder; give a file name")
    if is_flight_folder(parent) and real.name != product:
        raw = {f"{t}.csv" for t in TOPICS} | {"meta.json", "config.json", "summary.json", ".reserve"}
        if real.exists() or real.name in raw:
            raise ValueError(f"{out}: would overwrite {real.name} of the flight log in {parent}; write elsewhere"
                             + (f" (or to {product} there)" if product else ""))
    if source is not None and real.exists() and Path(source).is_dir():
        for f in Path(source).iterdir():
            with contextlib.suppress(OSError):
                if f.name != product and os.path.samefile(f, real):
                    raise ValueError(f"{out}: is the flight log's {f.name} (a link to it); write elsewhere")
    return out


def write_output(out: Path, data: bytes) -> None:
    """Write a log tool's product; a write error (disk full, /dev/full) raises OSError, never passes silently."""
    with open(out, "wb") as f:
        f.write(data)
        f.flush()


def latest_flight(directory: str | Path) -> Path | None:
    """The most recently created flight folder under ``directory`` (None if there is none)."""
    base = Path(directory)
    if not base.is_dir():
        return None
    folders = [p for p in base.iterdir() if (p / "meta.json").exists()]
    return max(folders, key=lambda p: p.stat().st_mtime_ns, default=None)


@dataclass(frozen=True)
class Crossing:
    t: float  # flight time of the crossing, s
    d_center: float  # distance from the gate centre in the gate plane, m
    radius: float  # gate radius, m

    @property
    def through(self) -> bool:
        return self.d_center < self.radius


def gate_crossings(flight: Flight) -> list[Crossing]:
    """Where the logged vehicle position (truth topic) crossed the logged virtual gate's plane.

    Scoring only (synthetic-camera flights): the gate centre is interpolated to the truth samples, and
    each crossing (signed distance along the gate's first logged normal going + -> -) is companion/scoring.py's
    ``plane_crossings``, the geometry of the simulator and of the app's judge. This re-scores the log's own
    samples; ``flight_crossings`` gives the app's live judgement where the flight recorded one.
    """
    gate, truth = flight.tables.get("gate"), flight.tables.get("truth")
    if gate is None or truth is None or len(gate) < 2 or len(truth) < 2:
        return []
    out: list[Crossing] = []
    for k in np.unique(gate["k"][np.isfinite(gate["k"])]):
        out += _crossings_of(gate, truth, np.isfinite(gate["gate_n"]) & (gate["k"] == k))
    return sorted(out, key=lambda c: c.t)


def flight_crossings(flight: Flight) -> list[Crossing]:
    """The flight's gate crossings as the app judged them live (summary.json "truth", on the flight-log clock).

    One computation for a flight: its verdict, summary.json and the gate lines printed after it all come from
    the app's judge (companion/app/outcome.py); re-scoring the logged topics (``gate_crossings``) stamps the
    truth rows at another instant and so can give another distance. A log without that record (killed, shadow
    mode, written before summary.json kept the crossing time) is re-scored from its topics.
    """
    truth = flight.summary.get("truth")
    gates = truth.get("gates") if isinstance(truth, dict) else None
    t0 = flight.meta.get("t0_monotonic")
    if not isinstance(gates, list) or t0 is None \
            or any(g.get("crossed") and g.get("t_monotonic_s") is None for g in gates):
        return gate_crossings(flight)
    return sorted((Crossing(float(g["t_monotonic_s"]) - float(t0), float(g["d_center_m"]), float(g["radius_m"]))
                   for g in gates if g.get("crossed")), key=lambda c: c.t)


def _crossings_of(gate: Table, truth: Table, g_ok: np.ndarray) -> list[Crossing]:
    gt = gate["t"][g_ok]
    if len(gt) < 2:
        return []
    tt = truth["t"]
    t_own = truth.data.get("t_truth")
    if t_own is not None and t_own.dtype.kind == "f" and np.isfinite(t_own).all():
        tt = t_own  # the sample's own time, as the app's judge takes it (older logs: the row's)
    sel = (tt >= gt[0]) & (tt <= gt[-1])
    tt = tt[sel]
    p = np.column_stack([truth[c][sel] for c in ("n", "e", "d")])
    c = np.column_stack([np.interp(tt, gt, gate[k][g_ok]) for k in ("gate_n", "gate_e", "gate_d")])
    # One normal and radius per gate, the first logged (as the app's judge takes them): a gate does not turn or grow.
    normal = np.array([gate[k][g_ok][0] for k in ("normal_n", "normal_e", "normal_d")])
    radius = float(gate["radius"][g_ok][0])
    return [Crossing(x.t, x.d_center, radius) for x in plane_crossings(normal, tt, p, c)]
