"""The live view's own process (started by companion/app/liveview.py, never by hand): serves the annotated stream.

    python -m companion.app.liveview_proc SOCK_FD MEM_FD WAKE_FD SIZE MAX_FPS QUALITY NICE

SOCK_FD is the listening socket, MEM_FD the shared frame slot (layout in liveview.py), WAKE_FD the read end of the
flight's wake-up pipe (its end of file means: the flight is done, exit). Runs niced; asks for a frame (WANT) only
while a client is connected and at most MAX_FPS times a second.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import select
import signal
import socket
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

# Only the standard library at the top: the process lowers its priority (main) before it imports anything heavy
# (numpy with companion.app.liveview, cv2 when the first frame arrives), so even its start-up yields to the flight.


class Hub:
    """The newest JPEG and the number of clients waiting for frames, shared by the handler threads."""

    def __init__(self) -> None:
        self.cv = threading.Condition()
        self.jpeg: bytes | None = None
        self.seq = 0
        self.clients = 0
        self.closed = False

    def publish(self, jpg: bytes) -> None:
        with self.cv:
            self.jpeg, self.seq = jpg, self.seq + 1
            self.cv.notify_all()

    def wait_jpeg(self, after: int, timeout: float) -> tuple[int, bytes | None]:
        with self.cv:
            self.cv.wait_for(lambda: self.seq > after or self.closed, timeout)
            return (self.seq, self.jpeg) if self.seq > after else (after, None)

    @contextlib.contextmanager
    def client(self) -> Any:
        with self.cv:
            self.clients += 1
        try:
            yield
        finally:
            with self.cv:
                self.clients -= 1


def make_server(sock: socket.socket, hub: Hub) -> ThreadingHTTPServer:
    from companion.app.liveview import BOUNDARY, PAGE

    class Handler(BaseHTTPRequestHandler):
        def log_message(self, *args: Any) -> None:  # no stderr line per request
            pass

        def do_GET(self) -> None:
            path = self.path.split("?")[0]
            if path == "/":
                self._send(200, "text/html", PAGE)
            elif path == "/frame.jpg":
                with hub.client():  # a fresh frame, not the one left from the last client
                    jpg = hub.wait_jpeg(hub.seq, 3.0)[1]
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
            seq = hub.seq
            with contextlib.suppress(OSError), hub.client():  # OSError: the client went away
                while not hub.closed:
                    seq, jpg = hub.wait_jpeg(seq, 1.0)
                    if jpg is None:
                        continue
                    self.wfile.write(f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(jpg)}"
                                     "\r\n\r\n".encode() + jpg + b"\r\n")
                    self.wfile.flush()

    server = ThreadingHTTPServer(sock.getsockname()[:2], Handler, bind_and_activate=False)
    server.socket.close()
    server.socket = sock  # bound and listening already (by the flight process)
    server.daemon_threads = True
    return server


def run(mem: mmap.mmap, wake_fd: int, hub: Hub, max_fps: float, quality: int) -> None:
    """Frames in, JPEGs out, until the flight closes its end of the wake pipe."""
    import numpy as np

    from companion.app.liveview import DATA, HEADER, IDLE, READY, WANT, annotate, unpack_header

    period = 1.0 / max_fps
    last = -1e9
    while True:
        now = time.monotonic()
        if hub.clients > 0 and mem[0] == IDLE and now - last >= period:
            mem[0] = WANT  # encode only while someone watches, at most max_fps
        timeout = max(0.0, period - (now - last)) if hub.clients > 0 and mem[0] == IDLE else 0.5
        if not select.select([wake_fd], [], [], timeout)[0]:
            continue
        if not os.read(wake_fd, 4096):
            return  # the flight closed the pipe (or died)
        if mem[0] != READY:
            continue
        _, shape, info = unpack_header(mem[1:1 + HEADER.size])
        image = np.ndarray(shape, np.uint8, buffer=mem, offset=DATA).copy()
        mem[0] = IDLE
        last = time.monotonic()
        if hub.clients > 0:
            import cv2  # here, not at start: without a client the view never loads it

            ok, buf = cv2.imencode(".jpg", annotate(image, info), [cv2.IMWRITE_JPEG_QUALITY, quality])
            if ok:
                hub.publish(buf.tobytes())


def main(argv: list[str]) -> int:
    sock_fd, mem_fd, wake_fd, size = (int(a) for a in argv[:4])
    max_fps, quality, nice = float(argv[4]), int(argv[5]), int(argv[6])
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the flight ends the view, not the terminal
    with contextlib.suppress(OSError):  # below the flight: drawing and encoding take only CPU the flight leaves
        os.nice(max(0, nice - os.nice(0)))  # (already niced by the nice command where there is one)
    mem = mmap.mmap(mem_fd, size)
    os.close(mem_fd)
    hub = Hub()
    server = make_server(socket.socket(fileno=sock_fd), hub)
    threading.Thread(target=server.serve_forever, name="liveview:http", daemon=True).start()
    try:
        run(mem, wake_fd, hub, max_fps, quality)
    except Exception as e:  # one line, not a traceback in the flight's terminal
        print(f"live view process: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    finally:
        with hub.cv:
            hub.closed = True
            hub.cv.notify_all()
        server.shutdown()
        server.server_close()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
