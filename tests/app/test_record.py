"""Recording (``fly --record``, ``replay --record``): frames with capture time and attitude, read back by replay;
bounded disk use; a recording that cannot write stops itself and never the flight."""

from __future__ import annotations

import csv
import json
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest
from flighthelpers import make_config

from companion.app.assemble import detector_available
from companion.app.record import Recorder, RecordingReader
from companion.app.states import Reason
from companion.config import load_config
from companion.flightlog import read_flight

pytestmark = pytest.mark.timeout(200)


def _rows(path):
    with open(path, encoding="utf-8", newline="") as f:
        return list(csv.DictReader(f))


def _slerp_at(tel, t):
    from scipy.spatial.transform import Rotation, Slerp

    ok = np.isfinite(tel["t_att"]) & np.isfinite(tel["qw"])
    ts, keep = np.unique(tel["t_att"][ok], return_index=True)
    q = np.column_stack([tel[k][ok][keep] for k in ("qx", "qy", "qz", "qw")])
    x, y, z, w = Slerp(ts, Rotation.from_quat(q))([np.clip(t, ts[0], ts[-1])]).as_quat()[0]
    return np.array([w, x, y, z])


@pytest.mark.slow
@pytest.mark.skipif(detector_available(load_config()) is not None, reason="the shipped gate detector is missing")
def test_record_a_flight_and_replay_the_recording(sim, tmp_path):
    rec = tmp_path / "rec"
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.synthetic.render=image", "app.synthetic.motion=linear_slow")
    reason, folder, summary = run_flight_recorded(cfg, rec)
    assert reason is Reason.OK, summary
    f = read_flight(folder)
    idx = _rows(rec / "index.csv")
    det = f["detections"]
    # Every frame the app saw is on disk, or counted as skipped when the writer fell behind (a loaded machine:
    # the flight never waits for the disk); the recorded ones are the app's frames, in order.
    meta = json.loads((rec / "meta.json").read_text())
    assert meta["frames_written"] == len(idx) and meta["stopped"] is None
    assert meta["frames_written"] + meta["frames_skipped_queue_full"] == len(det)
    seen = [int(k) for k in det["frame"]]
    rec_frames = [int(r["frame"]) for r in idx]
    assert rec_frames == sorted(rec_frames) and set(rec_frames) <= set(seen)
    rows = [seen.index(k) for k in rec_frames]
    for r in idx[:: max(1, len(idx) // 20)]:
        assert (rec / r["file"]).is_file()
    # Capture time on the flight clock: the same as the detections' t_frame.
    assert np.allclose([float(r["t"]) for r in idx], np.asarray(det["t_frame"])[rows], atol=1e-5)
    # The attitude at capture time: PX4's attitude (telemetry) interpolated to the frame time, within the
    # telemetry's 20 Hz log sampling (the app interpolates its own 50 Hz history).
    tel = f["telemetry"]
    errs = []
    for r in idx[10::10]:
        q_rec = np.array([float(r[k]) for k in ("qw", "qx", "qy", "qz")])
        q_tel = _slerp_at(tel, float(r["t"]))
        errs.append(np.degrees(2 * np.arccos(min(1.0, abs(float(q_rec @ q_tel))))))
    assert np.median(errs) < 1.0 and max(errs) < 5.0, errs
    # A labelling tool's view: images of the camera's size.
    img = __import__("cv2").imread(str(rec / idx[0]["file"]))
    assert img.shape == (cfg.camera.height, cfg.camera.width, 3)

    # Replay reads the recording back: same frames, same times, the recorded attitude.
    out = tmp_path / "replay"
    res = subprocess.run([sys.executable, "-m", "companion.cli", "replay", str(rec), "--out", str(out), "--quiet",
                          "--set", "app.camera=synthetic"], capture_output=True, text=True, timeout=180)
    assert res.returncode == 0, res.stderr
    rep = _rows(out / "replay.csv")
    assert len(rep) == len(idx)
    assert np.allclose([float(r["t"]) for r in rep], [float(r["t"]) for r in idx], atol=1e-5)
    assert np.allclose([float(r["qw"]) for r in rep], [float(r["qw"]) for r in idx], atol=1e-6)
    boxes = sum(int(r["box"]) for r in rep)
    assert boxes > 0.5 * int(np.sum(np.asarray(det["valid"])[rows] == 1))  # the detector finds the gate again

    # Replay --record (the function behind it, on the first 15 frames): the replayed frames again, losslessly.
    from companion.replay import replay

    again = tmp_path / "again"
    replay(rec, load_config([], ["app.camera=synthetic"]), out=tmp_path / "r2", progress=False, max_frames=15,
           record=again, record_kw={"fmt": "png"})
    idx2 = _rows(again / "index.csv")
    assert len(idx2) == 15 and idx2[0]["file"].endswith(".png")
    assert np.allclose([float(r["t"]) for r in idx2], [float(r["t"]) for r in idx[:15]], atol=1e-5)
    a = __import__("cv2").imread(str(again / idx2[5]["file"]))
    b = __import__("cv2").imread(str(rec / idx[5]["file"]))
    assert np.array_equal(a, b)  # PNG is lossless: the replayed frame exactly


def run_flight_recorded(cfg, rec):
    import asyncio

    from companion.app.session import fly

    async def main():
        return await asyncio.wait_for(fly(cfg, plot=False, handle_signals=False, record=rec), 90.0)

    return asyncio.run(main())


def _frames(n, h=120, w=160):
    rng = np.random.default_rng(0)
    return [rng.integers(0, 255, (h, w, 3), dtype=np.uint8) for _ in range(n)]


def test_recording_stops_at_its_byte_budget(tmp_path):
    stops = []
    r = Recorder(tmp_path / "r", fmt="png", max_bytes=200_000, on_stop=stops.append, queue_size=1000)
    for k, img in enumerate(_frames(40)):  # random images: ~58 kB each as PNG
        r.add(k, float(k), img, [1, 0, 0, 0])
    r.close()
    assert r.stopped is not None and "byte budget" in r.stopped and stops == [r.stopped]
    assert 0 < r.written < 40 and r.bytes <= 200_000
    on_disk = sum(p.stat().st_size for p in (tmp_path / "r" / "frames").iterdir())
    assert on_disk == r.bytes and len(_rows(tmp_path / "r" / "index.csv")) == r.written
    assert len(RecordingReader(tmp_path / "r").rows) == r.written  # what was written reads back


def test_recording_that_cannot_write_stops_and_never_raises(tmp_path):
    stops = []
    r = Recorder(tmp_path / "r", on_stop=stops.append)
    frames = _frames(5)
    r.add(0, 0.0, frames[0], None)
    deadline = time.monotonic() + 10
    while r.written < 1 and time.monotonic() < deadline:
        time.sleep(0.01)
    shutil.rmtree(tmp_path / "r" / "frames")  # the card was pulled / the folder removed
    for k, img in enumerate(frames[1:], 1):
        r.add(k, float(k), img, None)
    r.close()
    assert r.written == 1 and r.stopped is not None and "write failed" in r.stopped and len(stops) == 1
    r.add(9, 9.0, frames[0], None)  # after the stop: ignored, no exception


def test_recording_refuses_a_folder_that_already_holds_one(tmp_path):
    Recorder(tmp_path / "r").close()
    res = subprocess.run([sys.executable, "-m", "companion.cli", "fly", "--record", str(tmp_path / "r")],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and "already holds a recording" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
