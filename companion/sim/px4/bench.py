"""Benchmark of the simulated PX4 + the vehicle link through real mavsdk over UDP (reported, never asserted).

    python -m companion.sim.px4.bench [--seconds 5]

Measures: connect / health / arm / takeoff / offboard-start times, setpoint latency (``set_setpoint``
call -> datagram parsed by the sim), attitude telemetry latency (sim sends -> link cache) and rate,
and the sim thread's load (busy fraction of one core, skipped physics steps).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import time
from types import SimpleNamespace
from typing import Any

import numpy as np


def _pct(xs: list[float], q: float) -> float:
    return float(np.percentile(xs, q)) if xs else math.nan


async def _bench(seconds: float) -> dict[str, Any]:
    from companion.app.link import VehicleLink
    from companion.config import Config
    from companion.sim.px4.realtime import SimPX4

    cfg = Config()
    out: dict[str, Any] = {}
    with SimPX4(cfg, px4_params={"MPC_TKO_SPEED": 3.0, "MIS_TAKEOFF_ALT": 3.0}) as sim:
        link = VehicleLink.from_config(cfg)
        t = time.monotonic()
        await link.connect(sim.url_for_mavsdk, 5.0)
        out["connect_s"] = time.monotonic() - t
        t = time.monotonic()
        await link.wait_healthy(10.0)
        out["healthy_s"] = time.monotonic() - t
        t = time.monotonic()
        hover = await link.hover_thrust()
        out["param_read_s"] = time.monotonic() - t
        t = time.monotonic()
        await link.arm()
        out["arm_s"] = time.monotonic() - t
        t = time.monotonic()
        await link.takeoff(3.0, 20.0)
        out["takeoff_3m_s"] = time.monotonic() - t
        yaw = math.degrees(math.atan2(link.attitude.R_ned_frd[1, 0], link.attitude.R_ned_frd[0, 0]))
        t = time.monotonic()
        await link.start_offboard(SimpleNamespace(roll_deg=0.0, pitch_deg=0.0, yaw_deg=yaw, thrust=hover))
        out["offboard_start_s"] = time.monotonic() - t

        sp_lat: list[float] = []
        tel_lat: list[float] = []
        seen: set[float] = set()
        t_end = time.monotonic() + seconds
        k = 0
        while time.monotonic() < t_end:
            k += 1
            thrust = hover + 1e-4 * (k % 50)  # a value the sim can recognise (float32 on the wire)
            t_call = time.monotonic()
            await link.set_setpoint(SimpleNamespace(roll_deg=0.0, pitch_deg=0.0, yaw_deg=yaw, thrust=thrust))
            deadline = t_call + 0.05
            while time.monotonic() < deadline:
                if abs(sim.last_setpoint()[2] - np.float32(thrust)) < 1e-6:
                    sp_lat.append(sim.last_setpoint_rx_monotonic() - t_call)
                    break
                await asyncio.sleep(0.0005)
            att = link.attitude
            if att.t_vehicle not in seen:
                seen.add(att.t_vehicle)
                tel_lat.append(att.t_rx - sim.monotonic_of(att.t_vehicle))
            await asyncio.sleep(max(0.0, t_call + 1 / 30 - time.monotonic()))
        out["setpoints_sent"] = k
        out["setpoint_latency_ms_median"] = 1e3 * _pct(sp_lat, 50)
        out["setpoint_latency_ms_p95"] = 1e3 * _pct(sp_lat, 95)
        out["setpoints_matched"] = len(sp_lat)
        out["attitude_latency_ms_median"] = 1e3 * _pct(tel_lat, 50)
        out["attitude_latency_ms_p95"] = 1e3 * _pct(tel_lat, 95)
        stamps: set[float] = set()
        t0 = time.monotonic()
        while time.monotonic() - t0 < 1.0:  # distinct attitude samples reaching the cache in 1 s
            stamps.add(link.attitude.t_vehicle)
            await asyncio.sleep(0.002)
        out["attitude_rate_hz"] = len(stamps) / (time.monotonic() - t0)
        await link.stop_offboard()
        t = time.monotonic()
        await link.close()
        out["close_s"] = time.monotonic() - t
        out.update({f"sim_{k}": v for k, v in sim.stats().items()})
    return out


def benchmark(seconds: float = 5.0) -> dict[str, Any]:
    return asyncio.run(_bench(seconds))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m companion.sim.px4.bench", description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0, help="offboard streaming period to measure")
    args = ap.parse_args(argv)
    res = benchmark(args.seconds)
    print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in res.items()}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
