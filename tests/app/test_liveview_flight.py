"""A hard failure of the live view never touches the flight: its process killed mid-flight, the flight logs one
line and flies on to a normal end (simulated PX4 over real mavsdk, rendered frames through the detector)."""

from __future__ import annotations

import asyncio
import http.client
import os
import signal
import threading

import pytest
from flighthelpers import make_config, run_flight

from companion.app.states import Reason
from companion.flightlog import read_flight

pytestmark = pytest.mark.timeout(150)


def _detector_missing() -> str | None:
    from companion.app.assemble import detector_available
    from companion.config import load_config

    return detector_available(load_config())


def _read_stream(port: int, stop: threading.Event) -> None:
    try:
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
        conn.request("GET", "/stream")
        r = conn.getresponse()
        while not stop.is_set() and r.readline():
            pass
    except OSError:
        pass  # the view was killed: its socket with it


@pytest.mark.skipif(_detector_missing() is not None, reason="the shipped gate detector (ONNX) is not available")
def test_killing_the_view_process_mid_flight_leaves_the_flight_ok(sim, tmp_path):
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.synthetic.render=image", "app.synthetic.motion=linear_slow",
                      "app.live_view.enabled=true", "app.live_view.port=0")
    stop = threading.Event()
    seen: dict[str, object] = {}

    async def kill_the_view(app) -> None:  # type: ignore[no-untyped-def]
        while getattr(app, "_live", None) is None:
            await asyncio.sleep(0.05)
        lv = app._live
        threading.Thread(target=_read_stream, args=(lv.port, stop), daemon=True).start()
        while lv.sent < 3 and lv.offered < 60:  # frames flowing to the client (or 2 s of frames: a slow machine)
            await asyncio.sleep(0.05)
        seen["sent"] = lv.sent
        os.kill(lv.proc.pid, signal.SIGKILL)
        while lv.failed is None:  # the frame loop notices on its next frames
            await asyncio.sleep(0.05)
        seen["failed"] = lv.failed

    try:
        reason, folder, summary = run_flight(cfg, kill_the_view)
    finally:
        stop.set()
    assert seen.get("failed") is not None, seen
    assert reason is Reason.OK, summary
    f = read_flight(folder)
    assert f.state_path()[-1] == "SAFE_LANDED" and f.summary["truth"]["through"] == 1
    stopped = [t for t in f["events"]["text"] if "live view" in t]
    assert stopped[0].startswith("live view at http://127.0.0.1:")
    assert len(stopped) == 2 and stopped[1].startswith("live view stopped"), stopped
