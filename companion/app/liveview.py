"""The live view: the annotated camera stream over HTTP as MJPEG (``app.live_view``), for a browser or VLC.

    http://ADDRESS:PORT/            a page showing the stream
    http://ADDRESS:PORT/stream      multipart/x-mixed-replace JPEG stream (VLC: open the network stream)
    http://ADDRESS:PORT/frame.jpg   the newest annotated frame

What it shows: the tracked box (green while engaged, yellow for a candidate awaiting the operator's
confirmation, grey otherwise), the engagement's phase, the track state and the last event.

Why it cannot slow the flight: the frame loop only calls ``offer()``, which stores a reference to the frame and
its annotation in a one-slot mailbox (a newer frame replaces an unread one: frames are dropped, never queued)
and signals a condition; drawing, JPEG encoding (at most ``max_fps``) and every client's socket run in this
module's own daemon threads. A slow or stalled client blocks only its own handler thread. Binds 127.0.0.1
unless ``app.live_view.address`` says otherwise.
"""

from __future__ import annotations

import contextlib
import threading
import time
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import numpy as np

BOUNDARY = "companionframe"
PAGE = (b"<!doctype html><html><head><title>companion live view</title></head>"
        b"<body style='margin:0;background:#111'><img src='/stream' style='width:100%'></body></html>")


@dataclass(frozen=True, slots=True)
class ViewInfo:
    """What to draw on one frame."""

    box: Any = None  # perception.types.BoundingBox or None
    phase: str = ""
    awaiting: bool = False  # a candidate waits for the operator's confirmation
    text: str = ""  # one more line (track state, the last event)


def annotate(image: np.ndarray, info: ViewInfo) -> np.ndarray:
    import cv2

    img = image.copy() if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    b = info.box
    if b is not None:
        colour = (0, 220, 255) if info.awaiting else (0, 255, 0) if info.phase in ("ENGAGE", "PASS") else (180, 180,
                                                                                                           180)
        x0, y0, x1, y1 = (round(v) for v in b.xyxy)
        cv2.rectangle(img, (x0, y0), (x1, y1), colour, 2)
        if info.awaiting:
            cv2.putText(img, "CONFIRM?", (x0, max(14, y0 - 6)), cv2.FONT_HERSHEY_SIMPLEX, 0.55, colour, 2,
                        cv2.LINE_AA)
    lines = [f"{info.phase}" + ("  candidate awaiting confirmation" if info.awaiting else ""), info.text]
    for i, s in enumerate(x for x in lines if x):
        cv2.putText(img, s, (8, 20 + 20 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 2, cv2.LINE_AA)
    return img


class LiveView:
    """``start()``, then ``offer(image, info)`` per frame (never blocks), ``close()`` at the end."""

    def __init__(self, address: str = "127.0.0.1", port: int = 0, max_fps: float = 15.0, quality: int = 70) -> None:
        self.address, self.port, self.max_fps, self.quality = address, int(port), float(max_fps), int(quality)
        self._cv = threading.Condition()
        self._slot: tuple[np.ndarray, ViewInfo] | None = None  # the newest unread frame (one slot)
        self._jpeg: bytes | None = None
        self._seq = 0  # number of the newest JPEG
        self._closed = False
        self.offered = self.dropped = self.taken = self.encoded = 0  # offered == dropped + taken (+ 1 unread)
        self._server: ThreadingHTTPServer | None = None
        self._threads: list[threading.Thread] = []

    @property
    def url(self) -> str:
        return f"http://{self.address}:{self.port}/"

    def start(self) -> LiveView:
        view = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args: Any) -> None:  # no stderr line per request
                pass

            def do_GET(self) -> None:
                path = self.path.split("?")[0]
                if path == "/":
                    self._send(200, "text/html", PAGE)
                elif path == "/frame.jpg":
                    jpg = view.wait_jpeg(-1, 2.0)[1]
                    self._send(200, "image/jpeg", jpg) if jpg else self._send(503, "text/plain", b"no frame yet")
                elif path == "/stream":
                    self._stream()
                else:
                    self._send(404, "text/plain", b"not found")

            def _send(self, code: int, ctype: str, body: bytes) -> None:
                self.send_response(code)
                self.send_header("Content-Type", ctype)
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                self.wfile.write(body)

            def _stream(self) -> None:
                self.send_response(200)
                self.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY}")
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                seq = -1
                with contextlib.suppress(OSError):  # the client went away
                    while not view._closed:
                        seq, jpg = view.wait_jpeg(seq, 1.0)
                        if jpg is None:
                            continue
                        self.wfile.write(f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(jpg)}"
                                         "\r\n\r\n".encode() + jpg + b"\r\n")
                        self.wfile.flush()

        self._server = ThreadingHTTPServer((self.address, self.port), Handler)
        self._server.daemon_threads = True
        self.port = self._server.server_address[1]
        for name, target in (("liveview:http", self._server.serve_forever), ("liveview:encode", self._encode_loop)):
            th = threading.Thread(target=target, name=name, daemon=True)
            th.start()
            self._threads.append(th)
        return self

    def offer(self, image: np.ndarray | None, info: ViewInfo) -> None:
        """The frame loop's only call: O(1), no copy, no encoding; an unread older frame is dropped."""
        if image is None or self._closed:
            return
        with self._cv:
            self.offered += 1
            if self._slot is not None:
                self.dropped += 1
            self._slot = (image, info)
            self._cv.notify_all()

    def wait_jpeg(self, after: int, timeout: float) -> tuple[int, bytes | None]:
        """The newest JPEG newer than number ``after`` (waits up to ``timeout`` s): (its number, bytes or None)."""
        with self._cv:
            self._cv.wait_for(lambda: self._seq > after or self._closed, timeout)
            return (self._seq, self._jpeg) if self._seq > after else (after, None)

    def _encode_loop(self) -> None:
        import cv2

        period = 1.0 / self.max_fps
        last = -1e9
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._slot is not None or self._closed)
                if self._closed:
                    return
                item, self._slot = self._slot, None
                self.taken += 1
            assert item is not None
            ok, buf = cv2.imencode(".jpg", annotate(item[0], item[1]), [cv2.IMWRITE_JPEG_QUALITY, self.quality])
            if ok:
                with self._cv:
                    self._jpeg, self._seq = buf.tobytes(), self._seq + 1
                    self.encoded += 1
                    self._cv.notify_all()
            wait = period - (time.monotonic() - last)
            last = time.monotonic()
            if wait > 0:
                time.sleep(wait)  # at most max_fps encodes: frames offered meanwhile replace each other

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._cv.notify_all()
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
        for th in self._threads:
            th.join(timeout=2.0)


def from_config(cfg: Any) -> LiveView | None:
    """The live view of ``app.live_view``, started; None when it is off."""
    lv = cfg.app.live_view
    if not lv.enabled:
        return None
    return LiveView(lv.address, lv.port, lv.max_fps, lv.quality).start()
