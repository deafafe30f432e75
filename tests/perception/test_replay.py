"""``companion replay`` on a video the test renders: annotated output, and LOS against ground truth."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.config import load_config
from companion.frames import R_from_euler_ned_deg, quat_wxyz_from_R
from perception.los import CameraModel
from perception.render import TRAIN_STYLE, Gate, make_background, render_gate_frame

FPS = 30.0
N = 30


def _gate_centre(k: int) -> np.ndarray:
    """World NED: 12 m ahead, sweeping 3 m east and rising 0.5 m over the clip."""
    s = k / (N - 1)
    return np.array([12.0 - 2.0 * s, -1.5 + 3.0 * s, -0.5 * s])


def _attitude(k: int, moving: bool) -> np.ndarray:
    """Body FRD -> NED; the moving case yaws and pitches during the clip."""
    if not moving:
        return np.eye(3)
    s = k / (N - 1)
    return R_from_euler_ned_deg(3.0 * math.sin(2 * s), 4.0 * s, 6.0 - 10.0 * s)


def _write_video(path: Path, moving: bool) -> list[np.ndarray]:
    """Render the clip (camera at the origin, attitude per frame) and return the true LOS (NED) per frame."""
    cfg = load_config()
    model = CameraModel.from_config(cfg.camera)
    rng = np.random.default_rng(21)
    bg = make_background(model.width, model.height, rng, TRAIN_STYLE)
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (model.width, model.height))
    assert w.isOpened()
    truth = []
    for k in range(N):
        R_ned_frd = _attitude(k, moving)
        c = _gate_centre(k)
        gate = Gate(c, np.array([1.0, 0.0, 0.0]), 1.0, "ring", (20, 40, 230), 0.15, up=(0.0, 0.0, -1.0))
        img, box = render_gate_frame(model, R_ned_frd @ model.R_body_cam, np.zeros(3), gate, TRAIN_STYLE, rng,
                                     background=bg, t=k / FPS)
        assert box is not None
        w.write(img)
        truth.append(c / np.linalg.norm(c))
    w.release()
    return truth


def _read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def _check_outputs(out: Path, rows: list[dict[str, str]], truth: list[np.ndarray]) -> None:
    cap = cv2.VideoCapture(str(out / "annotated.mp4"))
    assert cap.isOpened()
    n, green = 0, 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        assert frame.shape == (480, 640, 3)
        # the box is drawn in pure green; the rendered scene has no such saturated green
        green += int(((frame[..., 1] > 200) & (frame[..., 0] < 80) & (frame[..., 2] < 80)).sum() > 50)
        n += 1
    cap.release()
    assert n == N
    boxed = [r for r in rows if r["box"] == "1"]
    assert green >= len(boxed) - 2
    assert (out / "replay.png").stat().st_size > 10_000
    assert len(rows) == N and [int(r["frame"]) for r in rows] == list(range(N))
    assert len(boxed) >= N - 3  # acquisition takes confirm_frames
    errs = []
    for r in boxed:
        los = np.array([float(r["los_raw_n"]), float(r["los_raw_e"]), float(r["los_raw_d"])])
        errs.append(_angle_deg(los, truth[int(r["frame"])]))
    # box centre vs projected gate centre: perspective offset + detector error, well under a degree
    assert np.median(errs) < 0.6 and max(errs) < 1.5, errs
    # the controller ran on every frame and produced a sane setpoint
    assert all(0.0 < float(r["thrust"]) <= 1.0 for r in rows)
    assert any(r["mode"] == "pn" for r in rows)


def test_replay_cli_level_attitude(tmp_path: Path) -> None:
    from companion.cli import main

    video = tmp_path / "flight.avi"
    truth = _write_video(video, moving=False)
    out = tmp_path / "out"
    assert main(["replay", str(video), "--out", str(out), "--quiet"]) == 0
    rows = _read_csv(out / "replay.csv")
    _check_outputs(out, rows, truth)
    s = json.loads((out / "summary.json").read_text())
    assert s["frames"] == N and s["attitude"] == "level"


def test_replay_with_attitude_log(tmp_path: Path) -> None:
    """A JSON-lines attitude log at a different rate than the video: slerped to each frame time."""
    from companion.replay import replay

    video = tmp_path / "flight.avi"
    truth = _write_video(video, moving=True)
    log = tmp_path / "att.jsonl"
    with open(log, "w") as f:
        for j in range(2 * N + 3):  # 60 Hz attitude, a little beyond the clip
            t = j / (2 * FPS)
            # the attitude function is smooth in k; sample it at the fractional frame index
            kf = t * FPS
            s = kf / (N - 1)
            R = R_from_euler_ned_deg(3.0 * math.sin(2 * s), 4.0 * s, 6.0 - 10.0 * s)
            q = quat_wxyz_from_R(R)
            f.write(json.dumps({"t": t, "qw": q[0], "qx": q[1], "qy": q[2], "qz": q[3]}) + "\n")
        f.write('{"t": 9.9, "qw": 1')  # a cut-off last line, as a killed logger leaves it
    out = tmp_path / "out2"
    s = replay(video, load_config(), log=log, out=out, progress=False)
    assert s["frames"] == N
    rows = _read_csv(out / "replay.csv")
    _check_outputs(out, rows, truth)
    # Without the attitude, the LOS would be off by the yaw/pitch (up to ~6 deg): the log was used.
    r0 = rows[5]
    assert float(r0["qw"]) < 0.9999


def test_replay_refuses_bad_input(tmp_path: Path) -> None:
    from companion.replay import ReplayError, load_attitude, replay

    with pytest.raises(ReplayError, match="video file not found"):
        replay(tmp_path / "nope.mp4", load_config())
    small = tmp_path / "small.avi"
    w = cv2.VideoWriter(str(small), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (320, 240))
    for _ in range(3):
        w.write(np.zeros((240, 320, 3), np.uint8))
    w.release()
    with pytest.raises(ReplayError, match=r"frames are 320x240 but camera.width x camera.height is 640x480"):
        replay(small, load_config(), out=tmp_path / "o")
    bad = tmp_path / "bad.csv"
    bad.write_text("t,qw,qx\n0,1,0\n")
    with pytest.raises(ReplayError, match=r"bad\.csv: row 1: missing qy, qz"):
        load_attitude(bad)


def test_attitude_from_a_flight_folder(tmp_path: Path) -> None:
    """The app's flight log: telemetry quaternions, and frame times from the detections topic."""
    from companion.flightlog import FlightLog
    from companion.replay import load_attitude

    log = FlightLog(tmp_path / "flight")
    for j in range(11):  # yaw 0 -> 50 deg over 1 s
        q = quat_wxyz_from_R(R_from_euler_ned_deg(0.0, 0.0, 5.0 * j))
        log.write("telemetry", t=0.1 * j, t_att=0.1 * j, qw=q[0], qx=q[1], qy=q[2], qz=q[3])
    for k in range(3):
        log.write("detections", t=0.5 + 0.1 * k, t_frame=0.45 + 0.1 * k, frame=k, cx=1, cy=1, w=1, h=1,
                  confidence=1, valid=1)
    log.close()
    track = load_attitude(tmp_path / "flight")
    assert track.frame_times == pytest.approx({0: 0.45, 1: 0.55, 2: 0.65})
    from companion.frames import R_from_quat_wxyz, euler_ned_deg_from_R

    _, _, yaw = euler_ned_deg_from_R(R_from_quat_wxyz(track.at(0.45)))
    assert yaw == pytest.approx(22.5, abs=1e-6)  # slerp halfway between 20 and 25 deg
    _, _, yaw_end = euler_ned_deg_from_R(R_from_quat_wxyz(track.at(5.0)))
    assert yaw_end == pytest.approx(50.0, abs=1e-6)  # held after the last sample


def test_replay_runs_the_engagement_core(tmp_path: Path) -> None:
    """The app's decisions on the recorded frames: PX4 holds (no setpoint) until a stable track, then ENGAGE
    with the setpoint the app would have sent."""
    from companion.replay import replay

    video = tmp_path / "clip.avi"
    _write_video(video, moving=False)
    s = replay(video, load_config(), out=tmp_path / "out", progress=False)
    rows = _read_csv(tmp_path / "out" / "replay.csv")
    states = [r["state"] for r in rows]
    first = states.index("ENGAGE")
    assert set(states[:first]) == {"ACQUIRE"} and all(r["app_thrust"] == "" for r in rows[:first])
    assert set(states[first:]) == {"ENGAGE"} and all(0.0 < float(r["app_thrust"]) <= 1.0 for r in rows[first:])
    assert rows[first]["app_event"].startswith("gate 1 engaged; stable track for")
    assert first >= load_config().app.acquire_frames - 1
    assert s["engagement"]["state"] == "ENGAGE" and s["engagement"]["passes"][0]["status"] == "engaged"
