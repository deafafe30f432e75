"""``companion bench``: the speed figures the issues set goals for, measured on this machine.

Sections (each reported in the JSON under its own key; the controller step and the simulator frame also as
ratios to a reference numpy kernel timed beside them, ``ratio_to_kernel``):
  controller_step_us     LOS (ray + rotation) + LOS filter + PN solve + setpoint conversion, per frame
  sim_speed_x_realtime   in-process simulator with the geometric camera, one core
  sim_speed_all_cores    the same on every core at once (one process each), summed
  pipeline_ms_per_frame  detector + tracker at 640x480, one core
  frame_to_setpoint_ms   frame -> setpoint latency inside the flight app, in simulation

Numbers are reported, never asserted: tests stay deterministic on a slow machine.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import add_config_arguments, config_from_args


def _kernel(m: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The reference work unit: a 3x3 matrix-vector product, a cross product, an atan2 and a new 3-vector."""
    v = m @ a
    c = np.cross(v, b)
    return np.array([c[0], c[1], math.atan2(float(c[1]), float(c[0]))])


def bench_kernel(calls: int = 500, repetitions: int = 30) -> dict[str, Any]:
    """Median per-call time (us) of the reference kernel, ``calls`` calls timed together, ``repetitions`` times.
    The other sections are reported as ratios to it: this machine's speed swings, the ratio much less."""
    rng = np.random.default_rng(1)
    m, a, b = rng.normal(size=(3, 3)), rng.normal(size=3), rng.normal(size=3)
    # CPU time of this process, like the simulator's frame_us: a preemption by another process (6 engineers on 2
    # cores) is not counted, which wall time would.
    clock = time.process_time_ns
    per_call = np.empty(repetitions)
    for k in range(repetitions):
        t0 = clock()
        for _ in range(calls):
            _kernel(m, a, b)
        per_call[k] = (clock() - t0) / calls / 1e3
    return {"median_us": float(np.median(per_call)), "calls": calls, "repetitions": repetitions}


# Goals of issue 21, as ratios to the reference kernel timed in the same run.
RATIO_GOALS = {"controller_step": 1.6, "sim_frame": 7.0}
SIM_GOAL_X_REALTIME = 200.0  # the in-process simulator on 2 cores


def bench_controller(cfg: Any, steps: int = 20000) -> dict[str, Any]:
    """Per-step time of PNController.step on a weaving target seen from a gently rotating vehicle."""
    from companion.controller import PNController
    from companion.frames import R_from_euler_ned_deg, quat_wxyz_from_R
    from perception.types import BoundingBox

    ctrl = PNController.from_config(cfg)
    rng = np.random.default_rng(0)
    # Inputs prepared up front so only the controller is timed.
    atts = [
        quat_wxyz_from_R(R_from_euler_ned_deg(3 * math.sin(k / 40), -10 + 2 * math.cos(k / 30), 5 * math.sin(k / 90)))
        for k in range(256)
    ]
    boxes = [BoundingBox(320 + 40 * math.sin(k / 25) + rng.normal(0, 1), 240 + 20 * math.cos(k / 35), 40, 40)
             for k in range(256)]
    dt = 1.0 / cfg.camera.rate
    times = np.empty(steps)
    clock = time.perf_counter_ns
    for k in range(steps):
        i = k & 255
        t0 = clock()
        ctrl.step(k * dt, boxes[i], atts[i])
        times[k] = clock() - t0
    us = times[steps // 10:] / 1e3  # skip warm-up
    return {"median": float(np.median(us)), "p95": float(np.percentile(us, 95)), "steps": steps, "goal_median": 50.0}


def _sim_in_process(cfg: Any, seconds: float) -> dict[str, float]:
    from companion.sim.runner import bench_sim

    return bench_sim(seconds, cfg)


def bench_sim_cores(cfg: Any, cores: int | None = None, quick: bool = False) -> dict[str, Any]:
    """The in-process simulator on every core at once (one process per core, as ``companion eval --jobs N``
    runs it): simulated seconds per wall second, summed over the processes, whose timed spans overlap."""
    import multiprocessing
    import os
    from concurrent.futures import ProcessPoolExecutor

    n = cores or os.cpu_count() or 1
    seconds = 10.0 if quick else 60.0
    with ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("fork")) as pool:
        each = list(pool.map(_sim_in_process, [cfg] * n, [seconds] * n))
    rate = sum(r["sim_seconds"] / r["wall_seconds"] for r in each)
    return {"sim_speed_x_realtime": rate, "processes": n,
            "each_x_realtime": [r["sim_seconds"] / r["wall_seconds"] for r in each]}


# (JSON key, module, function) of the benchmarks other modules own.
_EXTERNAL = (
    ("sim_speed_x_realtime", "companion.sim.runner", "bench_sim"),
    ("sim_speed_all_cores", "companion.bench", "bench_sim_cores"),
    ("pipeline_ms_per_frame", "perception.bench", "bench_perception"),
    ("frame_to_setpoint_ms", "companion.app.bench", "bench_app"),
)


def run(args: argparse.Namespace) -> int:
    only = set(args.only or [])
    sections = ("controller_step_us", *(key for key, _, _ in _EXTERNAL))
    unknown = sorted(only - set(sections))
    if unknown:
        print(f"companion bench: --only {', '.join(unknown)}: no such section (valid: {', '.join(sections)})",
              file=sys.stderr)
        return 2
    cfg = config_from_args(args)
    results: dict[str, Any] = {
        "machine": {"python": platform.python_version(), "cpu": platform.processor() or platform.machine()},
    }

    def want(key: str) -> bool:
        return not only or key in only

    kernels: list[float] = []

    def kernel() -> float:
        """The reference kernel, timed again beside each section (the speed drifts within a run)."""
        k = bench_kernel()["median_us"]
        kernels.append(k)
        print(f"reference kernel: median {k:.2f} us per call (500 calls x 30)")
        return k

    ratios: dict[str, float] = {}
    if want("controller_step_us"):
        k = kernel()
        r = bench_controller(cfg, steps=2000 if args.quick else 20000)
        results["controller_step_us"] = r
        ratios["controller_step"] = r["median"] / k
        print(f"controller step: median {r['median']:.1f} us, p95 {r['p95']:.1f} us = "
              f"{ratios['controller_step']:.2f}x the kernel (goal <= {RATIO_GOALS['controller_step']})")
    for key, module, func in _EXTERNAL:
        if not want(key):
            continue
        try:
            fn = getattr(importlib.import_module(module), func)
        except (ModuleNotFoundError, AttributeError) as e:
            results[key] = {"error": f"not available: {e}"}
            print(f"{key}: not available ({e})", file=sys.stderr)
            continue
        # Every section times the configured system (--config / --set), not the defaults.
        accepts = fn.__code__.co_varnames[:fn.__code__.co_argcount]
        kwargs = {k: v for k, v in (("quick", args.quick), ("cfg", cfg), ("pc", cfg.perception)) if k in accepts}
        k = kernel() if key == "sim_speed_x_realtime" else None
        r = fn(**kwargs)
        if k is not None and isinstance(r, dict) and "frame_us" in r:
            ratios["sim_frame"] = r["frame_us"] / k
            print(f"simulator frame: {r['frame_us']:.1f} us = {ratios['sim_frame']:.2f}x the kernel "
                  f"(goal <= {RATIO_GOALS['sim_frame']})")
        if key == "sim_speed_all_cores" and isinstance(r, dict) and "processes" in r:
            print(f"simulator on {r['processes']} cores at once: {r['sim_speed_x_realtime']:.0f}x real time "
                  f"(goal >= {SIM_GOAL_X_REALTIME:.0f}x on 2 cores)")
        # Each owner returns {key: value-or-dict, ...}; keep its whole dict under the section key.
        results[key] = r.get(key, r) if isinstance(r, dict) and len(r) == 1 else r
        print(f"{key}: {json.dumps(results[key])}")
    if kernels:
        results["reference_kernel_us"] = {"median": float(np.median(kernels)), "each": kernels}
        results["ratio_to_kernel"] = {**ratios, "goals": RATIO_GOALS}
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(results, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0


def register(sub: Any) -> None:
    p = sub.add_parser("bench", help="measure controller step time, simulator speed, perception and app latency")
    add_config_arguments(p)
    p.add_argument("--json", metavar="PATH", help="write machine-readable results here")
    p.add_argument("--quick", action="store_true", help="fewer iterations (a smoke run, less precise)")
    p.add_argument("--only", action="append", metavar="SECTION",
                   help="run only this section (repeatable): controller_step_us, sim_speed_x_realtime, "
                        "sim_speed_all_cores, pipeline_ms_per_frame, frame_to_setpoint_ms")
    p.set_defaults(func=run)
