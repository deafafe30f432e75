"""``companion sim``: fly one simulated run in-process and plot it.

The run logic lives in companion/sim/runner.py (:func:`run_once`); this is only the command.
``--in-process`` names this mode explicitly, so the command can later grow a MAVLink mode
(simulated PX4 + the real app) without changing what ``companion sim --in-process`` does.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from companion.config import add_config_arguments, config_from_args
from companion.sim.gates import MOTIONS
from companion.sim.runner import CAMERAS, CONTROLLERS, RunSpec, run_once


def add_in_process_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--in-process", action="store_true",
                   help="fly the in-process simulator (dynamics + geometric camera + controller in one loop)")
    p.add_argument("--motion", choices=MOTIONS, default="planar", help="gate motion (default planar)")
    p.add_argument("--seed", type=int, default=0, help="run seed (initial condition, noise)")
    p.add_argument("--controller", choices=CONTROLLERS, default="pn",
                   help="pn (ours), pn_true_vrel (true closing speed), baseline (Bhattacharya et al.)")
    p.add_argument("--camera", choices=CAMERAS, default="geometric",
                   help="geometric: projected box (paper V-A); rendered: drawn frames through the real detector")
    p.add_argument("--plot", type=Path, default=Path("sim_run.png"), metavar="PNG",
                   help="plot file (default sim_run.png)")
    p.add_argument("--no-plot", action="store_true")
    p.add_argument("--json", type=Path, default=None, metavar="PATH", help="write the run's result as JSON")


def register(subparsers: Any) -> None:
    p = subparsers.add_parser("sim", help="fly one simulated run and plot it",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_in_process_arguments(p)
    add_config_arguments(p)
    p.set_defaults(func=cmd_in_process)


def cmd_in_process(args: argparse.Namespace) -> int:
    cfg = config_from_args(args)
    radii = list(cfg.sim.scenario.gate_radii)
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
        print(f"{args.motion} seed {args.seed}: failed ({o.reason}) after {res.sim_time:.2f} s")
    print("success by gate radius: " + ", ".join(f"{k} m: {'yes' if v else 'no'}" for k, v in d["success"].items()))
    if args.json is not None:
        args.json.write_text(json.dumps(d, indent=1))
    if not args.no_plot:
        from companion.evaluation import plot_run

        plot_run(res, args.plot)
        print(f"plot: {args.plot}", file=sys.stderr)
    return 0
