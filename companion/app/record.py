"""Frame recording for replay and labelling: ``companion fly --record DIR``, ``companion replay --record DIR``.

Layout of a recording (a labelling tool opens the images; ``companion replay DIR`` reads it back)::

    DIR/meta.json     format, camera section of the config (intrinsics, distortion, mount), source, start time
    DIR/index.csv     frame, file, t (s, flight clock), t_mono (s, host monotonic), qw, qx, qy, qz
                      (PX4's attitude at the capture time, body FRD -> NED, scalar first), width, height
    DIR/frames/       000001.jpg ... (JPEG quality 95 by default; ``png`` for lossless)

Writing runs in its own thread behind a bounded queue: the flight loop never waits for the disk. A
frame that finds the queue full is skipped (counted). The recording stops, cleanly and for good, when
its byte budget is spent, when the disk's free space falls below a margin, or on any write error
(disk full, folder removed): one event in the flight log and on stderr, the flight goes on.
"""

from __future__ import annotations

import contextlib
import csv
import datetime as dt
import json
import queue
import shutil
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

FORMAT = "companion-recording"
INDEX_COLUMNS = ("frame", "file", "t", "t_mono", "qw", "qx", "qy", "qz", "width", "height")
FREE_MARGIN_BYTES = 200 * 1024 * 1024  # leave this much free on the disk (the flight log needs room too)


class RecordError(ValueError):
    """A recording folder that cannot be used or read (one line)."""


class Recorder:
    """Frames + capture time + attitude to DIR, in a writer thread, within a byte budget."""

    def __init__(self, folder: str | Path, *, fmt: str = "jpg", quality: int = 95, max_bytes: int = 4 * 1024**3,
                 t0: float = 0.0, meta: dict[str, Any] | None = None, on_stop: Callable[[str], None] | None = None,
                 free_margin: int = FREE_MARGIN_BYTES, queue_size: int = 32, blocking: bool = False) -> None:
        if fmt not in ("jpg", "png"):
            raise RecordError(f"recording format {fmt!r}: use jpg or png")
        self.folder = Path(folder)
        try:
            (self.folder / "frames").mkdir(parents=True, exist_ok=True)
            if (self.folder / "index.csv").exists():
                raise RecordError(f"{self.folder}: already holds a recording (index.csv); choose a new folder")
            self._index = open(self.folder / "index.csv", "w", encoding="utf-8", newline="")  # noqa: SIM115
        except OSError as e:
            raise RecordError(f"{self.folder}: cannot record here ({e.strerror or e})") from None
        self._csv = csv.writer(self._index, lineterminator="\n")
        self._csv.writerow(INDEX_COLUMNS)
        self._index.flush()
        info = {"format": FORMAT, "version": 1, "image_format": fmt, "start_utc": dt.datetime.now(dt.UTC).isoformat(
            timespec="milliseconds"), **(meta or {})}
        self._info = info
        (self.folder / "meta.json").write_text(json.dumps(info, indent=1, default=str) + "\n", encoding="utf-8")
        self.fmt, self.quality, self.max_bytes, self.t0 = fmt, int(quality), int(max_bytes), float(t0)
        self.free_margin = int(free_margin)
        self.on_stop = on_stop
        self.blocking = blocking  # True: add() waits for the writer (offline); False: skips (live camera)
        self.written = 0
        self.skipped = 0  # queue full: the writer was behind
        self.bytes = 0
        self.stopped: str | None = None  # why the recording stopped early
        self._q: queue.Queue = queue.Queue(maxsize=queue_size)
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()

    # -------------------------------------------------------------------------------- caller side
    def add(self, index: int, t_mono: float, image: np.ndarray | None, q_wxyz: Any) -> None:
        """Queue one frame (never raises; never blocks unless the recorder is ``blocking``)."""
        if self.stopped is not None or image is None:
            return
        q = (np.full(4, np.nan) if q_wxyz is None else np.asarray(q_wxyz, float))
        item = (int(index), float(t_mono), image, q)
        if self.blocking:
            self._q.put(item)  # offline (replay): every frame, at the writer's pace
            return
        try:
            self._q.put_nowait(item)
        except queue.Full:
            self.skipped += 1

    def close(self, timeout: float = 10.0) -> None:
        with contextlib.suppress(queue.Full):
            self._q.put(None, timeout=timeout)
        self._thread.join(timeout)
        with contextlib.suppress(Exception):
            self._index.close()
        # What became of every frame offered: a user (and a test) can tell a writer that fell behind from a
        # camera that dropped frames.
        done = {**self._info, "frames_written": self.written, "frames_skipped_queue_full": self.skipped,
                "stopped": self.stopped}
        with contextlib.suppress(OSError):
            tmp = self.folder / "meta.json.tmp"
            tmp.write_text(json.dumps(done, indent=1, default=str) + "\n", encoding="utf-8")
            tmp.replace(self.folder / "meta.json")

    # -------------------------------------------------------------------------------- writer thread
    def _stop(self, why: str) -> None:
        if self.stopped is None:
            self.stopped = why
            if self.on_stop is not None:
                with contextlib.suppress(Exception):
                    self.on_stop(why)

    def _run(self) -> None:
        import cv2

        params = [cv2.IMWRITE_JPEG_QUALITY, self.quality] if self.fmt == "jpg" else [cv2.IMWRITE_PNG_COMPRESSION, 1]
        while True:
            item = self._q.get()
            if item is None:
                return
            if self.stopped is not None:
                continue  # drain: the caller may still be queueing
            index, t_mono, image, q = item
            try:
                ok, buf = cv2.imencode("." + self.fmt, image, params)
                if not ok:
                    raise OSError(f"cannot encode frame {index} as {self.fmt}")
                if self.bytes + buf.nbytes > self.max_bytes:
                    self._stop(f"recording stopped: byte budget {self.max_bytes / 1e6:.0f} MB reached after "
                               f"{self.written} frames")
                    continue
                if shutil.disk_usage(self.folder).free - buf.nbytes < self.free_margin:
                    self._stop(f"recording stopped: less than {self.free_margin / 1e6:.0f} MB free on the disk "
                               f"after {self.written} frames")
                    continue
                name = f"frames/{index:06d}.{self.fmt}"
                with open(self.folder / name, "wb") as f:
                    f.write(buf.tobytes())
                self._csv.writerow([index, name, f"{t_mono - self.t0:.6f}", f"{t_mono:.6f}",
                                    *(format(float(v), ".9g") for v in q), image.shape[1], image.shape[0]])
                self._index.flush()
                self.bytes += buf.nbytes
                self.written += 1
            except (OSError, ValueError) as e:  # disk full, folder gone: stop recording, never the flight
                self._stop(f"recording stopped: write failed after {self.written} frames "
                           f"({getattr(e, 'strerror', None) or e})")


class RecordingCamera:
    """A camera source that records every frame it delivers (with the attitude at its capture time)."""

    def __init__(self, camera: Any, recorder: Recorder, attitude_at: Callable[[float], Any]) -> None:
        self.camera = camera
        self.recorder = recorder
        self.attitude_at = attitude_at

    async def read(self) -> Any:
        frame = await self.camera.read()
        if frame.image is not None:
            try:
                q = self.attitude_at(frame.t)
            except Exception:  # (no attitude yet: record the frame anyway)
                q = None
            self.recorder.add(frame.index, frame.t, frame.image, q)
        return frame

    def close(self) -> None:
        try:
            self.camera.close()
        finally:
            self.recorder.close()

    def __getattr__(self, name: str) -> Any:  # everything else is the wrapped camera's
        return getattr(self.camera, name)


def link_attitude(link: Any) -> Callable[[float], Any]:
    """PX4's attitude at a capture time (interpolated history; the latest sample otherwise)."""

    def at(t: float) -> Any:
        hist = getattr(link, "attitude_history", None)
        q = hist.at(t) if hist is not None else None
        if q is None and link.attitude is not None:
            q = link.attitude.q_wxyz
        return q

    return at


def recorder_for_flight(folder: str | Path, cfg: Any, log: Any, stderr: Any, **kw: Any) -> Recorder:
    """A Recorder whose times are on the flight log's clock and whose stop is an event in the log."""
    from companion.config import config_as_dict

    def on_stop(why: str) -> None:
        log.event(why, "warn")
        print(f"companion: {why}", file=stderr, flush=True)

    meta = {"camera": config_as_dict(cfg)["camera"], "flight_log": str(log.folder),
            "source": cfg.app.camera if cfg.app.camera == "synthetic" else cfg.perception.source}
    return Recorder(folder, t0=log.t0, meta=meta, on_stop=on_stop, **kw)


# Reading a recording back: companion/recording.py (replay's input checks); the names stay importable here.
from companion.recording import RecordingReader, is_recording  # noqa: E402, F401


def add_record_arguments(p: Any) -> None:
    p.add_argument("--record", metavar="DIR", help="save every camera frame with its time and attitude to DIR "
                                                  "(frames/ + index.csv; replay and labelling tools read it)")
    p.add_argument("--record-format", choices=("jpg", "png"), default="jpg",
                   help="jpg (quality 95, default) or png (lossless, ~5x larger)")
    p.add_argument("--record-max-mb", type=float, default=4000.0,
                   help="stop recording after this many MB (default 4000); it also stops when the disk is nearly full")


MAX_RECORD_MB = 10_000_000.0  # 10 TB: a larger budget is a typo (and inf overflowed int())
MIN_RECORD_BYTES = 10 * 1024 * 1024  # room for the first few hundred frames beyond the free margin


def check_record_target(folder: str | Path, free_margin: int = FREE_MARGIN_BYTES) -> None:
    """Refuse, before anything is made or flown, a --record folder that cannot take a recording: not a
    folder (/dev/null, a file), not writable, or on a disk with too little free space (the recorder would
    stop at its first frame while the flight goes on). RecordError, one line."""
    import os

    p = Path(folder)
    if p.exists() and not p.is_dir():
        raise RecordError(f"--record {folder}: not a folder")
    probe = p
    while not probe.exists():  # the nearest existing ancestor is where the folder will be made
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        raise RecordError(f"--record {folder}: {probe} is not a writable folder")
    free = shutil.disk_usage(probe).free
    if free < free_margin + MIN_RECORD_BYTES:
        raise RecordError(f"--record {folder}: {free / 1e6:.0f} MB free on its disk; recording needs more than "
                          f"{(free_margin + MIN_RECORD_BYTES) / 1e6:.0f} MB (it always leaves "
                          f"{free_margin / 1e6:.0f} MB free for the flight log)")


def record_kwargs(args: Any) -> dict[str, Any]:
    """Recorder options from the command line, checked (ConfigError, one line) before anything starts."""
    import math

    from companion.configbase import ConfigError

    if not getattr(args, "record", None):
        return {"fmt": args.record_format, "max_bytes": int(4000.0 * 1e6)}
    mb = args.record_max_mb
    if not (math.isfinite(mb) and 0 < mb <= MAX_RECORD_MB):
        raise ConfigError(f"--record-max-mb {mb}: must be a number > 0 and <= {MAX_RECORD_MB:g}")
    try:
        check_record_target(args.record)
    except RecordError as e:
        raise ConfigError(str(e)) from None
    return {"fmt": args.record_format, "max_bytes": int(mb * 1e6)}
