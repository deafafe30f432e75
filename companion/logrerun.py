"""``companion log rerun FLIGHT...``: the flight core stepped again on a flight log's frames, with the config the
flight flew or a changed one (``--set``, ``--config``): what would it have decided on the same frames?

Open loop. The frames, attitudes and IMU samples are the logged ones, so a rerun with the flown config must
reproduce the log (each logged setpoint, each phase change: the check of the log and of this tool), and a rerun
with another config shows where that config decides otherwise. After its first different decision the logged
vehicle no longer flew what the rerun commands: later decisions answer "on these frames", not "in that flight".
In a shadow-mode log nothing the app decided moved the vehicle, so every decision of a rerun is as valid as the
log's; there the core starts a new engagement after each end, as shadow mode does.

Inputs per frame: ``inputs.csv`` (what the loop gave ``FlightCore.step``, companion/app/perframe.py) and the
frame's box from ``detections.csv``. A log written before inputs.csv existed is rerun from ``telemetry.csv``
(attitude slerped from its 20 Hz samples, the newest accelerometer row, no baro floor, no operator confirmation,
the hover thrust of summary.json): approximate. On the 200 real-PX4 flights of
docs/results/px4_*_100_20261206e, 189 make the logged phase changes on the same frames that way (the
rest a frame or more apart; no setpoint is reproduced exactly).

The box's appearance (target verification's appearance rule) is not in the log: a rerun judges boxes without it.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from companion.attitude import AttitudeTrack
from companion.core import FlightCore, FrameInput, ImuReading
from companion.flightlog import Flight, Table, read_flight
from companion.hover import HoverThrustEstimator, use_hover_thrust
from perception.types import BoundingBox

SETPOINT_TOL = 1e-4  # deg / thrust fraction: the log's 9 significant digits, carried through one step


@dataclass
class Step:
    t_frame: float  # capture time, flight-log clock
    phase: str
    why: str
    setpoint: tuple[float, float, float, float] | None  # roll, pitch, yaw deg, thrust


@dataclass
class Rerun:
    folder: Path
    exact: bool  # from inputs.csv (False: reconstructed from telemetry.csv)
    steps: list[Step] = field(default_factory=list)
    # (t_frame, phase, why) of each change: the capture time of the frame that made it; the log's the same way
    changes: list[tuple[float, str, str]] = field(default_factory=list)
    logged_changes: list[tuple[float, str]] = field(default_factory=list)
    setpoint_diff: float = 0.0  # largest difference to a logged setpoint on the same frame
    first_diff: float | None = None  # t_frame of the first logged setpoint the rerun does not reproduce
    compared: int = 0  # logged setpoints compared
    perception: dict[str, Any] | None = None  # --rerender: the boxes on the frames drawn again (logrender.summary)


def _num(v: Any) -> float | None:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def _boxes(flight: Flight) -> dict[float, BoundingBox | None]:
    """The box of each perceived frame (flight-log clock), None where the frame gave none."""
    det, t0 = flight["detections"], float(flight.meta["t0_monotonic"])
    out: dict[float, BoundingBox | None] = {}
    for r in det.rows():
        tf = _num(r["t_frame"])
        if tf is None:
            continue
        vals = [_num(r[k]) for k in ("cx", "cy", "w", "h", "confidence")]
        ok = str(r["valid"]).strip() in ("1", "True", "true", "1.0") and all(v is not None for v in vals)
        # The frame's other candidate (logs before 2026-12-07 have none: the rule never acts on them)
        rv = [_num(r.get(f"rival_{k}")) for k in ("cx", "cy", "w", "h", "confidence")]
        rival = BoundingBox(*rv, t=t0 + tf) if all(v is not None for v in rv) else None  # type: ignore[arg-type, misc]
        out[tf] = BoundingBox(*vals, t=t0 + tf, rival=rival) if ok else None  # type: ignore[arg-type, misc]
    return out


def _inputs_logged(flight: Flight, boxes: dict[float, BoundingBox | None]) -> list[tuple[FrameInput, float | None]]:
    t0, out = float(flight.meta["t0_monotonic"]), []
    for r in flight["inputs"].rows():
        tf = _num(r["t_frame"])
        q = [_num(r[k]) for k in ("qw", "qx", "qy", "qz")]
        if tf is None or any(v is None for v in q):
            raise ValueError(f"{flight.folder}/inputs.csv: row at t={r['t']} has no frame time or attitude")
        acc = [_num(r[k]) for k in ("acc_f", "acc_r", "acc_d")]
        a = np.array(acc) if all(v is not None for v in acc) else None
        t_imu, t_now, conf = _num(r["t_imu"]), _num(r["t_now"]), _num(r["confirm"])
        inp = FrameInput(t0 + tf, boxes.get(tf), np.array(q), _num(r["baro_rel_m"]), accel_frd=a,
                         t_now=None if t_now is None else t0 + t_now,
                         imu=ImuReading(t0 + t_imu, a) if t_imu is not None and a is not None else None,
                         confirm=None if conf is None else bool(conf))
        out.append((inp, _num(r["hover_thrust"])))
    return out


def _inputs_from_telemetry(flight: Flight, boxes: dict[float, BoundingBox | None],
                           start: float) -> list[tuple[FrameInput, float | None]]:
    """An older log: the attitude at each frame slerped from telemetry.csv, its newest accelerometer row."""
    tel: Table = flight["telemetry"]
    t0 = float(flight.meta["t0_monotonic"])
    tt, ta = np.asarray(tel["t"], float), np.asarray(tel["t_att"], float)
    q = np.stack([np.asarray(tel[k], float) for k in ("qw", "qx", "qy", "qz")], 1)
    ok = np.isfinite(ta) & np.isfinite(q).all(1)
    if not ok.any():
        raise ValueError(f"{flight.folder}/telemetry.csv: no attitude to rerun from")
    ta, q = ta[ok], q[ok]
    _, first = np.unique(ta, return_index=True)
    att = AttitudeTrack(ta[first], q[first])
    acc = np.stack([np.asarray(tel[k], float) for k in ("acc_f", "acc_r", "acc_d")], 1)
    det = flight["detections"]
    # The frames the core stepped: from ACQUIRE on, but once it commanded only those with a logged setpoint (while
    # PX4 switched to OFFBOARD the app perceived frames without stepping the core: app/flight.py).
    sp_frames = [x for x in np.asarray(flight["setpoints"]["t_frame"], float) if math.isfinite(x)]
    first_sp, last_sp = (sp_frames[0], sp_frames[-1]) if sp_frames else (math.inf, math.inf)
    stepped = {round(x, 6) for x in sp_frames}
    out = []
    for t, tf in zip(np.asarray(det["t"], float), np.asarray(det["t_frame"], float), strict=True):
        if not (math.isfinite(t) and math.isfinite(tf)) or t < start:
            continue
        if first_sp < tf < last_sp and round(float(tf), 6) not in stepped:
            continue
        j = max(int(np.searchsorted(tt, t, side="right")) - 1, 0)
        a = acc[j] if np.isfinite(acc[j]).all() else None
        out.append((FrameInput(t0 + tf, boxes.get(float(tf)), att.at(float(tf)), None, accel_frd=a, t_now=t0 + t,
                               imu=ImuReading(t0 + tt[j], a) if a is not None else None), None))
    return out


def _hover0(flight: Flight) -> float | None:
    """The hover thrust the flight's core started from (summary.json; the autopilot's MPC_THR_HOVER)."""
    h = flight.summary.get("hover") if isinstance(flight.summary, dict) else None
    v = (((h or {}).get("preflight") or {}).get("hover_thrust") or {}).get("value") if isinstance(h, dict) else None
    return _num(v)


def _logged_changes(flight: Flight, shadow: bool) -> list[tuple[float, str]]:
    """The engagement's phase changes the log recorded, each at the capture time of the frame that made it: the
    frame whose detection row is the last written before the change (a loop logs the detection, steps the core,
    then writes the change, before it reads the next frame)."""
    core_phases = {"ENGAGE", "PASS", "RECOVER", "HANDBACK", "ABORT", "LAND"}
    if shadow:
        raw = []
        for r in flight["events"].rows():
            text = str(r["text"])
            if text.startswith("shadow: ") and " -> " in text.split(":")[1]:
                raw.append((float(r["t"]), text.split(" -> ")[1].split(":")[0]))
    else:
        # An ABORT of the core is named by the app's safe end (HANDBACK, SAFE_HOLD, ...): compare what both name.
        raw = [(float(r["t"]), r["to_state"]) for r in flight.states if r["to_state"] in core_phases]
    det = flight["detections"]
    t_w, t_f = np.asarray(det["t"], float), np.asarray(det["t_frame"], float)
    out = []
    for t, phase in raw:
        k = int(np.searchsorted(t_w, t, side="right")) - 1
        out.append((float(t_f[k]) if k >= 0 else t, phase))
    return out


def rerun(folder: str | Path, cfg: Any | None = None, rerender: bool = False) -> Rerun:
    """Step a fresh core (``cfg``, default: the flight's own config.json) over the flight's frames. ``rerender``: a
    rendered synthetic-camera flight's frames drawn again from its log and perceived again with ``cfg``
    (companion/logrender.py): the core gets those boxes, not the logged ones."""
    from companion.logclutter import config_of

    flight = read_flight(folder)
    for topic in ("detections", "setpoints"):
        if topic not in flight.tables:
            raise ValueError(f"{flight.folder}: no {topic}.csv: not a flight log this can rerun")
    if "t0_monotonic" not in flight.meta:
        raise ValueError(f"{flight.folder}/meta.json: no t0_monotonic")
    cfg = config_of(flight) if cfg is None else cfg
    boxes = _boxes(flight)
    shadow = any(s == "SHADOW" for s in flight["setpoints"]["state"]) if len(flight["setpoints"]) else False
    exact = "inputs" in flight.tables and len(flight["inputs"]) > 0
    if exact:
        inputs = _inputs_logged(flight, boxes)
    else:
        acq = [float(r["t"]) for r in flight.states if r["to_state"] == "ACQUIRE"]
        inputs = _inputs_from_telemetry(flight, boxes, acq[0] if acq else -math.inf)
    hover0 = next((h for _, h in inputs if h is not None), None) or _hover0(flight)
    core = FlightCore.from_config(cfg, hover_thrust=hover0)
    res = Rerun(Path(flight.folder), exact, logged_changes=_logged_changes(flight, shadow))
    t0, prev = float(flight.meta["t0_monotonic"]), None
    again = None
    if rerender:
        from companion.logrender import Rerendered

        again = Rerendered.of(flight, cfg)
    for inp, hover in inputs:
        if again is not None:
            inp = replace(inp, box=again.box(inp.t - t0, inp.q_wxyz_ned_frd))
        if hover is not None and core.phase.value == "ACQUIRE" and abs(hover - core.hover_thrust) > 1e-6:
            # Set by the app before its first setpoint (PX4's hover measured after take-off, app/hovercheck.py);
            # once the core commands, its own estimate rules, also under another config.
            use_hover_thrust(core.controller, hover, cfg.airframe.thrust_to_weight, core.engagement)
            if core.hover_estimator is not None:  # as the app does there: the estimate starts from it
                core.hover_estimator = HoverThrustEstimator(hover, cfg.hover)
        step = core.step(inp)
        d = step.decision
        if again is not None:
            step.tell_tracker(again.perception)  # as every loop does (drop a refused track, look past a candidate)
            again.decided(inp.t - t0, d.phase.value, d.events, core.engagement.used_box)
        sp = d.setpoint
        tf = inp.t - t0
        res.steps.append(Step(tf, d.phase.value, d.why, None if sp is None else
                              (sp.roll_deg, sp.pitch_deg, sp.yaw_deg, sp.thrust)))
        if d.phase is not prev:
            res.changes.append((tf, d.phase.value, d.why))
            prev = d.phase
        if d.phase.done:
            if not shadow:
                break
            core.restart()
            prev = None
    if again is not None:
        res.perception = again.summary()
    _compare(flight, res)
    return res


def _compare(flight: Flight, res: Rerun) -> None:
    """Each logged setpoint against the rerun's on the same frame."""
    withsp = [s for s in res.steps if s.setpoint is not None]
    ts = np.array([s.t_frame for s in withsp])
    sp = flight["setpoints"]
    for r in sp.rows():
        tf = _num(r["t_frame"])
        if tf is None:
            continue
        logged = tuple(_num(r[k]) for k in ("roll_deg", "pitch_deg", "yaw_deg", "thrust"))
        # the same frame: its time written with 9 significant digits
        k = int(np.argmin(np.abs(ts - tf))) if len(ts) else -1
        other = withsp[k].setpoint if k >= 0 and abs(ts[k] - tf) < 1e-5 else None
        if any(v is None for v in logged):
            continue
        res.compared += 1
        diff = math.inf if other is None else max(abs(a - b) for a, b in zip(logged, other, strict=True))  # type: ignore[operator]
        res.setpoint_diff = max(res.setpoint_diff, diff)
        if diff > SETPOINT_TOL and res.first_diff is None:
            res.first_diff = tf


def report(res: Rerun) -> str:
    """A few lines: how the rerun was made, whether it reproduces the log, its phase changes beside the log's (each
    at the capture time of the frame that made it)."""
    src = "inputs.csv" if res.exact else "telemetry.csv (approximate: the log predates inputs.csv)"
    lines = [f"{res.folder}: rerun from {src}"]
    if res.compared:
        same = res.first_diff is None
        big = ("a logged one has none in the rerun" if math.isinf(res.setpoint_diff)
               else f"largest difference {res.setpoint_diff:.3g}")
        lines.append(f"  setpoints: {res.compared} logged, " + (
            f"all reproduced (largest difference {res.setpoint_diff:.2g})" if same else
            f"the rerun's first differs at t_frame {res.first_diff:.3f} s ({big})"))
    # times: the capture time of the frame that made each change (flight-log clock)
    lines.append("  rerun:  " + "; ".join(f"{t:.3f} {p}" + (f" ({w[:70]})" if w else "") for t, p, w in res.changes))
    lines.append("  logged: " + "; ".join(f"{t:.3f} {p}" for t, p in res.logged_changes))
    if res.perception is not None:
        from companion.logrender import report_lines

        lines.extend(report_lines(res.perception))
    return "\n".join(lines)


def flight_folders(paths: list[str]) -> list[Path]:
    """Flight folders, or directories holding them (an eval's output), in order."""
    out: list[Path] = []
    for p in map(Path, paths):
        if (p / "detections.csv").exists() or not p.is_dir():
            out.append(p)
        else:
            found = sorted(f.parent for f in p.rglob("detections.csv"))
            out.extend(found if found else [p])
    return out


def register(lsub: Any) -> None:
    """``companion log rerun``."""
    rp = lsub.add_parser("rerun", help="step the flight core again on a log's frames (as flown, or with --set): "
                                       "does it reproduce the log, where would another config decide otherwise")
    rp.add_argument("folders", nargs="+", help="flight folders, or directories holding them (an eval's output)")
    rp.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="change the flight's config for the rerun (repeatable)")
    rp.add_argument("--rerender", action="store_true",
                    help="rendered synthetic-camera flights: draw the frames again from the log's truth and perceive "
                         "them again (with --set perception.*); the core gets those boxes (companion/logrender.py)")
    rp.set_defaults(func=_cmd)


def _cmd(args: argparse.Namespace) -> int:
    from companion.config import Config
    from companion.configbase import ConfigError, deep_merge, parse_override

    rc, n, same_sp, same_phases = 0, 0, 0, 0
    for folder in flight_folders(args.folders):
        try:
            flight = read_flight(folder)
            data = dict(flight.config)
            for ov in args.overrides:
                data = deep_merge(data, parse_override(ov))
            try:
                cfg = Config.model_validate(data)
            except ValueError as e:
                raise ValueError(f"{folder}/config.json with {' '.join(args.overrides) or 'no change'}: not a config "
                                 f"({str(e).splitlines()[0]})") from None
            res = rerun(folder, cfg, rerender=args.rerender)
        except (ValueError, FileNotFoundError, ConfigError, KeyError) as e:
            print(f"companion log rerun: {str(e).splitlines()[0]}", file=sys.stderr)
            rc = 2
            continue
        print(report(res))
        n += 1
        same_sp += res.compared > 0 and res.first_diff is None
        same_phases += same_path(res)
    if n > 1:
        print(f"{n} flights: {same_phases} with the logged phase changes, {same_sp} with every logged setpoint")
    return rc


ENDS = {"HANDBACK", "ABORT", "LAND"}  # the core's ends; the app names an ABORT by its safe end (often HANDBACK)


def same_path(res: Rerun, tol_s: float = 1e-4) -> bool:
    """The rerun made the log's phase changes, in order, each on the same frame (capture times within ``tol_s``);
    any end matches any end on the same frame (the app names a TARGET_LOST abort HANDBACK)."""
    def path(changes: list[tuple[float, str]]) -> list[tuple[float, str]]:
        out: list[tuple[float, str]] = []
        for t, p in changes:
            q = "end" if p in ENDS else p
            if q in ("end", "ENGAGE", "PASS", "RECOVER") and not (q == "end" and out and out[-1][1] == "end"):
                out.append((t, q))  # the app's HANDBACK then LAND is one end
        return out

    mine, logged = path([(t, p) for t, p, _ in res.changes]), path(res.logged_changes)
    return len(mine) == len(logged) and all(
        p == q and abs(t - u) <= tol_s for (t, p), (u, q) in zip(mine, logged, strict=True))
