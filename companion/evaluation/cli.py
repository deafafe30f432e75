"""``companion eval SUITE``: the paper's simulation studies (section V-A) on the in-process simulator.

Suites (paper numbers beside ours in every table):

* ``table1``   Table I: runs spread evenly over the five gate motions, success for 1 m / 2 m
               gates, mean t_gate per motion and in total, top speed.
* ``latency``  Fig. "robustness_latency": box delays 0/100/200/300 ms on stationary, linear
               fast and planar gates, success for 0.5 / 1 / 2 m gates.
* ``vrel``     Table "relative_velocity_estimation": starts at 30 m and 150 m, knot with
               d_knot = 5 m, v_rel_bar = 30 / 20 / 10 m/s and the true closing speed; d_center.
* ``baseline`` Table III: ours with gamma_bar = 3.5 deg against the PN acceleration controller of
               Bhattacharya et al. (companion/baseline.py) on a 0.5 m gate, gates moving linearly
               and planar at 1.25-5 m/s (drawn per run, the same draws for both controllers).

Every suite: ``--seed`` (per-run seeds derive from it), ``--jobs`` worker processes, a progress
bar, a JSON file of per-run and aggregate results (success by radius under ``"total"``), a
Markdown table, plots (sample 3D trajectories; success against delay), and the usual
``--config FILE`` / ``--set section.key=value`` overrides for perturbed scenarios.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from companion.config import add_config_arguments, config_from_args
from companion.evaluation.compare import run_compare
from companion.evaluation.dispatch import AUTOPILOTS, evaluate
from companion.evaluation.plots import plot_latency, plot_trajectories, sample_runs
from companion.evaluation.suites import SUITES
from companion.evaluation.tables import json_default, suite_markdown
from companion.evaluation.tune import REWARDS, TUNE_MOTIONS, tune, write_tuned_overlay
from companion.px4sitl.launcher import PX4SitlError
from companion.sim.runner import CAMERAS, PROTOCOLS

if TYPE_CHECKING:
    from companion.config import Config


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "eval", help="run an evaluation suite of the paper on the in-process simulator",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("suite", choices=(*SUITES, "tune", "compare"),
                   help="which study to run (tune: Bayesian optimisation of k_pn and gamma_bar, paper IV-D; "
                   "compare A.json B.json: do two results differ beyond their noise, exit 1 if so)")
    p.add_argument("files", nargs="*", type=Path, metavar="RESULTS_JSON", help="compare: the two results.json")
    p.add_argument("--runs", type=int, default=None, metavar="N",
                   help="total runs (quick mode: e.g. --runs 10); default: the suite's full size")
    p.add_argument("--seed", type=int, default=0, help="suite seed; every run's seed derives from it")
    p.add_argument("--jobs", "-j", type=int, default=2, help="worker processes (default 2)")
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="directory for results.json, table.md and plots (default eval_out/SUITE)")
    p.add_argument("--json", type=Path, default=None, metavar="PATH",
                   help="JSON result file (default DIR/results.json)")
    p.add_argument("--no-plots", action="store_true", help="skip the plots")
    p.add_argument("--camera", choices=CAMERAS, default="geometric",
                   help="geometric: projected box (paper V-A); rendered: frames through the real detector (slow)")
    p.add_argument("--protocol", choices=PROTOCOLS, default="engagement",
                   help="engagement (default): the app's engagement logic (acquire, close, straight pass, "
                   "recover, aborts) on detector-like boxes clipped to the image; controller: the paper's "
                   "protocol (controller only until the gate plane, box centred on the gate)")
    p.add_argument("--iterations", type=int, default=25, help="tune: BO iterations after the random start (25)")
    p.add_argument("--init-points", type=int, default=5, help="tune: random points first (5)")
    p.add_argument("--reward", choices=tuple(REWARDS), default="dt",
                   help="tune: dt = distance + time (c_t 10, c_d 3), d = distance only (c_d 5, c 3)")
    p.add_argument("--overlay", type=Path, default=None, metavar="PATH",
                   help="tune: write the result as a config overlay (includes the --config files) for fly/eval")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--autopilot", choices=AUTOPILOTS, default="in-process",
                   help="px4: table1 or intercept in real time on PX4 SITL (SIH) with the complete app, one PX4 "
                   "instance per --jobs (companion/evaluation/px4.py)")
    p.add_argument("--px4-dir", default=None, metavar="DIR", help="PX4 SITL build (default px4.sitl_dir, "
                   "$PX4_SITL_DIR)")
    p.add_argument("--motions", default=None, metavar="M1,M2", help="only these gate motions (--autopilot px4)")
    p.add_argument("--cluster", default=None, metavar="ADDRESS",
                   help="run on a Ray cluster (its head's ADDRESS host:port, or auto for the one this machine "
                   "joined) instead of the local pool; needs pip install '.[cluster]' (docs/cluster.md)")
    add_config_arguments(p)
    p.set_defaults(func=_cmd_eval)


def _cmd_eval(args: argparse.Namespace) -> int:
    if args.suite == "compare":
        return run_compare(args.files)
    if args.files:
        print(f"companion eval {args.suite}: unexpected arguments {' '.join(map(str, args.files))}", file=sys.stderr)
        return 2
    if args.runs is not None and args.runs < 1:
        print(f"companion eval: --runs must be >= 1 (got {args.runs})", file=sys.stderr)
        return 2
    if args.jobs < 1:
        print(f"companion eval: --jobs must be >= 1 (got {args.jobs})", file=sys.stderr)
        return 2
    cfg = config_from_args(args)
    out_dir = args.out if args.out is not None else Path("eval_out") / args.suite
    out_dir.mkdir(parents=True, exist_ok=True)
    if args.suite == "tune":
        return _cmd_tune(args, cfg, out_dir)
    px4 = args.autopilot == "px4"
    try:
        res = evaluate(args.suite, cfg, autopilot=args.autopilot, runs=args.runs, seed=args.seed, n_jobs=args.jobs,
                       progress=not args.no_progress, camera=args.camera, protocol=args.protocol, out_dir=out_dir,
                       px4_dir=args.px4_dir,
                       motions=[m.strip() for m in args.motions.split(",")] if args.motions else None,
                       config_files=list(args.config), overrides=list(args.overrides), cluster=args.cluster)
    except (ValueError, PX4SitlError) as e:  # e.g. the rendered camera's detector model is missing, no PX4 build
        print(f"companion eval: {e}", file=sys.stderr)
        return 2
    json_path = args.json if args.json is not None else out_dir / "results.json"
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(res, indent=1, default=json_default))
    cmd = "companion eval " + " ".join(sys.argv[2:]) if len(sys.argv) > 2 else f"companion eval {args.suite}"
    md = suite_markdown(res, cmd, cfg)
    (out_dir / "table.md").write_text(md)
    print(md)
    if px4:  # no plots on PX4: its record is one flight log per run
        print(f"wrote {json_path}, {out_dir / 'table.md'}, flight logs in {out_dir / 'flights'}")
        with contextlib.suppress(Exception):
            errors = [r for r in res["runs"] if r.get("error")]
            if errors:
                print(f"companion eval: {len(errors)} run(s) failed in the harness, first: {errors[0]['error']}",
                      file=sys.stderr)
        return 0
    if not args.no_plots:
        samples = sample_runs(args.suite, cfg, args.seed, protocol=args.protocol)
        plot_trajectories(samples, out_dir / "trajectories.png", f"{args.suite}: sample runs")
        if args.suite == "latency":
            plot_latency(res, out_dir / "latency.png")
    print(f"wrote {json_path}, {out_dir / 'table.md'}" + ("" if args.no_plots else f", plots in {out_dir}"))
    return 0


def _cmd_tune(args: argparse.Namespace, cfg: Config, out_dir: Path) -> int:
    if args.iterations < 0 or args.init_points < 1:
        print("companion eval tune: --iterations must be >= 0 and --init-points >= 1", file=sys.stderr)
        return 2
    per = max(1, (args.runs or 2 * len(TUNE_MOTIONS)) // len(TUNE_MOTIONS))
    res = tune(cfg, iterations=args.iterations, init_points=args.init_points, reward=args.reward,
               runs_per_motion=per, seed=args.seed, n_jobs=args.jobs, progress=not args.no_progress,
               protocol=args.protocol, cluster=args.cluster)
    json_path = args.json if args.json is not None else out_dir / "results.json"
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(res, indent=1, default=json_default))
    md = f"## tune (reward R_{args.reward})\n\n{res['markdown']}\n"
    (out_dir / "table.md").write_text(md)
    print(md)
    best = res["best"]
    print(f"best: --set guidance.k_pn={best['k_pn']:.3f} --set guidance.gamma_bar={best['gamma_bar']:.3f}")
    if args.overlay is not None:
        write_tuned_overlay(args.overlay, best, args.reward, list(args.config), args.seed, args.iterations,
                            args.init_points, per, args.protocol)
        print(f"wrote {args.overlay} (use it with --config)")
    return 0
