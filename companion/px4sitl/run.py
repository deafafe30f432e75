"""``companion sim --autopilot px4``: one flight of the app against real PX4 SITL (SIH), start to finish.

Starts PX4 with the config's SIH vehicle (px4.sih, MPC_THR_HOVER = airframe.hover_thrust, px4.params) in a
fresh working folder, waits for its pre-flight checks, flies the app exactly as ``companion fly --synthetic``
(arm, take off, acquire, engage, pass, hand back, land) with the virtual gate drawn from SIH's ground truth,
then stops PX4. The flight log records PX4's working folder and ULog (meta.json / summary.json "px4").
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
from pathlib import Path
from typing import Any

from companion.px4sitl.launcher import PX4Sitl, PX4SitlError


def add_px4_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--autopilot", choices=("sim", "px4"), default="sim",
                   help="sim: our simulated PX4 (default); px4: real PX4 SITL with SIH (PX4_SITL_DIR)")
    p.add_argument("--px4-dir", default=None, metavar="DIR",
                   help="PX4 SITL build (bin/px4, etc/); default px4.sitl_dir or $PX4_SITL_DIR")
    p.add_argument("--px4-instance", type=int, default=None, metavar="N",
                   help="PX4 instance (UDP ports shift by N); default px4.instance or the first free one")


def record_px4(folder: Path, px4: PX4Sitl) -> None:
    """PX4's side of the flight beside ours: its working folder, console and ULog(s)."""
    info: dict[str, Any] = {"sitl_dir": str(px4.sitl), "instance": px4.instance, "work_dir": str(px4.work),
                            "console": str(px4.console), "ulog": [str(p) for p in px4.ulog_paths()],
                            "params": px4.params}
    for name in ("meta.json", "summary.json"):
        p = folder / name
        try:
            data = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            data = {}
        data["px4"] = info
        tmp = p.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
        os.replace(tmp, p)


def run_px4_sim(args: argparse.Namespace) -> int:
    from companion.app.session import fly
    from companion.config import load_config
    from companion.sim.appflight import print_flight_report, sim_overrides

    ov = sim_overrides(args)
    cfg = load_config(args.config, ov)

    def say(m: str) -> None:
        print(f"companion sim: {m}", file=sys.stderr, flush=True)

    try:
        px4 = PX4Sitl.from_config(cfg, sitl_dir=args.px4_dir, instance=args.px4_instance, log=say)
    except PX4SitlError as e:
        print(f"companion sim: {e}", file=sys.stderr)
        return 2
    try:
        try:
            px4.start()
            say(f"SIH vehicle: {cfg.px4.sih.mass:.2f} kg, thrust-to-weight {cfg.px4.sih.thrust_to_weight:.2f}, "
                f"drag {cfg.px4.sih.kdv:g} N/(m/s); waiting for PX4's pre-flight checks (30-40 s)")
            t = px4.wait_preflight(cfg.px4.preflight_timeout)
        except PX4SitlError as e:
            print(f"companion sim: {e}", file=sys.stderr)
            return int(_reason("PREFLIGHT_FAILED"))
        say(f"pre-flight OK after {t:.0f} s")
        cfg = load_config(args.config, [*ov, *px4.config_overrides()])
        reason, folder, summary = asyncio.run(fly(cfg, status_line=not getattr(args, "no_status", False),
                                                  plot=not getattr(args, "no_plot", False)))
    finally:
        px4.stop()
    record_px4(folder, px4)
    print_flight_report(folder, summary)
    print(f"PX4: {', '.join(str(p) for p in px4.ulog_paths()) or 'no ULog'} (console {px4.console})")
    return int(reason)


def _reason(name: str) -> Any:
    from companion.app.states import Reason

    return Reason[name]
