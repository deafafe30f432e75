"""The plots of ``companion eval`` (sample 3D trajectories, success against delay) and of ``companion sim``
(one run over time)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from companion.evaluation.suites import LATENCY_DELAYS, PAPER, build_suite
from companion.sim.runner import RunResult, run_once
from companion.sim.scoring import rkey

if TYPE_CHECKING:
    from companion.config import Config


def plot_trajectories(results: list[RunResult], path: Path, title: str = "") -> None:
    """3D paths of vehicle and gate for recorded runs, with the crossing point."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(8, 7))
    ax = fig.add_subplot(projection="3d")
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for k, r in enumerate(results):
        if r.trajectory is None or not r.trajectory.t:
            continue
        a = r.trajectory.arrays()
        c = colors[k % len(colors)]
        o = r.outcome
        status = f"d={o.d_center:.2f} m" if o.crossed else o.reason
        ax.plot(a["p"][:, 0], a["p"][:, 1], a["p"][:, 2], color=c, label=f"{r.spec.motion} #{r.spec.seed}: {status}")
        ax.plot(a["gate"][:, 0], a["gate"][:, 1], a["gate"][:, 2], color=c, ls="--", lw=1)
        ax.scatter(*a["p"][0], color=c, marker="o", s=20)
        if o.crossing_point is not None:
            ax.scatter(*o.crossing_point, color=c, marker="x", s=40)
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_zlabel("up [m]")
    ax.set_title(title or "vehicle (solid), gate centre (dashed), crossing (x)")
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_latency(out: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    for k, r in enumerate(out["radii"]):
        key = rkey(r)
        ds = [d for d in LATENCY_DELAYS if f"{d:.1f}" in out["groups"]]
        ours = [out["groups"][f"{d:.1f}"]["success"][key] for d in ds]
        paper = [PAPER["latency"][key][f"{d:.1f}"] for d in ds]
        c = f"C{k}"
        ax.plot(ds, ours, "o-", color=c, label=f"ours r = {r:g} m")
        ax.plot(ds, paper, "x--", color=c, alpha=0.6, label=f"paper r = {r:g} m")
    ax.set_xlabel("box delay [s]")
    ax.set_ylabel("success rate")
    ax.set_ylim(0, 1.05)
    ax.legend(fontsize=7, ncol=2)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def sample_runs(name: str, cfg: Config, seed: int, per_group: int = 1, protocol: str = "engagement") -> list[RunResult]:
    """Re-fly the first run(s) of each group with recording on (cheap: a handful of runs)."""
    suite = build_suite(name, cfg, None, seed)
    seen: dict[str, int] = {}
    picked = []
    for job in suite.jobs:
        key = json.dumps({k: v for k, v in job.group.items() if k not in ("gate_speed_mps", "delay_s")},
                         sort_keys=True)
        if seen.get(key, 0) < per_group:
            seen[key] = seen.get(key, 0) + 1
            picked.append(job)
    return [run_once(j.cfg, replace(j.spec, protocol=protocol), record=True) for j in picked[:8]]


def plot_run(result: RunResult, path: Path) -> None:
    """One run: 3D paths plus speed, thrust, LOS rate and box centre over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tr = result.trajectory
    if tr is None or not tr.t:
        raise ValueError("plot_run: the run was not recorded (run_once(..., record=True))")
    a = tr.arrays()
    o = result.outcome
    fig = plt.figure(figsize=(11, 7))
    ax = fig.add_subplot(2, 2, 1, projection="3d")
    ax.plot(a["p"][:, 0], a["p"][:, 1], a["p"][:, 2], label="vehicle")
    ax.plot(a["gate"][:, 0], a["gate"][:, 1], a["gate"][:, 2], "--", label="gate centre")
    if o.crossing_point is not None:
        ax.scatter(*o.crossing_point, color="k", marker="x", s=40, label="crossing")
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_zlabel("up [m]")
    ax.legend(fontsize=7)
    t = a["t"]
    ax2 = fig.add_subplot(2, 2, 2)
    ax2.plot(t, np.linalg.norm(a["v"], axis=1), label="speed [m/s]")
    ax2.plot(t, np.linalg.norm(a["gate"] - a["p"], axis=1), label="range to gate [m]")
    ax2.set_xlabel("t [s]")
    ax2.legend(fontsize=7)
    ax2.grid(alpha=0.3)
    ax3 = fig.add_subplot(2, 2, 3)
    ax3.plot(t, tr.thrust, label="thrust setpoint [0..1]")
    ax3.plot(t, tr.lambda_dot, label="LOS rate [rad/s]")
    ax3.plot(t, tr.demand_scale, label="PN demand scale", alpha=0.7)
    ax3.set_xlabel("t [s]")
    ax3.legend(fontsize=7)
    ax3.grid(alpha=0.3)
    ax4 = fig.add_subplot(2, 2, 4)
    cx = [np.nan if b is None else b[0] for b in tr.box]
    cy = [np.nan if b is None else b[1] for b in tr.box]
    ax4.plot(t, cx, label="box cx [px]")
    ax4.plot(t, cy, label="box cy [px]")
    ax4.set_xlabel("t [s]")
    ax4.legend(fontsize=7)
    ax4.grid(alpha=0.3)
    status = f"crossed at t = {o.t_gate:.2f} s, d_center = {o.d_center:.2f} m" if o.crossed else f"failed: {o.reason}"
    fig.suptitle(f"{result.spec.motion} (seed {result.spec.seed}, {result.spec.controller}): {status}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
