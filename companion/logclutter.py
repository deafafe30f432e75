"""``companion log clutter FOLDER...``: was the box each engagement flew at the gate or clutter? From flight logs.

For synthetic-camera flights (PX4 SITL with ``app.camera: synthetic``, ``companion eval table1 --autopilot px4``):
each frame's true gate box is recomputed from the log, the way the synthetic camera drew it
(companion/app/synthcam.py ``SyntheticCamera._render``: perception/render.py ``gate_box`` through the camera as it
truly sits on the body, ``true_camera_config``), and the box the engagement used on that frame is judged against
it with the project's tally (companion/engagetally.py, as ``companion replay --labels`` and
tools/clutter_engagements.py do).

What each frame is made of, from the log alone:

* pose: position from ``truth.csv`` (SIH's truth, interpolated to the frame's capture time ``t_frame``), attitude
  from ``telemetry.csv`` (PX4's estimate at ``t_att``, slerped to ``t_frame``). The camera drew with SIH's true
  attitude, which the log does not keep: the estimate's error (a degree or so, ~8 px) is what ``margin`` absorbs;
* gate: the ``gate.csv`` row written by that frame's capture (the last one with ``visible`` before the frame's
  detection row), so a moving gate is where it was drawn;
* phase: ``setpoints.csv``'s state on that ``t_frame`` (no row: the core did not command, ACQUIRE or the switch to
  OFFBOARD); events (``gate N engaged``, ``gate N close``, ``intercept: pulled up``) go to the frame whose detection
  row precedes them (the app logs the detection, steps the core, then logs its events);
* used box: the detection (``valid``), minus what the app refused on the engaged frames (its target lock,
  companion/targetlock.py, or verification): read from ``los.csv`` (the controller given "no box" for a valid
  detection), or for older logs the lock re-run with the logged attitude. It is judged as perceived, before the
  engagement's completion of a box cut by the image border: the truth box is clipped to the image too.

A box is on the gate when its centre lies inside the true box grown by ``margin`` px on every side (engagetally's
rule with a tolerance for the reconstruction; docs/verification-px4.md says how the default was chosen). Such a box
more than twice the true box's size is also counted apart as *oversize* (engagetally's ``*_oversize``).
Frames within ``NEAR_RADII`` gate radii of the gate are not judged (the log's pose cannot place the box there), so
a pass claimed on one is engagetally's ``passes_claimed_unlabelled``: here that means *claimed at the gate*, not
elsewhere (on the 2026-12-07 SIH table 83 of 99 claims; ``passes_claimed_wrong`` judges the other 16).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.attitude import AttitudeTrack
from companion.engagetally import EngagementTally, total
from companion.flightlog import Flight, Table, flight_crossings, read_flight
from companion.frames import F_FRD_FLU, R_enu_flu_from_ned_frd, R_from_quat_wxyz, ned_to_enu
from companion.sim.camera import true_camera_config
from perception.los import CameraModel
from perception.render import Gate, PinholeCamera, gate_box
from perception.types import BoundingBox

MARGIN_PX = 24.0  # px (~3 deg): docs/verification-px4.md (the least margin that clears x500's good runs, doubled)
SEARCH_PX = 48.0  # px (~6 deg): PX4's heading error on SIH, which old logs cannot undo otherwise
NEAR_RADII = 1.5  # gate radii: nearer, frames are not judged (docs/verification-px4.md)
MIN_SPELL = 5  # frames of the gate in view that count as a chance to engage (engagetally's default)


@dataclass
class FrameRow:
    """One perceived frame of a flight log, with its truth."""

    t: float  # capture time (flight-log clock)
    box: BoundingBox | None  # the perceived box when valid
    phase: str  # the core's phase after this frame ("" when the core did not command)
    events: tuple[str, ...]
    truth: BoundingBox | None  # the gate's true image box (None: not in view)
    q: np.ndarray  # PX4's attitude estimate at t (NED/FRD wxyz), what the app's lock used
    used: BoundingBox | None = None  # the box the engagement used (after the target lock)
    judged: bool = True  # False: too near the gate for the log's pose to place its box (neither right nor wrong)
    refused: bool | None = None  # the app passed its controller no box for this valid one (los.csv "no box")
    # What the camera drew this frame from (companion/logrender.py draws it again): the vehicle's position NED and
    # attitude (NED/FRD wxyz) at capture as the log has them, the gate drawn (centre NED, normal NED, radius m;
    # None: no gate in front). pose None: the log has no position then.
    pose: tuple[np.ndarray, np.ndarray] | None = None
    drawn: tuple[np.ndarray, np.ndarray, float] | None = None


def truth_box(cfg: Any, p_ned: np.ndarray, q_wxyz: np.ndarray, centre_ned: np.ndarray, normal_ned: np.ndarray,
              radius: float, t: float = 0.0) -> BoundingBox | None:
    """The gate's box as the synthetic camera draws it (companion/app/synthcam.py ``_render``): NED pose and
    gate -> the scene's ENU, the camera as it truly sits (``sim.camera.mount_error``), perception's ``gate_box``."""
    cam_cfg = true_camera_config(cfg)
    model = CameraModel.from_config(cam_cfg)
    R_enu_cam = R_enu_flu_from_ned_frd(R_from_quat_wxyz(q_wxyz)) @ F_FRD_FLU @ model.R_body_cam
    gate = Gate(ned_to_enu(np.asarray(centre_ned, float)), ned_to_enu(np.asarray(normal_ned, float)), float(radius))
    return gate_box(PinholeCamera.from_config(cam_cfg), R_enu_cam, ned_to_enu(np.asarray(p_ned, float)), gate, t)


class NoFrames(ValueError):
    """A flight log without the rows to judge (e.g. the camera failed before its first frame)."""


def _need(flight: Flight, *topics: str) -> None:
    missing = [t for t in topics if t not in flight.tables or len(flight.tables[t]) == 0]
    if missing:
        raise NoFrames(f"{flight.folder}: no {', '.join(missing)} rows (a synthetic-camera flight log is needed)")


def has_true_attitude(truth: Table) -> bool:
    """truth.csv carries the simulator's attitude (logs from 2026-12-02 on; SIH's HIL_STATE_QUATERNION)."""
    return "qw" in truth.columns and "t_truth" in truth.columns and bool(np.isfinite(truth["qw"]).any())


def _attitude(tel: Table) -> AttitudeTrack:
    return _attitude_of(tel, "t_att" if "t_att" in tel.columns else "t")


def _attitude_of(tel: Table, tcol: str) -> AttitudeTrack:
    t = tel[tcol]
    q = np.column_stack([tel[k] for k in ("qw", "qx", "qy", "qz")]).astype(float)
    ok = np.isfinite(t) & np.isfinite(q).all(axis=1)
    t, q = t[ok], q[ok]
    t, keep = np.unique(t, return_index=True)
    if len(t) == 0:
        raise ValueError(f"no attitude samples ({tcol}, qw, qx, qy, qz)")
    q = q[keep]
    return AttitudeTrack(t, q / np.linalg.norm(q, axis=1, keepdims=True))


def frames_of(flight: Flight, cfg: Any) -> list[FrameRow]:
    """Every perceived frame of a synthetic-camera flight log with its phase, events, box and true gate box."""
    _need(flight, "detections", "truth", "telemetry", "gate")
    det, tr, gate = flight["detections"], flight["truth"], flight["gate"]
    att = _attitude(flight["telemetry"])  # what the app's lock used
    true_att = has_true_attitude(tr)
    draw_att = _attitude_of(tr, "t_truth") if true_att else att  # what the camera drew with (best the log has)
    trt = tr["t_truth"] if true_att else tr["t"]  # the sample's own time where logged
    okt = np.isfinite(trt)
    trt, trp = trt[okt], np.column_stack([tr[k][okt] for k in ("n", "e", "d")])
    phase_at: dict[float, str] = {}
    if "setpoints" in flight.tables:
        sp = flight["setpoints"]
        phase_at = {float(tf): str(s) for tf, s in zip(sp["t_frame"], sp["state"], strict=True)}
    ev_t: list[float] = []
    ev_text: list[str] = []
    if "events" in flight.tables:
        ev = flight["events"]
        ev_t, ev_text = [float(x) for x in ev["t"]], [str(x) for x in ev["text"]]
    refused_at: dict[float, bool] = {}
    if "los" in flight.tables and "rejected" in flight["los"].columns:
        lo = flight["los"]
        refused_at = {float(tf): str(why) == "no box" for tf, why in zip(lo["t_frame"], lo["rejected"], strict=True)}
    vis = gate["visible"] if "visible" in gate.columns else np.ones(len(gate))
    n_gates = max(1, len(set(gate["k"].tolist()))) if "k" in gate.columns else 1
    gt = gate["t"]
    det_t = det["t"]
    rows: list[FrameRow] = []
    for i in range(len(det)):
        tf = float(det["t_frame"][i])
        if not math.isfinite(tf):
            continue
        box = None
        if det["valid"][i] > 0:
            box = BoundingBox(float(det["cx"][i]), float(det["cy"][i]), float(det["w"][i]), float(det["h"][i]),
                              float(det["confidence"][i]), tf)
        t_next = float(det_t[i + 1]) if i + 1 < len(det) else math.inf
        events = tuple(x for te, x in zip(ev_t, ev_text, strict=True) if det_t[i] <= te < t_next
                       and (x.endswith(" engaged") or x.endswith(" close") or x.endswith("intercept: pulled up")))
        truth, judged, drawn = None, True, None
        q, q_drawn = att.at(tf), draw_att.at(tf)
        # The gate rows this frame's capture wrote (one per gate, just before its detection row): the one drawn.
        last = int(np.searchsorted(gt, det_t[i], side="right"))
        mine = range(max(0, last - n_gates), last)
        p = np.array([np.interp(tf, trt, trp[:, c]) for c in range(3)]) if len(trt) else np.full(3, np.nan)
        for j in mine:
            c = np.array([gate["gate_n"][j], gate["gate_e"][j], gate["gate_d"][j]], float)
            n = np.array([gate["normal_n"][j], gate["normal_e"][j], gate["normal_d"][j]], float)
            radius = float(gate["radius"][j])
            if not (np.isfinite(c).all() and np.isfinite(n).all() and np.isfinite(p).all()):
                continue
            # In the ring (range < NEAR_RADII radii) a 20 ms stamp or a degree moves the rim across the image:
            # the frame can be judged neither way.
            judged &= bool(np.linalg.norm(p - c) >= NEAR_RADII * radius)
            if vis[j] > 0:
                truth = truth_box(cfg, p, q_drawn, c, n, radius, tf)
                drawn = (c, n, radius)
        refused = refused_at.get(tf) if box is not None else None
        pose = (p, q_drawn) if np.isfinite(p).all() else None
        rows.append(FrameRow(tf, box, phase_at.get(tf, ""), events, truth, q, judged=judged, refused=refused,
                             pose=pose, drawn=drawn))
    return rows


def apply_lock(rows: list[FrameRow], cfg: Any) -> int:
    """Set each row's used box: the perceived one, except on ENGAGE frames the app refused it (its target lock
    or verification). The app's own decision where the log has it (los.csv: the controller was given no box for
    a valid detection); for older logs the lock is re-run as companion/engagement.py runs it, on the box it
    sees (completed when cut by the border), without the closing-speed filter those logs do not keep (its
    v_max bound). Returns the rejections."""
    if any(r.refused is not None for r in rows):
        n = 0
        for r in rows:
            r.used = None if r.refused and r.phase == "ENGAGE" else r.box
            n += r.used is None and r.box is not None
        return n
    from companion.engagement import EngagementParams, complete_clipped_box
    from companion.targetlock import TargetLock

    p = EngagementParams.from_config(cfg)
    lock = None
    if cfg.app.target_lock:  # as Engagement.from_config builds it
        lock = TargetLock.from_config(cfg, CameraModel.from_config(cfg.camera))
    rejected = 0
    for r in rows:
        r.used = r.box
        if lock is None or r.box is None:
            continue
        seen = r.box
        if p.complete_boxes:
            whole = complete_clipped_box(seen, p.width, p.height, p.cut_edge_px)
            seen = whole if whole.is_valid(p.width, p.height) else seen
        R = R_from_quat_wxyz(r.q)
        if any(e.endswith(" engaged") for e in r.events):
            lock.reset()
            lock.check(r.t, seen, R)  # the engaged box is the first reference
        elif r.phase == "ENGAGE" and not lock.check(r.t, seen, R).ok:
            r.used = None
            rejected += 1
    return rejected


def attitude_offset(rows: list[FrameRow], search: float = SEARCH_PX) -> tuple[float, float, int]:
    """The constant pixel offset (dx, dy, frames) of the perceived boxes from the true ones, the median over the
    frames whose box centre lies within ``search`` px of the true box: an old PX4 log's stand-in for SIH's
    attitude, which it did not keep (PX4's heading estimate is a few degrees off for a whole flight). A box
    farther off (clutter) neither counts nor can be pulled onto the gate by more than ``search``."""
    d = [(r.box.cx - r.truth.cx, r.box.cy - r.truth.cy) for r in rows if r.box is not None and r.truth is not None
         and not EngagementTally._wrong(r.box, grown(r.truth, search))]
    if len(d) < MIN_SPELL:
        return 0.0, 0.0, len(d)
    m = np.median(np.array(d), axis=0)
    return float(m[0]), float(m[1]), len(d)


def shift_truth(rows: list[FrameRow], dx: float, dy: float) -> None:
    for r in rows:
        if r.truth is not None:
            r.truth = BoundingBox(r.truth.cx + dx, r.truth.cy + dy, r.truth.w, r.truth.h, r.truth.confidence,
                                  r.truth.t)


def grown(b: BoundingBox | None, margin: float) -> np.ndarray:
    """The true box grown by ``margin`` px on every side, as engagetally's labelled boxes (none: no rows)."""
    if b is None:
        return np.zeros((0, 4))
    x0, y0, x1, y1 = b.xyxy
    return np.array([[x0 - margin, y0 - margin, x1 + margin, y1 + margin]])


def iou(a: BoundingBox, b: BoundingBox) -> float:
    ax0, ay0, ax1, ay1 = a.xyxy
    bx0, by0, bx1, by1 = b.xyxy
    iw, ih = max(0.0, min(ax1, bx1) - max(ax0, bx0)), max(0.0, min(ay1, by1) - max(ay0, by0))
    u = a.w * a.h + b.w * b.h - iw * ih
    return iw * ih / u if u > 0 else 0.0


def tally_rows(rows: list[FrameRow], margin: float = MARGIN_PX, min_spell: int = MIN_SPELL) -> dict[str, Any]:
    """engagetally's counts over a flight's frames (truth boxes grown by ``margin``), plus the distribution of
    the engaged boxes' error against the truth (IoU, centre distance px) on the frames judged on the gate."""
    tally = EngagementTally(min_spell=min_spell, grown=margin)
    ious, dists = [], []
    closes: list[tuple[float, bool]] = []  # (t, judged wrong) of each pass claim, as the tally judges it
    last: tuple[BoundingBox, np.ndarray | None] | None = None
    for r in rows:
        gts = grown(r.truth, margin) if r.judged else None
        if r.phase == "ENGAGE" and r.used is not None:
            last = (r.used, gts)
        if any(e.endswith(" close") or e.endswith("intercept: pulled up") for e in r.events):
            b, g = (r.used, gts) if r.used is not None else (last or (None, None))
            closes.append((r.t, bool(EngagementTally._wrong(b, g))))
        tally.add(r.phase, r.events, r.used, gts)
        if r.phase == "ENGAGE" and r.used is not None and r.truth is not None and r.judged:
            d = math.hypot(r.used.cx - r.truth.cx, r.used.cy - r.truth.cy)
            if not tally._wrong(r.used, grown(r.truth, margin)):
                ious.append(iou(r.used, r.truth))
                dists.append(d)
    out = tally.finish()
    out["closes"] = closes
    out["engaged_on_gate_iou"] = [round(x, 4) for x in ious]
    out["engaged_on_gate_centre_px"] = [round(x, 2) for x in dists]
    return out


def config_of(flight: Flight) -> Any:
    from companion.config import Config

    try:
        return Config.model_validate(flight.config)
    except ValueError as e:
        raise ValueError(f"{flight.folder}/config.json: not a config ({str(e).splitlines()[0]})") from None


def clutter_of(folder: str | Path, margin: float = MARGIN_PX) -> dict[str, Any]:
    """One flight folder: its tally, the lock's rejections, and the ground truth's verdict (summary.json)."""
    flight = read_flight(folder)
    cfg = config_of(flight)
    if cfg.app.camera != "synthetic" or cfg.app.synthetic.render != "image":
        raise ValueError(f"{folder}: not a rendered synthetic-camera flight (app.camera {cfg.app.camera!r}, "
                         f"app.synthetic.render {cfg.app.synthetic.render!r})")
    rows = frames_of(flight, cfg)
    rejected = apply_lock(rows, cfg)
    if has_true_attitude(flight["truth"]):
        d_att = "simulator truth"
    elif isinstance(flight.summary.get("px4"), dict):
        # Real PX4 SITL before truth.csv kept SIH's attitude: the camera drew with SIH's, the log has EKF2's.
        dx, dy, n = attitude_offset(rows)
        shift_truth(rows, dx, dy)
        d_att = f"PX4 estimate, offset ({dx:.1f}, {dy:.1f}) px from {n} frames"
    else:
        d_att = "PX4 estimate (the truth source's attitude: the camera drew with it)"
    d = tally_rows(rows, margin, cfg.app.acquire_frames)
    d["lock_rejected"] = rejected
    # A claim on clutter after the vehicle had already crossed the gate's plane (it flew through unaware, then
    # took clutter for the gate) is another failure than one that steered it away from the gate.
    t_cross = [c.t for c in flight_crossings(flight)]
    d["passes_claimed_wrong_after_crossing"] = sum(w and any(tc < tq for tc in t_cross) for tq, w in d.pop("closes"))
    d["engaged_after_crossing_s"] = engaged_after_crossing(rows, t_cross)
    d["attitude"] = d_att
    tr = flight.summary.get("truth") if isinstance(flight.summary, dict) else None
    d["through"] = bool(tr.get("through")) if isinstance(tr, dict) else None
    d["outcome"] = f"{flight.summary.get('outcome', '?')} {flight.summary.get('reason', '')}".strip()
    d["folder"] = str(folder)
    return d


LATE_S = 0.2  # s in ENGAGE after the crossing worth a line (a frame or two of a box is the detector's lag)


def engaged_after_crossing(rows: list[FrameRow], t_cross: list[float]) -> float | None:
    """Seconds the vehicle was still in ENGAGE (PN steering at whatever box it had) after it first crossed the
    gate's plane: from the crossing to the last ENGAGE frame after it; 0.0 when it left ENGAGE before; None when
    it never crossed. On PX4's SIH quad (2026-12-06) the detector's boxes after a crossing were the ring's last
    sliver and then background boxes ~2 m "away" that neither grew nor shrank, and the app steered at them for up
    to 1.3 s before it claimed the pass: the pass was true, the flight after it was not at the gate."""
    if not t_cross:
        return None
    t_c = t_cross[0]
    after = [r.t for r in rows if r.phase == "ENGAGE" and r.t > t_c]
    return round(max(after) - t_c, 3) if after else 0.0


def flight_folders(paths: list[str]) -> list[Path]:
    """Finished flight folders (with summary.json) under each path, in name order; a path that is one counts."""
    out: list[Path] = []
    for s in paths:
        p = Path(s)
        if not p.exists():
            raise ValueError(f"{p}: no such file or directory")
        if (p / "summary.json").is_file():
            out.append(p)
            continue
        out += sorted(q.parent for q in p.rglob("summary.json") if (q.parent / "detections.csv").is_file())
    return out


def _wrong(d: dict[str, Any]) -> bool:
    return bool(d["begun_on_wrong"] or d["engaged_frames_wrong"] or d["passes_claimed_wrong"])


def _oversize(d: dict[str, Any]) -> bool:
    return bool(d["begun_oversize"] or d["engaged_frames_oversize"] or d["passes_claimed_oversize"])


def report(paths: list[str], margin: float = MARGIN_PX,
           skipped: list[str] | None = None) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Every flight under ``paths`` judged, and the totals. Among several flights, one without frames to judge
    (its camera failed before the first frame, say) is left out with its reason in ``skipped`` (counted as
    ``runs_without_frames``) rather than ending the report; a single flight folder without them is an error."""
    folders = flight_folders(paths)
    per: list[dict[str, Any]] = []
    reasons: list[str] = []
    for f in folders:
        try:
            per.append(clutter_of(f, margin))
        except NoFrames as e:
            if len(folders) == 1:
                raise
            reasons.append(str(e))
    if skipped is not None:
        skipped += reasons
    tot = total([{k: v for k, v in d.items() if k not in ("through",)} for d in per])
    for k in ("engaged_on_gate_iou", "engaged_on_gate_centre_px"):
        tot.pop(k, None)
    ious = np.array([x for d in per for x in d["engaged_on_gate_iou"]])
    dists = np.array([x for d in per for x in d["engaged_on_gate_centre_px"]])
    q = (5, 50, 95, 99)
    tot["runs"] = len(per)
    tot["runs_without_frames"] = len(reasons)
    tot["runs_through"] = sum(bool(d["through"]) for d in per)
    tot["runs_with_wrong"] = sum(_wrong(d) for d in per)
    tot["runs_with_oversize"] = sum(_oversize(d) for d in per)
    tot["margin_px"] = margin
    late = np.array([d["engaged_after_crossing_s"] for d in per if d.get("engaged_after_crossing_s") is not None])
    tot["runs_crossed"] = len(late)
    tot["runs_engaged_over_0.2s_after_crossing"] = int((late > LATE_S).sum())
    tot["engaged_after_crossing_s_p50_95_max"] = ([round(float(x), 2) for x in (*np.percentile(late, (50, 95)),
                                                                                late.max())] if len(late) else None)
    tot["on_gate_iou_p5_50_95_99"] = [round(float(x), 3) for x in np.percentile(ious, q)] if len(ious) else None
    tot["on_gate_centre_px_p5_50_95_99"] = ([round(float(x), 1) for x in np.percentile(dists, q)]
                                            if len(dists) else None)
    return per, tot


def run_line(d: dict[str, Any]) -> str:
    through = {True: "through", False: "missed", None: "no truth verdict"}[d["through"]]
    return (f"{d['folder']}: {through}, {d['outcome']}; engagements {d['engagements']}, begun on wrong "
            f"{d['begun_on_wrong']}, frames on wrong {d['engaged_frames_wrong']}/{d['engaged_frames']}, passes "
            f"claimed on wrong {d['passes_claimed_wrong']}/{d['passes_claimed']}, never engaged while gate in view "
            f"{d['never_engaged_spells']}, lock rejected {d['lock_rejected']}"
            + (f" (claimed on wrong after crossing the gate's plane: {d['passes_claimed_wrong_after_crossing']})"
               if d["passes_claimed_wrong"] else "")
            + (f"; on the gate but over {EngagementTally.size_ratio:g}x its size: begun {d['begun_oversize']}, frames "
               f"{d['engaged_frames_oversize']}, passes claimed {d['passes_claimed_oversize']}" if _oversize(d) else "")
            + (f"; engaged {late:.2f} s after crossing the gate's plane"
               if (late := d.get("engaged_after_crossing_s")) else ""))


def register(lsub: Any) -> None:
    """``companion log clutter``."""
    cp = lsub.add_parser("clutter", help="per run: did the engagement fly at the gate or at clutter (synthetic-camera "
                                         "logs, judged against the simulator's truth)")
    cp.add_argument("folders", nargs="+", help="flight folders, or directories holding them (an eval's output)")
    cp.add_argument("--margin", type=float, default=MARGIN_PX,
                    help=f"px the true box is grown by before a box's centre must fall in it (default {MARGIN_PX})")
    cp.add_argument("--all", action="store_true", help="a line for every run, not only those engaging clutter")
    cp.add_argument("--json", action="store_true", help="per-run tallies too, as JSON")
    cp.set_defaults(func=_cmd)


def _cmd(args: argparse.Namespace) -> int:
    skipped: list[str] = []
    try:
        per, tot = report(args.folders, args.margin, skipped)
    except (FileNotFoundError, ValueError) as e:
        print(f"companion log clutter: {e}", file=sys.stderr)
        return 2
    for why in skipped:
        print(f"companion log clutter: left out: {why}", file=sys.stderr)
    if not per:
        print(f"companion log clutter: no finished flight folder (summary.json) under {' '.join(args.folders)}",
              file=sys.stderr)
        return 2
    for d in per:
        if args.all or _wrong(d) or _oversize(d) or (d.get("engaged_after_crossing_s") or 0.0) > LATE_S:
            print(run_line(d))
    out: dict[str, Any] = {"total": tot}
    if args.json:
        out["runs"] = [{k: v for k, v in d.items() if not k.startswith("engaged_on_gate_")} for d in per]
    print(json.dumps(out, indent=1))
    return 0
