"""Benchmark of the flight app: frame -> setpoint latency and CPU use on a short simulated flight.

The simulated PX4 runs in its own process (so its physics does not count as the app's CPU), the
real mavsdk talks to it over UDP, and the synthetic camera feeds the app: rendered frames through
the detector when the shipped model exists, else the geometric camera. Latency is measured from
the moment a frame is available to the app (rendering = exposure and read-out, excluded) to the
return of the setpoint call: perception + LOS + controller + safety + the mavsdk send.
"""

from __future__ import annotations

import asyncio
import tempfile
from pathlib import Path
from typing import Any

FAST_PX4 = ["--param", "MPC_TKO_SPEED=3.0", "--param", "MPC_LAND_SPEED=1.5"]


def _detector_available(cfg: Any) -> bool:
    try:
        from perception.detector import Detector

        Detector.from_config(cfg.perception)
        return True
    except Exception:  # a missing/broken model: bench the geometric camera instead, and say so
        return False


def bench_app(quick: bool = False, cfg: Any = None, render: str | None = None) -> dict[str, Any]:
    """Fly one simulated flight (take-off 5 m, linear-fast gate 25 m away) and report the app's numbers."""
    from companion.app.session import fly
    from companion.config import load_config
    from companion.configbase import deep_merge
    from companion.sim.process import SimPX4Process

    base = cfg if cfg is not None else load_config()
    if render is None:
        render = "image" if _detector_available(base) else "geometric"
    with tempfile.TemporaryDirectory(prefix="companion-bench-") as tmp, \
            SimPX4Process(overrides=[f"sim.seed={base.sim.seed}"], extra=FAST_PX4) as px4:
        overrides = {
            "link": {"url": px4.url},
            "app": {"camera": "synthetic", "takeoff_altitude": 5.0,
                    "synthetic": {"render": render, "motion": "linear_fast", "distance": 25.0}},
            "log": {"directory": str(Path(tmp) / "flights"), "plot": False},
        }
        merged = base.model_validate(deep_merge(base.model_dump(), overrides))
        reason, _, summary = asyncio.run(fly(merged, plot=False, handle_signals=False))
    lat = summary.get("frame_to_setpoint_ms", {})
    return {
        "frame_to_setpoint_ms": {"p50": lat.get("p50"), "p95": lat.get("p95"), "n": lat.get("n"), "goal_p95": 20.0},
        "cpu_percent": summary.get("cpu_percent"),
        "camera": render,
        "outcome": summary.get("outcome"),
        "reason": reason.name,
    }

