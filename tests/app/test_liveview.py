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

from companion.app.liveview import BOUNDARY, HEADER, RIVAL_BGR, LiveView, ViewInfo, annotate, pack_header, unpack_header
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


def _magenta(region: np.ndarray) -> int:
    """Rows of ``region`` with a pixel near the rival's colour (after JPEG: a tolerance)."""
    near = np.abs(region.astype(int) - RIVAL_BGR).max(axis=-1) < 90
    return int(near.any(axis=1).sum())


def test_header_round_trip() -> None:
    info = ViewInfo(BoundingBox(160, 120, 80, 60), "ENGAGE", True, "tracking, é")
    seq, shape, back = unpack_header(pack_header(7, (240, 320, 3), info))
    assert (seq, shape) == (7, (240, 320, 3))
    assert back.box.xyxy == (120.0, 90.0, 200.0, 150.0)  # cx -+ w/2, cy -+ h/2
    assert (back.phase, back.awaiting, back.text) == ("ENGAGE", True, "tracking, é")
    assert unpack_header(pack_header(1, (10, 20), ViewInfo()))[1:] == ((10, 20), ViewInfo())
    assert back.rival is None and back.box.confidence == 1.0  # no rival given: none decoded


def test_header_round_trip_with_a_rival() -> None:
    rival = BoundingBox(40, 30, 20, 10, 0.42)
    box = BoundingBox(160, 120, 80, 60, 0.87, rival=rival)
    _, _, back = unpack_header(pack_header(2, (240, 320, 3), ViewInfo(box, "ACQUIRE", True, "x", box.rival)))
    assert back.rival.xyxy == (30.0, 25.0, 50.0, 35.0) and back.rival.confidence == 0.42
    assert back.box.xyxy == (120.0, 90.0, 200.0, 150.0) and back.box.confidence == 0.87
    assert (back.phase, back.awaiting, back.text) == ("ACQUIRE", True, "x")
    # the box's own .rival is not what is sent: only ViewInfo.rival (the frame loop fills it from the box)
    assert unpack_header(pack_header(3, (240, 320, 3), ViewInfo(box)))[2].rival is None


def test_a_header_of_another_layout_is_refused() -> None:
    raw = bytearray(pack_header(1, (10, 20), ViewInfo()))
    raw[0] ^= 0xFF  # another version: the view stops with one line rather than drawing garbage
    with pytest.raises(ValueError, match="version"):
        unpack_header(bytes(raw))
    with pytest.raises(ValueError):
        unpack_header(bytes(HEADER.size - 1))


RIVAL = BoundingBox(250, 60, 80, 50, 0.42)  # x 210..290, y 35..85


def _is(img: np.ndarray, bgr: tuple[int, int, int]) -> np.ndarray:
    return (np.abs(img.astype(int) - bgr).max(axis=-1) == 0)


def test_annotate_draws_the_rival_dashed_in_its_own_colour() -> None:
    frame = np.full((240, 320, 3), 60, np.uint8)
    box = BoundingBox(100, 150, 80, 60, 0.87)  # x 60..140, y 120..180: away from the rival
    with_rival = annotate(frame, ViewInfo(box, "ACQUIRE", True, "tracking", RIVAL))
    without = annotate(frame, ViewInfo(box, "ACQUIRE", True, "tracking"))
    rival_px = _is(with_rival, RIVAL_BGR)
    assert not _is(without, RIVAL_BGR).any()  # no rival: not one pixel of its colour
    # each edge (2 px at x 210 / 290, y 35 / 85) is dashed in the rival's colour: much of it, not all of it
    edges = {"left": rival_px[35:86, 209:212].any(axis=1), "right": rival_px[35:86, 289:292].any(axis=1),
             "top": rival_px[34:37, 210:291].any(axis=0), "bottom": rival_px[84:87, 210:291].any(axis=0)}
    for name, on in edges.items():
        assert 0.45 < on.mean() < 0.9, (name, on.mean())
    # its inside untouched, its label ("other 0.42") above it in its colour, nothing of it elsewhere
    assert not rival_px[40:80, 215:285].any()
    assert rival_px[15:34, 210:300].sum() > 30
    assert rival_px.sum() == rival_px[15:90, 205:300].sum()
    # the held box is drawn as before (its yellow on its left edge)
    assert _is(with_rival[130:170, 59:62], (0, 220, 255)).mean() > 0.5


def test_annotate_labels_the_held_box_with_its_confidence() -> None:
    frame = np.full((240, 320, 3), 60, np.uint8)

    def label(conf: float) -> np.ndarray:  # the text above the box (x 60.., y 120)
        return annotate(frame, ViewInfo(BoundingBox(100, 150, 80, 60, conf), "ENGAGE"))[95:120, 55:160]

    assert _is(label(0.87), (0, 255, 0)).sum() > 20  # a label in the box's green
    assert (label(0.87) != label(0.12)).any()  # which shows the confidence: another number, other pixels


def test_annotate_skips_a_box_it_cannot_draw() -> None:
    frame = np.full((60, 80, 3), 60, np.uint8)
    nan = BoundingBox(float("nan"), 30, 10, 10)
    img = annotate(frame, ViewInfo(nan, "", False, "", nan))  # a detector's NaN: no exception, nothing drawn
    assert (img == frame).all()


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
        assert _magenta(img[40:90, 248:252]) == 0  # no rival given: none drawn where the next one will be
        # a candidate awaiting confirmation is yellow, and /frame.jpg serves a fresh frame; the rival in view with
        # it is drawn dashed in its colour at its place (left edge x 250, y 50..80)
        rival = BoundingBox(280, 65, 60, 30, 0.42)
        with Feeder(lv, frame, ViewInfo(BoundingBox(160, 120, 80, 60), "ACQUIRE", True, "", rival)):
            conn = http.client.HTTPConnection("127.0.0.1", lv.port, timeout=20)
            conn.request("GET", "/frame.jpg")
            body = conn.getresponse().read()
        img2 = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR)
        px = img2[100:140, 119:122].reshape(-1, 3).mean(axis=0)
        assert px[2] > 180 and px[1] > 150 and px[0] < 100, px  # BGR yellow-orange
        assert _magenta(img2[50:81, 248:253]) >= 12, _magenta(img2[50:81, 248:253])  # rows of the dashed edge
        assert _magenta(img2[100:140, 100:220]) == 0  # and not on or around the held box
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
