"""Camera sources: V4L2/USB index, video file, GStreamer pipeline, RTSP URL, or synthetic frames.

Each source runs a reader thread that grabs frames as fast as the device delivers them,
timestamps each one at capture (``time.monotonic()``) and keeps only the newest: the control
loop always gets the latest frame, and every frame replaced before it was read counts as
dropped. ``read(timeout)`` returns ``(t, frame)`` of a frame not returned before, or None on
timeout / end of stream.

A video file is read at its own frame rate by default (``realtime=True``, like a camera);
``realtime=False`` reads it as fast as possible without dropping (offline replay).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np


class SourceError(RuntimeError):
    """A source that cannot be opened, as one line."""


FrameFn = Callable[[float], np.ndarray | None]  # synthetic: time since start (s) -> frame, or None = end


class FrameSource:
    """Reader thread + newest-frame slot. Build with :func:`open_source`."""

    def __init__(self, grab: Callable[[], np.ndarray | None], name: str, fps: float = 0.0,
                 pace: bool = False, drop: bool = True, release: Callable[[], None] | None = None) -> None:
        self.name = name
        self.fps = float(fps)
        self._grab = grab
        self._pace = pace and fps > 0
        self._drop = drop
        self._release = release
        self._cond = threading.Condition()
        self._latest: tuple[float, np.ndarray] | None = None
        self._fresh = False
        self._ended = False
        self._stop = threading.Event()
        self.captured = 0
        self.delivered = 0
        self.dropped = 0  # frames replaced by a newer one before anyone read them
        self.error: str | None = None
        self._thread = threading.Thread(target=self._run, name=f"source:{name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        period = 1.0 / self.fps if self._pace else 0.0
        next_t = time.monotonic()
        try:
            while not self._stop.is_set():
                frame = self._grab()
                t = time.monotonic()
                if frame is None:
                    break
                with self._cond:
                    if not self._drop:  # offline: wait until the last frame was taken
                        while self._fresh and not self._stop.is_set():
                            self._cond.wait(0.1)
                    if self._fresh:
                        self.dropped += 1
                    self._latest = (t, frame)
                    self._fresh = True
                    self.captured += 1
                    self._cond.notify_all()
                if period:
                    next_t += period
                    self._stop.wait(max(0.0, next_t - time.monotonic()))
        except Exception as e:  # a device error ends the stream; read() then returns None
            self.error = f"{self.name}: {e}"
        finally:
            with self._cond:
                self._ended = True
                self._cond.notify_all()

    def read(self, timeout: float = 1.0) -> tuple[float, np.ndarray] | None:
        """The newest frame not returned before, waiting up to ``timeout`` s; None on timeout or end."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while not self._fresh:
                if self._ended:
                    return None
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)
            self._fresh = False
            self.delivered += 1
            assert self._latest is not None
            self._cond.notify_all()
            return self._latest

    @property
    def ended(self) -> bool:
        with self._cond:
            return self._ended and not self._fresh

    def stats(self) -> dict[str, int]:
        return {"captured": self.captured, "delivered": self.delivered, "dropped": self.dropped}

    def close(self, timeout: float = 2.0) -> None:
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        self._thread.join(timeout)
        if self._release is not None:
            self._release()
            self._release = None

    def __enter__(self) -> FrameSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _has_gstreamer() -> bool:
    for line in cv2.getBuildInformation().splitlines():
        if line.strip().startswith("GStreamer:"):
            return "YES" in line
    return False


def _capture(spec: str | int, api: int) -> cv2.VideoCapture:
    cap = cv2.VideoCapture(spec, api)
    if not cap.isOpened():
        cap.release()
        raise SourceError(f"camera source {spec!r}: cannot open")
    return cap


def open_source(spec: str | int, realtime: bool = True, frame_fn: FrameFn | None = None,
                fps: float = 30.0) -> FrameSource:
    """Open a source from its spec.

    ``int`` or digits -> V4L2 device index; ``rtsp://``/``http(s)://`` -> network stream;
    a string containing ``!`` -> GStreamer pipeline (must end in ``appsink``); ``"synthetic"`` ->
    ``frame_fn(t)`` called at ``fps``; anything else -> a video file path.
    """
    if isinstance(spec, str) and spec == "synthetic":
        if frame_fn is None:
            raise SourceError("camera source 'synthetic': needs a frame function")
        n = [0]

        def grab_syn() -> np.ndarray | None:
            # Frame k is rendered for its nominal time k/fps so replays are deterministic.
            f = frame_fn(n[0] / fps)
            n[0] += 1
            return f

        return FrameSource(grab_syn, "synthetic", fps, pace=realtime, drop=realtime)
    if isinstance(spec, int) or (isinstance(spec, str) and spec.strip().isdigit()):
        cap = _capture(int(spec), cv2.CAP_V4L2)
        name = f"v4l2:{int(spec)}"
        pace, drop = False, True  # the device paces itself
    elif isinstance(spec, str) and spec.startswith(("rtsp://", "rtsps://", "http://", "https://")):
        cap = _capture(spec, cv2.CAP_FFMPEG)
        name, pace, drop = spec, False, True
    elif isinstance(spec, str) and "!" in spec:
        if not _has_gstreamer():
            raise SourceError(
                f"camera source {spec[:40]!r}...: this OpenCV build has no GStreamer support "
                "(the PyPI wheels do not; use a system OpenCV built with GStreamer)"
            )
        cap = _capture(spec, cv2.CAP_GSTREAMER)
        name, pace, drop = "gstreamer", False, True
    else:
        p = Path(str(spec))
        if not p.is_file():
            raise SourceError(f"camera source {spec!r}: no such video file")
        cap = _capture(str(p), cv2.CAP_ANY)
        name = str(p)
        pace, drop = realtime, realtime
    fps_dev = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    if fps_dev <= 0 or fps_dev > 1000:
        fps_dev = fps

    def grab() -> np.ndarray | None:
        ok, frame = cap.read()
        return frame if ok else None

    return FrameSource(grab, name, fps_dev, pace=pace, drop=drop, release=cap.release)
