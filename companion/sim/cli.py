"""``companion sim``: a simulated flight, in real time or in-process.

Default: the simulated PX4 in its own process (MAVLink over UDP on 127.0.0.1), the synthetic
camera and the flight app together in real time, exactly as on a drone: arm, take off, acquire,
engage, pass, recover, land. A live status line on stderr; the flight log and its plot at the end
(companion/sim/cli.py :func:`run_sim`). The exit code is the flight's outcome (0 = passed, landed).

``--autopilot px4``: the same flight against real PX4 SITL with its SIH simulator (from $PX4_SITL_DIR,
px4.sitl_dir or --px4-dir), started and stopped here (companion/px4sitl/run.py).

``--in-process``: the fast in-process simulator (companion/sim/runner.py :func:`run_once`):
dynamics + camera + controller in one loop, faster than real time, no autopilot.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from companion.app.main import exit_when_done, run_flight_process
from companion.app.session import StartRefused, fly
from companion.config import add_config_arguments, config_from_args
from companion.px4sitl.run import add_px4_arguments, run_px4_sim
from companion.sim.appflight import print_flight_report, sim_overrides
from companion.sim.gates import ALL_MOTIONS
from companion.sim.process import SimPX4Process
from companion.sim.runner import CAMERAS, CONTROLLERS, RunSpec, run_once


def add_in_process_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--in-process", action="store_true",
                   help="fly the in-process simulator (dynamics + geometric camera + controller in one loop)")
    p.add_argument("--motion", choices=ALL_MOTIONS, default=None,
                   help="gate motion (default: planar in-process, app.synthetic.motion otherwise)")
    p.add_argument("--seed", type=int, default=0, help="run seed (initial condition, noise)")
    p.add_argument("--controller", choices=CONTROLLERS, default="pn",
                   help="pn (ours), pn_true_vrel (true closing speed), baseline (Bhattacharya et al.)")
    p.add_argument("--camera", choices=CAMERAS, default=None,
                   help="geometric: projected box (paper V-A); rendered: drawn frames through the real detector "
                        "(default: geometric in-process, app.synthetic.render otherwise)")
    p.add_argument("--plot", type=Path, default=Path("sim_run.png"), metavar="PNG",
                   help="plot file (default sim_run.png)")
    p.add_argument("--no-plot", action="store_true")
    p.add_argument("--json", type=Path, default=None, metavar="PATH", help="write the run's result as JSON")


def add_sim_arguments(p: argparse.ArgumentParser) -> None:
    """The options ``companion sim`` adds for its default (simulated PX4 + app) mode."""
    p.add_argument("--no-status", action="store_true", help="no live status line on stderr")


def register(subparsers: Any) -> None:
    p = subparsers.add_parser("sim", help="fly one simulated run and plot it",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_in_process_arguments(p)
    add_sim_arguments(p)
    add_px4_arguments(p)
    add_config_arguments(p)
    p.set_defaults(func=cmd_sim)


def cmd_sim(args: argparse.Namespace) -> int:
    if args.in_process:
        return cmd_in_process(args)
    if args.camera is not None:
        args.overrides = [*args.overrides,
                          f"app.synthetic.render={'image' if args.camera == 'rendered' else 'geometric'}"]
    if args.autopilot == "px4":
        return run_px4_sim(args)
    return run_sim(args)


def run_sim(args: argparse.Namespace) -> int:
    """``companion sim``: simulated PX4 (own process) + synthetic camera + the app, in real time."""
    from companion.config import load_config

    ov = sim_overrides(args)
    with SimPX4Process(args.config, [o for o in ov if o.startswith(("sim.", "airframe."))]) as px4:
        print(f"companion sim: simulated PX4 on 127.0.0.1:{px4.port} (pid {px4.proc.pid})", file=sys.stderr)
        cfg = load_config(args.config, [*ov, f"link.url={px4.url}"])
        try:
            reason, folder, summary = run_flight_process(fly(cfg, status_line=not getattr(args, "no_status", False),
                                                             plot=not getattr(args, "no_plot", False)))
        except StartRefused as e:
            print(f"companion sim: {e}", file=sys.stderr)
            return 2
    print_flight_report(folder, summary)
    return exit_when_done(int(reason))


def cmd_in_process(args: argparse.Namespace) -> int:
    cfg = config_from_args(args)
    radii = list(cfg.sim.scenario.gate_radii)
    args.motion = args.motion or "planar"
    args.camera = args.camera or "geometric"
    try:
        res = run_once(cfg, RunSpec(args.motion, args.seed, args.controller, camera=args.camera),
                       record=not args.no_plot)
    except ValueError as e:  # e.g. the rendered camera's detector model is missing: one line, no traceback
        print(f"companion sim: {e}", file=sys.stderr)
        return 2
    d = res.as_dict(radii)
    o = res.outcome
    if o.crossed:
        print(f"{args.motion} seed {args.seed}: crossed the gate plane at t = {o.t_gate:.2f} s, "
              f"d_center = {o.d_center:.2f} m, top speed {o.top_speed:.1f} m/s")
    else:
        why = o.reason or "no crossing of the target's plane"  # a pull-up that stayed clear ends without one
        print(f"{args.motion} seed {args.seed}: failed ({why}) after {res.sim_time:.2f} s" if o.reason else
              f"{args.motion} seed {args.seed}: {why} after {res.sim_time:.2f} s")
    if d["max_tilt_deg"] is not None:
        osc = "" if d["roll_osc_amp_deg"] is None else (
            f", roll-setpoint oscillation {d['roll_osc_amp_deg']:.1f} deg at {d['roll_osc_freq_hz']:.2f} Hz "
            f"(RMS rate {d['roll_osc_rms_rate_dps']:.0f} deg/s)")
        print(f"commanded: max tilt {d['max_tilt_deg']:.1f} deg{osc}")
    if res.engagement is not None:  # the engagement protocol: how the app's decisions ended
        print(f"engagement: {res.engagement['end']}, pass {res.engagement['pass_status'] or 'none'}")
    if res.pullup is not None and res.pullup["pulled_up"]:  # on_close=pull_up: scored by truth
        pu = res.pullup
        miss = "-" if pu["predicted_miss_m"] is None else f"{pu['predicted_miss_m']:.2f} m"
        print(f"pull-up at t = {pu['t_pullup_s']:.2f} s ({pu['speed_at_pullup_mps']:.1f} m/s): predicted miss {miss}, "
              f"cleared the target by {pu['clearance_m']:.2f} m")
    print("success by gate radius: " + ", ".join(f"{k} m: {'yes' if v else 'no'}" for k, v in d["success"].items()))
    if args.json is not None:
        args.json.write_text(json.dumps(d, indent=1))
    if not args.no_plot:
        from companion.evaluation.plots import plot_run

        plot_run(res, args.plot)
        print(f"plot: {args.plot}", file=sys.stderr)
    return 0
