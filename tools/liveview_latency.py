"""Frame -> setpoint latency of the flight app with the live view off and on (a client reading the stream).

    PYTHONPATH=. python tools/liveview_latency.py --pairs 3

Each flight: the simulated PX4 (real mavsdk over UDP), the synthetic camera rendering images through the
detector (app.synthetic.render=image), take-off, one gate, land. Off and on alternate so machine load hits both.
Prints per flight the outcome, the median / p95 / max of app.stats.latencies_ms and the frames the view took,
then the pooled figures and the outcomes per setting, and the machine's load average before and after.
"""

from __future__ import annotations

import argparse
import asyncio
import http.client
import os
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "app"))
from flighthelpers import FAST_PX4, make_config, run_flight

from companion.config import load_config
from companion.sim.px4 import SimPX4


def _reader(port: int, stop: threading.Event, count: list[int]) -> None:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
    try:
        conn.request("GET", "/stream")
        r = conn.getresponse()
        while not stop.is_set():
            line = r.readline()
            if not line:
                break
            count[0] += line.startswith(b"--")
    except OSError:
        pass  # the flight ended and the server with it
    finally:
        conn.close()


def flight(live: bool, tmp: Path) -> tuple[list[float], int, str, str]:
    px4 = SimPX4(load_config([], ["sim.seed=7"]), px4_params=FAST_PX4)
    px4.start()
    stop, count, app_ref = threading.Event(), [0], []
    try:
        sets = ["app.synthetic.render=image", "app.engage=auto"]
        if live:
            sets += ["app.live_view.enabled=true", "app.live_view.port=0"]
        cfg = make_config(tmp, px4.url_for_mavsdk, *sets)

        async def side(app):  # type: ignore[no-untyped-def]
            app_ref.append(app)
            while live and getattr(app, "_live", None) is None:
                await asyncio.sleep(0.05)
            if live:
                threading.Thread(target=_reader, args=(app._live.port, stop, count), daemon=True).start()

        reason, _, _ = run_flight(cfg, side)
    finally:
        stop.set()
        px4.stop()
    lv = getattr(app_ref[0], "_live", None)
    took = f"; view took {lv.sent} of {lv.offered} frames" if lv is not None else ""
    return list(app_ref[0].stats.latencies_ms), count[0], reason.name, took


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--pairs", type=int, default=3)
    a = ap.parse_args()
    pooled: dict[bool, list[float]] = {False: [], True: []}
    outcomes: dict[bool, list[str]] = {False: [], True: []}
    print(f"load average at start: {' '.join(f'{v:.1f}' for v in os.getloadavg())}", flush=True)
    for i in range(a.pairs):
        for live in (False, True):
            with tempfile.TemporaryDirectory() as d:
                lat, parts, outcome, took = flight(live, Path(d))
            outcomes[live].append(outcome)
            x = np.array(lat)
            if not len(x):
                print(f"pair {i} live_view={live}: {outcome}, no setpoints (never engaged)", flush=True)
                continue
            pooled[live] += lat
            print(f"pair {i} live_view={'on ' if live else 'off'}: {outcome}, n={len(x)} median {np.median(x):.2f} "
                  f"ms, p95 {np.percentile(x, 95):.2f}, max {x.max():.2f}; stream parts read {parts}{took}; "
                  f"load {os.getloadavg()[0]:.1f}", flush=True)
    for live, lat in pooled.items():
        x = np.array(lat)
        if not len(x):
            continue
        rng = np.random.default_rng(0)
        boots = [np.median(rng.choice(x, len(x))) for _ in range(2000)]
        lo, hi = np.percentile(boots, [2.5, 97.5])
        print(f"live_view={'on ' if live else 'off'}: n={len(x)} median {np.median(x):.2f} ms (95% CI {lo:.2f}-"
              f"{hi:.2f}), p95 {np.percentile(x, 95):.2f}, max {x.max():.2f}; outcomes {', '.join(outcomes[live])}")
    print(f"load average at end: {' '.join(f'{v:.1f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
