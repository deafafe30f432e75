"""Replay's input read as untrusted (issue 22): a recording with missing, corrupt or resized frames, a torn,
reordered or hostile index.csv, and frame times by camera frame number (companion/recording.py)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from companion.app.record import Recorder
from companion.config import load_config
from companion.recording import RecordingReader, ReplayError

N = 12
T0 = 100.0  # the flight clock's origin: the recording's t = t_mono - T0


def _q(k: int) -> np.ndarray:
    """Yaw 3 deg per frame: each frame's attitude tells which frame it is."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_euler("z", 3.0 * k, degrees=True).as_quat()
    return np.array([w, x, y, z])


def _recording(folder: Path, size: tuple[int, int] = (640, 480)) -> Path:
    rec = Recorder(folder, fmt="png", t0=T0, blocking=True)
    for k in range(1, N + 1):  # the app numbers camera frames from 1
        img = np.full((size[1], size[0], 3), 20 * k % 255, np.uint8)
        rec.add(k, T0 + 0.05 * k, img, _q(k))
    rec.close()
    assert rec.written == N
    return folder


def _index(folder: Path) -> list[list[str]]:
    with open(folder / "index.csv", newline="") as f:
        return list(csv.reader(f))


def _write_index(folder: Path, rows: list[list[str]]) -> None:
    with open(folder / "index.csv", "w", newline="") as f:
        csv.writer(f, lineterminator="\n").writerows(rows)


def _replay(folder: Path, out: Path, **kw):
    from companion.replay import replay

    return replay(folder, load_config(), out=out, progress=False, **kw)


def test_missing_and_corrupt_frames_are_skipped_and_counted(tmp_path, capsys):
    rec = _recording(tmp_path / "rec")
    (rec / "frames" / "000005.png").unlink()
    (rec / "frames" / "000008.png").write_bytes(b"not a png")
    s = _replay(rec, tmp_path / "out")
    # Before: "replay: 4 frames" (stopped at the first missing one), no word about it.
    assert s["frames"] == N - 2
    assert s["unreadable"]["frames"] == ["frames/000005.png", "frames/000008.png"]
    err = capsys.readouterr().err
    assert "2 of 12 frame(s) missing or unreadable" in err and "frames/000005.png" in err
    with open(tmp_path / "out" / "replay.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    # Each replayed frame keeps its own recorded time (frame 6 is not given frame 5's time).
    want = [0.05 * k for k in range(1, N + 1) if k not in (5, 8)]
    assert [float(r["t"]) for r in rows] == pytest.approx(want, abs=1e-6)
    # ... and its own attitude, and the summary names where the attitude came from.
    assert [float(r["qz"]) for r in rows] == pytest.approx([_q(k)[3] for k in range(1, N + 1) if k not in (5, 8)],
                                                           abs=1e-6)
    assert s["attitude"] != "level" and "recorded" in s["attitude"]


def test_frames_of_another_size_than_the_index_are_refused(tmp_path):
    rec = _recording(tmp_path / "rec", size=(320, 240))
    rows = _index(rec)
    w, h = rows[0].index("width"), rows[0].index("height")
    for r in rows[1:]:
        r[w], r[h] = "640", "480"  # the index says 640x480 (the config's size), the files are 320x240
    _write_index(rec, rows)
    with pytest.raises(ReplayError, match=r"000001\.png is 320x240 but index\.csv says 640x480"):
        _replay(rec, tmp_path / "out")


def test_a_torn_last_row_is_dropped(tmp_path):
    rec = _recording(tmp_path / "rec")
    with open(rec / "index.csv", "a") as f:
        f.write("13,frames/000013.png,0.65")  # the writer killed mid-line
    r = RecordingReader(rec)
    assert len(r.rows) == N and r.torn == 1 and "cut off" in r.problems()


@pytest.mark.parametrize(("edit", "match"), [
    (lambda rows, t: rows[4].__setitem__(t, rows[3][t]), r"line 5: frame 4 at t 0\.150000 s does not come after"),
    (lambda rows, t: rows[6].__setitem__(t, "0.1"), r"line 7: .* does not come after frame 5"),
    (lambda rows, t: rows[3].__setitem__(t, "nan"), r"line 4: time t 'nan' is not a finite number"),
    (lambda rows, t: rows[2].__setitem__(1, "../../../../etc/passwd"), r"line 3: .*leads outside the recording"),
    (lambda rows, t: rows[2].__setitem__(1, "/etc/passwd"), r"line 3: .*must be a path inside the recording"),
    (lambda rows, t: rows[5].__setitem__(0, "x"), r"line 6: not a recording row"),
])
def test_a_bad_index_is_refused_with_its_line(tmp_path, edit, match):
    rec = _recording(tmp_path / "rec")
    rows = _index(rec)
    edit(rows, rows[0].index("t"))
    _write_index(rec, rows)
    with pytest.raises(ReplayError, match=match):
        RecordingReader(rec)


def test_a_symlinked_frame_out_of_the_folder_is_refused(tmp_path):
    rec = _recording(tmp_path / "rec")
    (tmp_path / "outside.png").write_bytes((rec / "frames" / "000003.png").read_bytes())
    (rec / "frames" / "000003.png").unlink()
    (rec / "frames" / "000003.png").symlink_to(tmp_path / "outside.png")
    with pytest.raises(ReplayError, match=r"line 4: frame file 'frames/000003\.png' leads outside"):
        RecordingReader(rec)


def test_log_of_its_own_flight_gives_each_frame_its_own_time(tmp_path):
    """--log FLIGHT with the recording of that flight: frame k at detections.csv's t_frame of frame k (the
    camera's number), not of frame k - 1."""
    from companion.flightlog import FlightLog

    rec = _recording(tmp_path / "rec")
    log = FlightLog(tmp_path / "flight")
    for j in range(0, 40):
        q = _q(j)  # the same yaw ramp, 3 deg per 0.05 s: the log's attitude at frame k's time is _q(k)
        log.write("telemetry", t=0.05 * j, t_att=0.05 * j, qw=q[0], qx=q[1], qy=q[2], qz=q[3])
    for k in range(1, N + 1):
        log.write("detections", t=0.05 * k + 0.01, t_frame=0.05 * k, frame=k, valid=False)
    log.close()
    s = _replay(rec, tmp_path / "out", log=tmp_path / "flight")
    with open(tmp_path / "out" / "replay.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [float(r["t"]) for r in rows] == pytest.approx([0.05 * k for k in range(1, N + 1)], abs=1e-6)
    assert [float(r["qz"]) for r in rows] == pytest.approx([_q(k)[3] for k in range(1, N + 1)], abs=1e-6)
    assert s["attitude"] == str(tmp_path / "flight")


def test_non_regular_index_is_refused_unread(tmp_path):
    import os

    rec = _recording(tmp_path / "rec")
    (rec / "index.csv").unlink()
    os.mkfifo(rec / "index.csv")  # opening a FIFO for reading would block forever
    with pytest.raises(ReplayError, match="not a regular file"):
        RecordingReader(rec)
    assert json.loads((rec / "meta.json").read_text())["frames_written"] == N
