"""``companion replay VIDEO [--log FLIGHT_LOG] [--out DIR]``: perception + LOS + controller over a recorded video.

What the app would have done on each frame: detector + tracker (perception.pipeline) -> box ->
LOS (perception.los, attitude at the frame time) -> PNController -> commanded attitude and thrust;
and the app's engagement core (companion/engagement.py) on the same boxes: its phase (ACQUIRE,
ENGAGE, PASS, RECOVER, ...), the setpoint the app would have sent and its gate events (columns
``state``, ``app_*``; ``summary.json`` ``engagement``).
Writes ``DIR/annotated.mp4`` (box, raw detections, LOS, commanded attitude and thrust),
``DIR/replay.csv`` (one row per frame) and ``DIR/replay.png`` (plots), with a progress bar.

Attitude: with ``--log``, from a flight log, interpolated (slerp) at each frame's time:
  * a flight folder (companion.flightlog): ``telemetry.csv`` (t, qw, qx, qy, qz, ...); frame k's
    time is the ``t_frame`` of ``detections.csv``'s row with ``frame == k`` when recorded, else
    ``--t0 + k / fps``;
  * a CSV file with a header containing t, qw, qx, qy, qz (scalar-first, body FRD -> world NED);
  * a JSON-lines file, one object per line with the same keys.
Without ``--log`` the attitude is level, heading north (q = 1, 0, 0, 0), frame k at ``k / fps``.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import Config, add_config_arguments, config_from_args
from companion.recording import (
    RecordingReader,
    ReplayError,
    frame_time,
    is_recording,
    level_attitude,
    load_attitude,
)

CSV_COLUMNS = (
    "frame", "t", "box", "cx", "cy", "w", "h", "confidence", "los_raw_n", "los_raw_e", "los_raw_d",
    "los_n", "los_e", "los_d", "mode", "rejected", "roll_deg", "pitch_deg", "yaw_deg", "thrust",
    "qw", "qx", "qy", "qz",
    # The engagement core (companion/engagement.py), as the app runs it on these frames: its phase, the
    # setpoint the app would have sent (blank while acquiring: PX4 holds) and its events.
    "state", "app_roll_deg", "app_pitch_deg", "app_yaw_deg", "app_thrust", "app_event",
    "engagement",  # the engagement this frame belongs to (1, 2, ...: replay restarts the core after each end)
)


def _load_labels(seq: str | Path | None) -> list[np.ndarray | None]:
    """Per frame (k-th image of SEQ/images by name): its labelled gate boxes (xyxy px), None when unlabelled."""
    if seq is None:
        return []
    from perception.evaluate import _load_folder

    p = Path(seq)
    if not (p / "images").is_dir():
        raise ReplayError(f"{p}: --labels needs a sequence folder with images/ and labels/")
    return [fr.boxes for fr in _load_folder(p, keep_unlabelled=True)]


def _project_ned(model: Any, los_ned: np.ndarray, R_ned_frd: np.ndarray) -> tuple[float, float] | None:
    return model.project_body(R_ned_frd.T @ los_ned)


def replay(
    video: str | Path, cfg: Config, log: str | Path | None = None, out: str | Path | None = None,
    t0: float = 0.0, progress: bool = True, max_frames: int = 0, record: str | Path | None = None,
    record_kw: dict[str, Any] | None = None, labels: str | Path | None = None,
) -> dict[str, Any]:
    """Run the replay; returns a summary (frames, boxes, output paths, pipeline stats, every engagement).

    ``labels``: a sequence folder of ``companion perception eval``'s layout (images/ + labels/, frame k of the
    video = the k-th image by name) to judge each engagement against (companion/engagetally.py)."""
    import cv2
    from tqdm import tqdm

    from companion.app.record import Recorder
    from companion.controller import PNController
    from companion.core import FlightCore, FrameInput
    from companion.engagetally import EngagementTally
    from companion.frames import R_from_quat_wxyz
    from perception.los import CameraModel, los_world
    from perception.pipeline import Pipeline

    video = Path(video)
    recording = RecordingReader(video) if is_recording(video) else None  # a `--record` folder: frames + index
    if recording is None and not video.is_file():
        raise ReplayError(f"{video}: video file not found")
    cap = recording if recording is not None else cv2.VideoCapture(str(video))
    if not cap.isOpened():
        raise ReplayError(f"{video}: cannot open as a video")
    fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    fps = fps if 0 < fps < 1000 else float(cfg.camera.rate)
    n_total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
    w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    if (w, h) != (cfg.camera.width, cfg.camera.height):
        cap.release()
        raise ReplayError(
            f"{video}: frames are {w}x{h} but camera.width x camera.height is "
            f"{cfg.camera.width}x{cfg.camera.height} (the intrinsics must match the video)"
        )
    track = load_attitude(log) if log is not None else None
    attitude_from = str(log) if log is not None else "level"
    if track is None and recording is not None:
        track = recording.attitude()  # the attitude recorded with each frame
        attitude_from = f"{video} (recorded with the frames)" if track is not None else "level"
    track = track or level_attitude()
    out_dir = Path(out) if out is not None else video.with_name(video.stem + "_replay")
    out_dir.mkdir(parents=True, exist_ok=True)
    model = CameraModel.from_config(cfg.camera)
    # Recorded frames of a real camera unless the config says they were rendered (app.camera: synthetic).
    pipe = Pipeline.from_config(cfg, real_frames=cfg.app.camera == "source")
    ctrl = PNController.from_config(cfg)  # the controller alone on every frame (what this frame's box asks for)
    core = FlightCore.from_config(cfg)  # the app's decisions (its own controller)
    ended = ""
    gts = _load_labels(labels)
    tally = EngagementTally(min_spell=cfg.app.acquire_frames)
    ends: list[str] = []
    engagement_no = 1
    passes_all: list[dict[str, Any]] = []
    last: tuple[str, list[Any]] = ("ACQUIRE", [])  # the last ended engagement (the summary's "engagement")
    writer = cv2.VideoWriter(str(out_dir / "annotated.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    if not writer.isOpened():
        cap.release()
        raise ReplayError(f"{out_dir / 'annotated.mp4'}: cannot write video")
    rec = Recorder(record, **(record_kw or {}), blocking=True, meta={"camera": cfg.model_dump(mode="json")["camera"],
                                                      "source": str(video)}) if record else None
    rows: list[dict[str, Any]] = []
    bar = tqdm(total=n_total or None, unit="frame", desc=f"replay {video.name}", disable=not progress)
    k = 0
    try:
        while True:
            ok, frame = cap.read()
            if not ok or (max_frames and k >= max_frames):
                break
            # By camera frame number (a video's frame k is the camera's k + 1): the time it was taken.
            t = frame_time(track, recording.frame_no if recording is not None else k + 1, k, t0, fps)
            q = track.at(t)
            R = R_from_quat_wxyz(q)
            if rec is not None:
                rec.add(k, t, frame, q)
            box = pipe.process(frame, t, R)  # a level track (no attitude recorded) moves nothing
            co = ctrl.step(t, box, q)
            # No barometer, accelerometer or processing time in a video: the altitude floor is not checked, the
            # closing speed runs on its prior, frames have no age.
            step = core.step(FrameInput(t, box, q))
            d = step.decision
            step.tell_tracker(pipe)  # as the flight does
            end_name = ""
            if d.changed and d.phase.done:
                ended = f"{d.phase.value} ({d.reason.name if d.reason else ''}): {d.why}"
                end_name = f"{d.phase.value} {d.reason.name if d.reason else ''}".strip()
            # Judged: the box the engagement used (a box it rejected as not the target is none).
            tally.add(d.phase.value, d.events, core.engagement.used_box, gts[k] if k < len(gts) else None, end_name)
            asp = d.setpoint
            raw = los_world(model, box.cx, box.cy, R) if box is not None else None
            sp = co.setpoint
            row = {
                "frame": k, "t": t, "box": int(box is not None),
                "cx": box.cx if box else "", "cy": box.cy if box else "", "w": box.w if box else "",
                "h": box.h if box else "", "confidence": box.confidence if box else "",
                "los_raw_n": raw[0] if raw is not None else "", "los_raw_e": raw[1] if raw is not None else "",
                "los_raw_d": raw[2] if raw is not None else "",
                "los_n": co.los_ned[0] if co.los_ned is not None else "",
                "los_e": co.los_ned[1] if co.los_ned is not None else "",
                "los_d": co.los_ned[2] if co.los_ned is not None else "",
                "mode": co.mode, "rejected": co.rejected or "",
                "roll_deg": sp.roll_deg, "pitch_deg": sp.pitch_deg, "yaw_deg": sp.yaw_deg, "thrust": sp.thrust,
                "qw": q[0], "qx": q[1], "qy": q[2], "qz": q[3],
                "state": d.phase.value, "app_roll_deg": asp.roll_deg if asp else "",
                "app_pitch_deg": asp.pitch_deg if asp else "", "app_yaw_deg": asp.yaw_deg if asp else "",
                "app_thrust": asp.thrust if asp else "",
                "app_event": "; ".join([*d.events, d.why] if d.why else d.events),
                "engagement": engagement_no,
            }
            rows.append(row)
            writer.write(_annotate(frame, pipe.last_detections, box, co, model, R, d.phase.value))
            if end_name:
                # Every engagement of the video is measured: after an end the app would be started again (as
                # shadow mode does), with a fresh engagement and tracker.
                ends.append(ended)
                passes_all += [{"engagement": engagement_no, **g.as_dict()} for g in core.engagement.passes]
                last = (d.phase.value, list(core.engagement.passes))
                core.restart()
                pipe.reset()
                engagement_no += 1
            k += 1
            bar.update(1)
    finally:
        bar.close()
        cap.release()
        writer.release()
        if rec is not None:
            rec.close()
    unread = recording.problems() if recording is not None else ""
    if not rows:
        raise ReplayError(f"{video}: no frames could be read" + (f" ({unread})" if unread else ""))
    if unread:  # replay goes on over the rest; the count is on stderr and in summary.json
        import sys

        print(f"companion replay: warning: {video}: {unread}", file=sys.stderr)
    with open(out_dir / "replay.csv", "w", newline="", encoding="utf-8") as f:
        wr = csv.DictWriter(f, fieldnames=CSV_COLUMNS, lineterminator="\n")
        wr.writeheader()
        wr.writerows(rows)
    _plot(rows, out_dir / "replay.png", video.name)
    summary = {
        "video": str(video), "frames": len(rows), "fps": fps, "boxes": sum(r["box"] for r in rows),
        "attitude": attitude_from, "out": str(out_dir),
        "unreadable": {"frames": recording.unreadable, "torn_index_row": recording.torn} if recording else None,
        # The running engagement at the end of the video, else the last one that ended.
        "engagement": {"state": core.phase.value if core.engagement.passes or not ends else last[0], "end": ended,
                       "passes": [g.as_dict() for g in (core.engagement.passes or last[1])]},
        "engagements": {**tally.finish(), "ends_in_order": ends,
                        "passes": passes_all + [{"engagement": engagement_no, **g.as_dict()}
                                                for g in core.engagement.passes],
                        "labels": str(labels) if labels else None},
        "annotated": str(out_dir / "annotated.mp4"), "csv": str(out_dir / "replay.csv"),
        "plot": str(out_dir / "replay.png"), "pipeline": pipe.stats.summary(), "model": str(pipe.det.path),
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def _annotate(frame: np.ndarray, dets: list, box: Any, co: Any, model: Any, R: np.ndarray,
              state: str = "") -> np.ndarray:
    import cv2

    img = frame.copy()
    for d in dets:  # raw detections: thin grey
        x0, y0, x1, y1 = (round(v) for v in d.xyxy)
        cv2.rectangle(img, (x0, y0), (x1, y1), (160, 160, 160), 1)
    if box is not None:  # the tracked, smoothed box that feeds the LOS
        x0, y0, x1, y1 = (round(v) for v in box.xyxy)
        cv2.rectangle(img, (x0, y0), (x1, y1), (0, 255, 0), 2)
        cv2.putText(img, f"{box.confidence:.2f}", (x0, max(12, y0 - 4)), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                    (0, 255, 0), 1, cv2.LINE_AA)
    if co.los_ned is not None:  # filtered LOS, projected back into the image
        uv = _project_ned(model, np.asarray(co.los_ned), R)
        if uv is not None and abs(uv[0]) < 1e5 and abs(uv[1]) < 1e5:
            u, v = round(uv[0]), round(uv[1])
            cv2.drawMarker(img, (u, v), (0, 0, 255), cv2.MARKER_CROSS, 18, 2)
    sp = co.setpoint
    lines = [
        f"t {co.t:7.3f}s  mode {co.mode}" + (f"  ({co.rejected})" if co.rejected else ""),
        f"roll {sp.roll_deg:+6.1f}  pitch {sp.pitch_deg:+6.1f}  yaw {sp.yaw_deg:+7.1f} deg",
        f"thrust {sp.thrust:.3f}  |lambda_dot| {co.lambda_dot:.3f} rad/s",
        f"engagement: {state}",
    ]
    panel = img[0:8 + 18 * len(lines), 0:420]
    panel[:] = (panel * 0.35).astype(np.uint8)  # darkened panel: text readable on any background
    for i, s in enumerate(lines):
        cv2.putText(img, s, (8, 18 + 18 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    hh = img.shape[0]
    bar = round(sp.thrust * (hh - 40))  # thrust bar on the right edge
    cv2.rectangle(img, (img.shape[1] - 18, hh - 20 - bar), (img.shape[1] - 8, hh - 20), (0, 200, 255), -1)
    return img


def _plot(rows: list[dict[str, Any]], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def col(k: str) -> np.ndarray:
        return np.array([float(r[k]) if r[k] != "" else np.nan for r in rows])

    t = col("t")
    fig, ax = plt.subplots(4, 1, figsize=(9, 10), sharex=True)
    ax[0].plot(t, col("cx"), label="cx")
    ax[0].plot(t, col("cy"), label="cy")
    ax[0].set_ylabel("box centre [px]")
    ax[0].legend(loc="upper right")
    ln, le, ld = col("los_n"), col("los_e"), col("los_d")
    ax[1].plot(t, np.degrees(np.arctan2(le, ln)), label="LOS azimuth")
    ax[1].plot(t, np.degrees(np.arcsin(np.clip(-ld, -1, 1))), label="LOS elevation")
    ax[1].set_ylabel("filtered LOS [deg]")
    ax[1].legend(loc="upper right")
    for k in ("roll_deg", "pitch_deg"):
        ax[2].plot(t, col(k), label=k)
    ax[2].set_ylabel("commanded [deg]")
    ax[2].legend(loc="upper right")
    ax[3].plot(t, col("thrust"), label="thrust")
    ax[3].set_ylabel("thrust [0..1]")
    ax[3].set_xlabel("t [s]")
    fig.suptitle(f"replay: {title}")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _tally_line(name: str, e: dict[str, Any]) -> str:
    s = (f"{name}: {e['engagements']} engagement(s), {e['begun_on_wrong']} begun on a wrong object, "
         f"{e['passes_claimed_wrong']}/{e['passes_claimed']} pass(es) claimed on one")
    if e.get("passes_claimed_unlabelled"):
        s += f" ({e['passes_claimed_unlabelled']} on an unlabelled frame: not judged)"
    if e["engaged_frames"]:
        s += (f", {e['engaged_frames_wrong']}/{e['engaged_frames']} labelled engaged frames on one "
              f"(on the gate {e['on_gate_share']:.2f})")
    if e["gate_spells"]:
        s += f", {e['never_engaged_spells']}/{e['gate_spells']} gate-in-view spells never engaged"
    if any(e.get(k) for k in ("begun_oversize", "engaged_frames_oversize", "passes_claimed_oversize")):
        from companion.engagetally import EngagementTally

        s += (f"; on a gate but over {EngagementTally.size_ratio:g}x its label: {e['begun_oversize']} begun, "
              f"{e['engaged_frames_oversize']} frames, {e['passes_claimed_oversize']} pass(es) claimed")
    return s


def _cmd(args: argparse.Namespace) -> int:
    import sys

    from companion.engagetally import total

    cfg = config_from_args(args)
    videos, labels = list(args.video), list(args.labels or [])
    if labels and len(labels) != len(videos):
        print(f"companion replay: --labels: {len(labels)} given for {len(videos)} video(s) (one per video)",
              file=sys.stderr)
        return 2
    tallies = []
    for i, video in enumerate(videos):
        out = args.out
        if out is not None and len(videos) > 1:
            out = str(Path(out) / Path(video).stem)
        try:
            from companion.app.record import record_kwargs

            s = replay(video, cfg, args.log, out, args.t0, progress=not args.quiet, record=args.record,
                       record_kw=record_kwargs(args), labels=labels[i] if labels else None)
        except ValueError as e:  # ReplayError, DetectorError, TrackerError: already one line
            if isinstance(e, UnicodeDecodeError):  # a binary --log file
                e = ValueError(f"{args.log}: not a text flight log (byte 0x{e.object[e.start]:02x} at offset "
                               f"{e.start})")
            print(f"companion replay: {e}", file=sys.stderr)
            return 2
        except (OSError, csv.Error) as e:  # an output folder that cannot be made, a log that is not text
            where = getattr(e, "filename", None) or args.log or out
            print(f"companion replay: {where}: {getattr(e, 'strerror', None) or e}", file=sys.stderr)
            return 2
        print(f"replay: {s['frames']} frames, box in {s['boxes']}; wrote {s['annotated']}, {s['csv']}, {s['plot']}")
        print("  " + _tally_line(Path(video).name, s["engagements"]))
        tallies.append(s["engagements"])
    if len(videos) > 1:
        print("  " + _tally_line("total", total(tallies)))
    return 0


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "replay", help="run detector + tracker + LOS + controller over a recorded video",
        description="Run detector + tracker + LOS + controller over a recorded video, as the app would have; "
        "write an annotated video (box, LOS, commanded attitude and thrust), a per-frame CSV and plots.",
    )
    p.add_argument("video", nargs="+",
                   help="recorded video file(s) or --record folder(s) (frame size = camera.width/height)")
    p.add_argument("--labels", action="append", default=None, metavar="SEQ",
                   help="ground truth per video (repeat in the videos' order): a sequence folder of `companion "
                   "perception eval` (images/ + labels/; frame k = the k-th image by name); each engagement "
                   "is then judged (begun / engaged / pass claimed on a wrong object, gate spells never engaged)")
    p.add_argument("--log", default=None, metavar="FLIGHT_LOG",
                   help="flight folder, or CSV / JSON-lines of t, qw, qx, qy, qz (NED/FRD); default: level")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="output folder (default: VIDEO_replay/ next to it; with several videos DIR/VIDEO_STEM/)")
    p.add_argument("--t0", type=float, default=0.0, help="flight time of the first frame, s (default 0)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    from companion.app.record import add_record_arguments

    add_record_arguments(p)
    add_config_arguments(p)
    p.set_defaults(func=_cmd)
