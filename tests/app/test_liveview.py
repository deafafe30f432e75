"""The live view (companion/app/liveview.py): a real HTTP client reads the MJPEG stream and decodes a JPEG."""

from __future__ import annotations

import http.client
import threading

import cv2
import numpy as np
import pytest

from companion.app.liveview import BOUNDARY, LiveView, ViewInfo
from perception.types import BoundingBox


def read_stream_jpeg(host: str, port: int, timeout: float = 10.0) -> tuple[str, np.ndarray]:
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


def test_stream_serves_the_annotated_frame() -> None:
    lv = LiveView("127.0.0.1", 0, max_fps=30).start()
    try:
        assert lv.url.startswith("http://127.0.0.1:")
        frame = np.full((240, 320, 3), 60, np.uint8)
        lv.offer(frame, ViewInfo(BoundingBox(160, 120, 80, 60), "ENGAGE", False, "tracking"))
        ctype, img = read_stream_jpeg("127.0.0.1", lv.port)
        assert ctype == f"multipart/x-mixed-replace; boundary={BOUNDARY}"
        assert img.shape == (240, 320, 3)
        # the engaged box is drawn in green on its edge (x0 = 120), the inside stays the grey frame
        edge = img[100:140, 119:122].reshape(-1, 3).mean(axis=0)
        assert edge[1] > 180 and edge[0] < 100 and edge[2] < 100, edge
        assert abs(float(img[120, 160].mean()) - 60) < 12
        # a candidate awaiting confirmation is yellow, and /frame.jpg serves the newest frame
        lv.offer(frame, ViewInfo(BoundingBox(160, 120, 80, 60), "ACQUIRE", True))
        seq0 = lv.encoded
        lv.wait_jpeg(seq0, 5.0)
        conn = http.client.HTTPConnection("127.0.0.1", lv.port, timeout=10)
        conn.request("GET", "/frame.jpg")
        body = conn.getresponse().read()
        img2 = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR)
        px = img2[100:140, 119:122].reshape(-1, 3).mean(axis=0)
        assert px[2] > 180 and px[1] > 150 and px[0] < 100, px  # BGR yellow-orange
        conn.request("GET", "/nothing")
        assert conn.getresponse().status == 404
        conn.close()
    finally:
        lv.close()


def test_offer_never_waits_for_a_client_and_drops_unread_frames() -> None:
    """A client that connects and never reads: the frame loop's offer() still returns, frames are replaced in the
    one-slot mailbox (counted), and the accounting holds."""
    lv = LiveView("127.0.0.1", 0, max_fps=5).start()
    stalled = http.client.HTTPConnection("127.0.0.1", lv.port, timeout=5)
    try:
        stalled.request("GET", "/stream")  # never read
        frame = np.zeros((480, 640, 3), np.uint8)
        done = threading.Event()

        def loop() -> None:
            for k in range(200):
                lv.offer(frame, ViewInfo(BoundingBox(320, 240, 40 + k % 50, 40), "ENGAGE"))
            done.set()

        th = threading.Thread(target=loop)
        th.start()
        th.join(timeout=30)
        assert done.is_set()
        with lv._cv:
            pending = int(lv._slot is not None)
            assert lv.offered == 200 == lv.dropped + lv.taken + pending
    finally:
        stalled.close()
        lv.close()


def test_binds_loopback_by_default() -> None:
    from companion.config import load_config

    cfg = load_config([], ["app.live_view.enabled=true", "app.live_view.port=0"])
    from companion.app.liveview import from_config

    lv = from_config(cfg)
    assert lv is not None
    try:
        assert lv._server is not None and lv._server.server_address[0] == "127.0.0.1"
    finally:
        lv.close()
    assert from_config(load_config()) is None


@pytest.mark.parametrize("bad", ["app.live_view.port=70000", "app.live_view.quality=0"])
def test_bad_config_is_refused(bad: str) -> None:
    from companion.config import load_config
    from companion.configbase import ConfigError

    with pytest.raises(ConfigError, match="live_view"):
        load_config([], [bad])
