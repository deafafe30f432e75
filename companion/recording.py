"""Replay's input, read and checked: a ``--record`` folder (frames + index.csv), and the attitude of a
flight log (a flight folder, a CSV or a JSON-lines file of t, qw, qx, qy, qz).

A recording is data from a disk that may have filled up, a process that was killed mid-write, or a hand
that edited it; it is read as untrusted:

* index.csv: a torn last row (the writer killed mid-line) is dropped and counted; any other row that does
  not parse, a time that is not finite, or a time or frame number that does not increase is refused with
  its line number; a file path that is absolute or leads out of the folder is refused (never opened);
  a quaternion that is not a rotation (NaN, zero) means "attitude unknown" for that frame.
* frames: a missing or undecodable frame file is skipped and counted (replay goes on with the next one and
  reports the count); a frame of another size than index.csv says is refused (the annotated video would
  silently drop it).
* frame numbers: every time lookup is by the camera's frame number (index.csv's ``frame``; a video's frame k
  is the camera's frame k + 1, the app numbers from 1), so a flight log's ``detections.csv`` times and the
  recording's own times land on the frame they were taken with.
"""

from __future__ import annotations

import csv
import json
import math
import os
import stat
from pathlib import Path
from typing import Any

import numpy as np

from companion.attitude import AttitudeTrack

MAX_TEXT_BYTES = 512 * 1024 * 1024  # an index or attitude log larger than this is not a flight's (~10^6 rows)
MAX_META_BYTES = 4 * 1024 * 1024
_FIELD_LIMIT = 1024 * 1024  # csv's own field limit is 128 KB; a longer field is refused by length, not a traceback


class ReplayError(ValueError):
    """Bad replay input, as one line."""


def level_attitude() -> AttitudeTrack:
    return AttitudeTrack(np.array([0.0]), np.array([[1.0, 0.0, 0.0, 0.0]]))


def _regular_file(path: Path, limit: int, what: str) -> None:
    """Refuse a FIFO, a device, a folder or a file too large to be ours, before opening it (a FIFO blocks)."""
    try:
        st = os.stat(path)
    except OSError as e:
        raise ReplayError(f"{path}: {what} cannot be read ({e.strerror or e})") from None
    if not stat.S_ISREG(st.st_mode):
        raise ReplayError(f"{path}: {what} is not a regular file")
    if st.st_size > limit:
        raise ReplayError(f"{path}: {what} is {st.st_size / 1e6:.0f} MB, more than the {limit / 1e6:.0f} MB accepted")


def read_csv_rows(path: Path, what: str = "CSV file") -> list[dict[str, Any]]:
    _regular_file(path, MAX_TEXT_BYTES, what)
    csv.field_size_limit(max(csv.field_size_limit(), _FIELD_LIMIT))
    try:
        with open(path, newline="", encoding="utf-8") as f:
            return list(csv.DictReader(f))
    except csv.Error as e:
        raise ReplayError(f"{path}: not a readable {what} ({e})") from None


def _rows_to_track(rows: list[dict[str, Any]], where: str) -> AttitudeTrack:
    need = ("t", "qw", "qx", "qy", "qz")
    good = []
    for i, r in enumerate(rows):
        missing = [k for k in need if k not in r]
        if missing:
            raise ReplayError(f"{where}: row {i + 1}: missing {', '.join(missing)} (need t, qw, qx, qy, qz)")
        try:
            vals = [float(r[k]) for k in need]
        except (TypeError, ValueError):
            continue  # a blank or cut-off line (a log killed mid-write): skip it
        if all(math.isfinite(v) for v in vals) and np.linalg.norm(vals[1:]) > 0.5:
            good.append(vals)
    if not good:
        raise ReplayError(f"{where}: no attitude samples (t, qw, qx, qy, qz)")
    a = np.array(sorted(good, key=lambda v: v[0]))
    t, keep = np.unique(a[:, 0], return_index=True)
    q = a[keep, 1:]
    return AttitudeTrack(t, q / np.linalg.norm(q, axis=1, keepdims=True))


def load_attitude(path: str | Path) -> AttitudeTrack:
    """Attitude from a flight folder, a CSV or a JSON-lines file (see companion/replay.py's doc)."""
    p = Path(path)
    if p.is_dir():
        tel = p / "telemetry.csv"
        if not tel.is_file():
            raise ReplayError(f"{p}: flight folder without telemetry.csv")
        track = _rows_to_track(read_csv_rows(tel, "telemetry log"), str(tel))
        det = p / "detections.csv"
        if det.is_file():
            ft = {}
            for r in read_csv_rows(det, "detections log"):
                try:
                    ft[int(float(r["frame"]))] = float(r["t_frame"])
                except (KeyError, TypeError, ValueError, OverflowError):
                    continue
            track.frame_times = {k: v for k, v in ft.items() if math.isfinite(v)} or None
        return track
    if not p.exists():
        raise ReplayError(f"{p}: flight log not found")
    if p.suffix in (".jsonl", ".json", ".ndjson"):
        _regular_file(p, MAX_TEXT_BYTES, "attitude log")
        rows = []
        lines = p.read_text(encoding="utf-8").splitlines()
        for i, line in enumerate(lines):
            if not line.strip():
                continue
            try:
                rows.append(json.loads(line))
            except ValueError:
                if i == len(lines) - 1:
                    continue  # a cut-off last line (log killed mid-write)
                raise ReplayError(f"{p}: line {i + 1}: not JSON") from None
        return _rows_to_track(rows, str(p))
    return _rows_to_track(read_csv_rows(p, "attitude log"), str(p))


def frame_time(track: AttitudeTrack, frame_no: int, k: int, t0: float, fps: float) -> float:
    """Capture time of the k-th frame read (camera frame number ``frame_no``): the log's time of that frame
    number when it has one, else ``t0 + k / fps``."""
    if track.frame_times:
        return track.frame_times.get(frame_no, t0 + k / fps)
    return t0 + k / fps


# ------------------------------------------------------------------------------------------------ recordings


def is_recording(path: str | Path) -> bool:
    p = Path(path)
    return p.is_dir() and (p / "index.csv").is_file()


_NEED = ("frame", "file", "t", "qw", "qx", "qy", "qz", "width", "height")


class RecordingReader:
    """A recording read back like a cv2.VideoCapture (``read``, ``get``, ``release``), plus its attitude.

    ``frame_no`` is the camera frame number of the frame ``read`` returned last; ``unreadable`` lists the
    frame files that were missing or undecodable (skipped); ``torn`` is 1 if index.csv's last row was cut."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self._root = os.path.realpath(self.folder)
        index = self.folder / "index.csv"
        _regular_file(index, MAX_TEXT_BYTES, "recording index")
        meta = self.folder / "meta.json"
        if meta.exists():
            _regular_file(meta, MAX_META_BYTES, "recording meta.json")
        try:
            with open(index, encoding="utf-8", newline="") as f:
                lines = list(csv.reader(f))
            self.meta = json.loads(meta.read_text(encoding="utf-8")) if meta.exists() else {}
        except (OSError, ValueError, csv.Error) as e:
            raise ReplayError(f"{self.folder}: not a readable recording ({e})") from None
        if not lines or any(c not in lines[0] for c in _NEED):
            raise ReplayError(f"{index}: not a recording index (header must name {', '.join(_NEED)})")
        head = lines[0]
        self.torn = 0
        self.rows: list[dict[str, Any]] = []
        body = [(n, ln) for n, ln in enumerate(lines[1:], start=2) if ln]
        for j, (line_no, cells) in enumerate(body):
            try:
                self.rows.append(self._parse(dict(zip(head, cells, strict=False)), len(cells) >= len(head)))
            except ReplayError as e:
                if j == len(body) - 1 and "cut" in str(e):
                    self.torn = 1  # the writer was killed mid-line: the last row is partial
                    continue
                raise ReplayError(f"{index}: line {line_no}: {e}") from None
            if len(self.rows) > 1:
                prev, cur = self.rows[-2], self.rows[-1]
                if not cur["t"] > prev["t"] or not cur["frame"] > prev["frame"]:
                    raise ReplayError(f"{index}: line {line_no}: frame {cur['frame']} at t {cur['t']:.6f} s does "
                                      f"not come after frame {prev['frame']} at {prev['t']:.6f} s (times and frame "
                                      "numbers must increase)")
        if not self.rows:
            raise ReplayError(f"{self.folder}: recording without frames")
        sizes = {(r["width"], r["height"]) for r in self.rows}
        if len(sizes) > 1:
            listed = ", ".join(f"{w}x{h}" for w, h in sorted(sizes))
            raise ReplayError(f"{index}: frames of {len(sizes)} sizes ({listed}): one camera, one size")
        self.t = np.array([r["t"] for r in self.rows])
        self.q = np.array([r["q"] for r in self.rows])
        self.unreadable: list[str] = []
        self.frame_no = 0
        self._k = 0
        span = self.t[-1] - self.t[0]
        self.fps = (len(self.rows) - 1) / span if len(self.rows) > 1 and span > 0 else 30.0

    def _parse(self, r: dict[str, str], whole: bool) -> dict[str, Any]:
        try:
            frame, w, h = int(r["frame"]), int(r["width"]), int(r["height"])
            t = float(r["t"])
            q = np.array([float(r[k]) for k in ("qw", "qx", "qy", "qz")])
        except (KeyError, TypeError, ValueError) as e:
            raise ReplayError(f"row cut or not a recording row ({e})" if not whole else f"not a recording row ({e})"
                              ) from None
        if not whole:
            raise ReplayError("row cut short")
        if not math.isfinite(t):
            raise ReplayError(f"time t {r['t']!r} is not a finite number")
        if w <= 0 or h <= 0:
            raise ReplayError(f"frame size {w}x{h}")
        if not np.isfinite(q).all() or not 0.5 < np.linalg.norm(q) < 2.0:
            q = np.full(4, np.nan)  # no attitude with this frame (the recorder writes NaN before the first)
        return {"frame": frame, "file": self._inside(r["file"]), "t": t, "q": q, "width": w, "height": h}

    def _inside(self, name: str) -> str:
        """The frame file's path, refused if absolute or outside the recording folder (symlinks resolved)."""
        if not name or os.path.isabs(name):
            raise ReplayError(f"frame file {name!r}: must be a path inside the recording folder")
        real = os.path.realpath(os.path.join(self._root, name))
        if os.path.commonpath([real, self._root]) != self._root:
            raise ReplayError(f"frame file {name!r} leads outside the recording folder {self.folder}")
        return real

    def isOpened(self) -> bool:  # cv2.VideoCapture's name
        return True

    def read(self) -> tuple[bool, np.ndarray | None]:
        """The next readable frame (missing or undecodable files are skipped and listed in ``unreadable``)."""
        import cv2

        while self._k < len(self.rows):
            r = self.rows[self._k]
            self._k += 1
            img = None
            try:
                if stat.S_ISREG(os.stat(r["file"]).st_mode):  # a FIFO would block imread
                    img = cv2.imread(r["file"], cv2.IMREAD_COLOR)
            except OSError:
                pass
            if img is None:
                self.unreadable.append(os.path.relpath(r["file"], self._root))
                continue
            if (img.shape[1], img.shape[0]) != (r["width"], r["height"]):
                raise ReplayError(f"{self.folder}: frame file {os.path.relpath(r['file'], self._root)} is "
                                  f"{img.shape[1]}x{img.shape[0]} but index.csv says {r['width']}x{r['height']}")
            self.frame_no = r["frame"]
            return True, img
        return False, None

    def get(self, prop: int) -> float:
        import cv2

        r = self.rows[0]
        props = {cv2.CAP_PROP_FPS: self.fps, cv2.CAP_PROP_FRAME_COUNT: float(len(self.rows)),
                 cv2.CAP_PROP_FRAME_WIDTH: float(r["width"]), cv2.CAP_PROP_FRAME_HEIGHT: float(r["height"])}
        return props.get(prop, 0.0)

    def release(self) -> None:
        self._k = len(self.rows)

    def attitude(self) -> AttitudeTrack | None:
        """The attitude track of the recording, each frame number at its recorded time."""
        ok = np.isfinite(self.q).all(axis=1)
        if not ok.any():
            return None
        t, keep = np.unique(self.t[ok], return_index=True)
        q = self.q[ok][keep]
        return AttitudeTrack(t, q / np.linalg.norm(q, axis=1, keepdims=True),
                             {r["frame"]: float(r["t"]) for r in self.rows})

    def problems(self) -> str:
        """One line on what could not be read ('' if everything was)."""
        parts = []
        if self.unreadable:
            parts.append(f"{len(self.unreadable)} of {len(self.rows)} frame(s) missing or unreadable, skipped "
                         f"(first: {self.unreadable[0]})")
        if self.torn:
            parts.append("index.csv's last row was cut off (dropped)")
        return "; ".join(parts)
