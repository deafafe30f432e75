"""The live view (companion/app/liveview.py + liveview_proc.py, its own process): a real HTTP client reads the
MJPEG stream and decodes a JPEG; the frame loop's side never waits and copies nothing without a client; a view
that cannot start or dies logs one line and the caller goes on."""

from __future__ import annotations

import http.client
import os
import signal
import socket

import cv2
import numpy as np
import pytest
from liveviewhelpers import Feeder

from companion.app.liveview import BOUNDARY, LiveView, ViewInfo, pack_header, unpack_header
from perception.types import BoundingBox

pytestmark = pytest.mark.timeout(60)


def read_stream_jpeg(host: str, port: int, timeout: float = 20.0) -> tuple[str, np.ndarray]:
    """GET /stream, parse the first multipart part, decode its JPEG; returns (content type, image)."""
    conn = http.client.HTTPConnection(host, port, timeout=timeout)
    conn.request("GET", "/stream")
    r = conn.getresponse()
    assert r.status == 200
    ctype = r.getheader("Content-Type")
    assert r.readline().strip() == f"--{BOUNDARY}".encode()
    headers = {}
    while (line := r.readline().strip()):
        k, v = line.decode().split(":", 1)
        headers[k.strip().lower()] = v.strip()
    assert headers["content-type"] == "image/jpeg"
    data = r.read(int(headers["content-length"]))
    conn.close()
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None
    return ctype, img


def test_header_round_trip() -> None:
    info = ViewInfo(BoundingBox(160, 120, 80, 60), "ENGAGE", True, "tracking, é")
    seq, shape, back = unpack_header(pack_header(7, (240, 320, 3), info))
    assert (seq, shape) == (7, (240, 320, 3))
    assert back.box.xyxy == (120.0, 90.0, 200.0, 150.0)  # cx -+ w/2, cy -+ h/2
    assert (back.phase, back.awaiting, back.text) == ("ENGAGE", True, "tracking, é")
    assert unpack_header(pack_header(1, (10, 20), ViewInfo()))[1:] == ((10, 20), ViewInfo())


def test_stream_serves_the_annotated_frame() -> None:
    lv = LiveView("127.0.0.1", 0, max_fps=30).start()
    try:
        assert lv.url.startswith("http://127.0.0.1:")
        frame = np.full((240, 320, 3), 60, np.uint8)
        with Feeder(lv, frame, ViewInfo(BoundingBox(160, 120, 80, 60), "ENGAGE", False, "tracking")):
            ctype, img = read_stream_jpeg("127.0.0.1", lv.port)
        assert ctype == f"multipart/x-mixed-replace; boundary={BOUNDARY}"
        assert img.shape == (240, 320, 3)
        # the engaged box is drawn in green on its edge (x0 = 120), the inside stays the grey frame
        edge = img[100:140, 119:122].reshape(-1, 3).mean(axis=0)
        assert edge[1] > 180 and edge[0] < 100 and edge[2] < 100, edge
        assert abs(float(img[120, 160].mean()) - 60) < 12
        # a candidate awaiting confirmation is yellow, and /frame.jpg serves a fresh frame
        with Feeder(lv, frame, ViewInfo(BoundingBox(160, 120, 80, 60), "ACQUIRE", True)):
            conn = http.client.HTTPConnection("127.0.0.1", lv.port, timeout=20)
            conn.request("GET", "/frame.jpg")
            body = conn.getresponse().read()
        img2 = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR)
        px = img2[100:140, 119:122].reshape(-1, 3).mean(axis=0)
        assert px[2] > 180 and px[1] > 150 and px[0] < 100, px  # BGR yellow-orange
        conn.request("GET", "/nothing")
        assert conn.getresponse().status == 404
        conn.close()
        assert lv.sent >= 2 and lv.offered == lv.sent + lv.skipped and lv.failed is None
    finally:
        lv.close()
    assert lv.proc is not None and lv.proc.poll() is not None  # closed: the process is gone


def test_offer_copies_nothing_without_a_client_and_never_waits_for_a_stalled_one() -> None:
    lv = LiveView("127.0.0.1", 0, max_fps=5).start()
    frame = np.zeros((480, 640, 3), np.uint8)
    try:
        for k in range(200):  # nobody watching: the view never asks, no frame is copied
            lv.offer(frame, ViewInfo(BoundingBox(320, 240, 40 + k % 50, 40), "ENGAGE"))
        assert (lv.offered, lv.sent, lv.skipped) == (200, 0, 200)
        stalled = http.client.HTTPConnection("127.0.0.1", lv.port, timeout=5)
        stalled.request("GET", "/stream")  # never read: the view's socket to it fills up
        for k in range(2000):  # returns every time (nothing here can wait on the client)
            lv.offer(frame, ViewInfo(BoundingBox(320, 240, 40 + k % 50, 40), "ENGAGE"))
        assert lv.offered == 2200 == lv.sent + lv.skipped and lv.failed is None
        stalled.close()
    finally:
        lv.close()


def test_a_dead_view_process_logs_one_line_and_offer_goes_on() -> None:
    errors: list[str] = []
    lv = LiveView("127.0.0.1", 0, max_fps=30, on_error=errors.append).start()
    frame = np.full((120, 160, 3), 90, np.uint8)
    info = ViewInfo(BoundingBox(80, 60, 40, 30), "ENGAGE")
    try:
        with Feeder(lv, frame, info):
            read_stream_jpeg("127.0.0.1", lv.port)  # running and serving
        assert lv.proc is not None
        os.kill(lv.proc.pid, signal.SIGKILL)
        lv.proc.wait(timeout=10)
        for _ in range(50):
            lv.offer(frame, info)
        assert len(errors) == 1 and errors[0].startswith("live view stopped"), errors
        assert lv.failed is not None
        with pytest.raises(OSError):  # its port is closed with it
            socket.create_connection(("127.0.0.1", lv.port), timeout=5).close()
    finally:
        lv.close()


def test_a_taken_port_logs_one_line_and_returns_none() -> None:
    from companion.app.liveview import from_config
    from companion.config import load_config

    taken = socket.create_server(("127.0.0.1", 0))
    try:
        port = taken.getsockname()[1]
        errors: list[str] = []
        cfg = load_config([], ["app.live_view.enabled=true", f"app.live_view.port={port}"])
        assert from_config(cfg, errors.append) is None
        assert len(errors) == 1 and f"127.0.0.1:{port}" in errors[0] and "flying on" in errors[0], errors
    finally:
        taken.close()


def test_binds_loopback_by_default() -> None:
    from companion.app.liveview import from_config
    from companion.config import load_config

    cfg = load_config([], ["app.live_view.enabled=true", "app.live_view.port=0"])
    lv = from_config(cfg)
    assert lv is not None
    try:
        assert lv.sockname[0] == "127.0.0.1"
        conn = http.client.HTTPConnection("127.0.0.1", lv.port, timeout=20)
        conn.request("GET", "/")
        assert b"<img src='/stream'" in conn.getresponse().read()
        conn.close()
    finally:
        lv.close()
    assert from_config(load_config()) is None


@pytest.mark.parametrize("bad", ["app.live_view.port=70000", "app.live_view.quality=0"])
def test_bad_config_is_refused(bad: str) -> None:
    from companion.config import load_config
    from companion.configbase import ConfigError

    with pytest.raises(ConfigError, match="live_view"):
        load_config([], [bad])
