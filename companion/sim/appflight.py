"""What a ``companion sim`` flight of the app shares between its autopilots (the simulated PX4,
companion/sim/cli.py, and PX4 SITL, companion/px4sitl/run.py): its config overrides and its report."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from companion.app.assemble import detector_available


def sim_overrides(args: argparse.Namespace) -> list[str]:
    """The ``--set`` list of a ``companion sim`` flight (simulated PX4 or PX4 SITL): synthetic camera, the
    gate motion and seed asked for, and the geometric camera when the detector cannot run."""
    from companion.config import load_config

    ov = [*getattr(args, "overrides", []), "app.camera=synthetic"]
    if getattr(args, "motion", None):
        ov.append(f"app.synthetic.motion={args.motion}")
    if getattr(args, "seed", None) is not None:
        ov.append(f"sim.seed={args.seed}")
    cfg = load_config(args.config, ov)
    if cfg.app.synthetic.render == "image" and (why := detector_available(cfg)) is not None:
        print(f"companion sim: detector unavailable ({why}); using the geometric camera", file=sys.stderr)
        ov.append("app.synthetic.render=geometric")
    return ov


def print_flight_report(folder: Path, summary: dict[str, Any]) -> None:
    """The end of ``companion sim``: outcome, each gate crossing (from the logged truth), latency, log folder."""
    from companion.flightlog import flight_crossings, read_flight

    f = read_flight(folder)
    cross = flight_crossings(f)
    lat = summary.get("frame_to_setpoint_ms", {})
    print(f"outcome: {summary.get('outcome')} ({summary.get('reason')}): {summary.get('detail')}")
    truth = summary.get("truth") if isinstance(summary.get("truth"), dict) else {}
    icpt = truth.get("intercepts") or []
    # An intercept's target is crossed over its top after the pull-up: scored as an intercept, not as a gate.
    t0 = f.meta.get("t0_monotonic")
    skip = {round(float(g["t_monotonic_s"]) - float(t0), 6) for g in truth.get("gates") or []
            if t0 is not None and g.get("t_monotonic_s") is not None and g.get("gate") in {i["gate"] for i in icpt}}
    for i, c in enumerate((c for c in cross if round(c.t, 6) not in skip), 1):
        print(f"gate {i}: crossed at t = {c.t:.2f} s, {c.d_center:.2f} m from the centre "
              f"({'through' if c.through else 'missed'}, radius {c.radius:.2f} m)")
    for r in icpt:
        miss = "-" if r.get("predicted_miss_m") is None else f"{r['predicted_miss_m']:.2f} m"
        clear = "-" if r.get("clearance_m") is None else f"{r['clearance_m']:.2f} m"
        print(f"intercept (target {r['gate']}): predicted miss {miss}, cleared by {clear} (ground truth)")
    if lat.get("p50") is not None:
        print(f"frame -> setpoint latency: p50 {lat['p50']:.1f} ms, p95 {lat['p95']:.1f} ms; "
              f"app CPU {summary.get('cpu_percent', 0):.0f} %")
    print(f"log: {folder}" + (f"  plot: {folder / 'plot.png'}" if (folder / "plot.png").exists() else ""))
