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
import json
import math
import multiprocessing as mp
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.config import add_config_arguments, config_as_dict, config_from_args
from companion.sim.runner import CAMERAS, PROTOCOLS, RunResult, RunSpec, run_once, with_overrides
from companion.sim.scoring import aggregate, rkey, setpoint_metrics

if TYPE_CHECKING:
    from companion.config import Config

SUITES = ("table1", "latency", "vrel", "baseline")

# The paper's numbers (Table I with reward R_dt, Fig. latency, Table II v_rel, Table III).
PAPER = {
    "table1": {
        "success_1m": {"stationary": 1.00, "linear_slow": 1.00, "linear_fast": 0.67, "planar": 1.00,
                       "knot": 1.00, "total": 0.93},
        "success_2m": {"stationary": 1.00, "linear_slow": 1.00, "linear_fast": 0.75, "planar": 1.00,
                       "knot": 1.00, "total": 0.95},
        "t_gate_s": {"stationary": 4.11, "linear_slow": 4.03, "linear_fast": 5.41, "planar": 4.01,
                     "knot": 4.03, "total": 4.32},
        "top_speed_mps": 14.6,
    },
    "latency": {  # success by delay (s) for each radius (m)
        "0.5": {"0.0": 0.63, "0.1": 0.44, "0.2": 0.48, "0.3": 0.28},
        "1.0": {"0.0": 0.96, "0.1": 0.93, "0.2": 0.63, "0.3": 0.52},
        "2.0": {"0.0": 1.00, "0.1": 1.00, "0.2": 1.00, "0.3": 0.93},
    },
    "vrel": {  # d_center mean, std (m) by top-speed class and knowledge
        "30m": {"30": (4.72, 1.03), "20": (1.01, 0.22), "10": (1.02, 0.34), "true": (0.42, 0.19)},
        "150m": {"30": (0.65, 0.05), "20": (0.70, 0.35), "10": (4.84, 0.45), "true": (1.19, 0.43)},
        "top_speed_mps": {"30m": 15.0, "150m": 25.0},
    },
    "baseline": {"linear": {"baseline": 0.35, "pn": 0.69}, "planar": {"baseline": 0.41, "pn": 0.56}},
}

TABLE1_MOTIONS = ("stationary", "linear_slow", "linear_fast", "planar", "knot")
LATENCY_MOTIONS = ("stationary", "linear_fast", "planar")
LATENCY_DELAYS = (0.0, 0.1, 0.2, 0.3)
VREL_ESTIMATES = ("30", "20", "10", "true")


@dataclass
class Job:
    cfg: Config
    spec: RunSpec
    group: dict[str, Any]  # what the suite varies in this run (motion, delay, controller, ...)


@dataclass
class Suite:
    name: str
    jobs: list[Job]
    radii: list[float]
    report: Callable[[list[dict], list[float]], tuple[dict, str]]  # -> (groups, markdown)
    plots: list[str] = field(default_factory=list)


# -- running ---------------------------------------------------------------------------------------


def _work(item: tuple[int, Job, list[float]]) -> tuple[int, dict]:
    i, job, radii = item
    r = run_once(job.cfg, job.spec)
    return i, {**job.group, **r.as_dict(radii)}


def run_jobs(jobs: Sequence[Job], radii: list[float], n_jobs: int = 2, progress: bool = True,
             desc: str = "runs") -> list[dict]:
    """Run every job (in ``n_jobs`` processes when > 1), results in job order."""
    from tqdm import tqdm

    items = [(i, j, radii) for i, j in enumerate(jobs)]
    out: list[dict | None] = [None] * len(items)
    bar = tqdm(total=len(items), desc=desc, unit="run", disable=not progress, file=sys.stderr)
    try:
        if n_jobs <= 1 or len(items) <= 1:
            for it in items:
                i, res = _work(it)
                out[i] = res
                bar.update()
        else:
            # fork: workers inherit the imported modules (fast start); each run is independent.
            ctx = mp.get_context("fork")
            with ctx.Pool(n_jobs) as pool:
                for i, res in pool.imap_unordered(_work, items, chunksize=1):
                    out[i] = res
                    bar.update()
    finally:
        bar.close()
    return [o for o in out if o is not None]


# -- suites ------------------------------------------------------------------------------------------


def _per(runs: int, cells: int) -> int:
    return max(1, runs // cells)


def _fmt(x: float | None, nd: int = 2) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{nd}f}"


def _groups(results: list[dict], key: Callable[[dict], str], radii: list[float]) -> dict[str, dict]:
    names: list[str] = []
    for r in results:
        if key(r) not in names:
            names.append(key(r))
    return {n: aggregate([r for r in results if key(r) == n], radii) for n in names}


def suite_table1(cfg: Config, runs: int | None = None) -> Suite:
    n = _per(runs or 60, len(TABLE1_MOTIONS))
    jobs = [Job(cfg, RunSpec(m, seed=k * 1000 + i), {"motion": m})
            for k, m in enumerate(TABLE1_MOTIONS) for i in range(n)]

    def report(results: list[dict], radii: list[float]) -> tuple[dict, str]:
        groups = _groups(results, lambda r: r["motion"], radii)
        p = PAPER["table1"]
        lines = ["| Gate motion | Success 1 m (paper) | Success 2 m (paper) | t_gate s (paper) | "
                 "d_center m | top speed m/s | failures (1 m) |", "|---|---|---|---|---|---|---|"]
        rows = [*TABLE1_MOTIONS, "total"]
        total = aggregate(results, radii)
        for m in rows:
            g = total if m == "total" else groups.get(m)
            if g is None:
                continue
            lines.append(
                f"| {m} | {_fmt(g['success']['1.0'])} ({p['success_1m'][m]:.2f}) | "
                f"{_fmt(g['success']['2.0'])} ({p['success_2m'][m]:.2f}) | {_fmt(g['t_gate_mean_s'])} "
                f"({p['t_gate_s'][m]:.2f}) | {_fmt(g['d_center_mean_m'])} | {_fmt(g['top_speed_mps'], 1)} | "
                f"{_reasons(g, '1.0')} |")
        lines.append(f"\nTop speed: ours {total['top_speed_mps']:.1f} m/s (paper {p['top_speed_mps']} m/s).")
        return groups, "\n".join(lines)

    return Suite("table1", jobs, [0.5, 1.0, 2.0], report, ["trajectories"])


def suite_latency(cfg: Config, runs: int | None = None) -> Suite:
    n = _per(runs or 120, len(LATENCY_DELAYS) * len(LATENCY_MOTIONS))
    jobs = []
    for d in LATENCY_DELAYS:
        c = with_overrides(cfg, {"sim": {"camera": {"delay": d}}})
        for k, m in enumerate(LATENCY_MOTIONS):
            # The same initial conditions at every delay: the delay is the only difference.
            jobs += [Job(c, RunSpec(m, seed=k * 1000 + i), {"motion": m, "delay_s": d}) for i in range(n)]

    def report(results: list[dict], radii: list[float]) -> tuple[dict, str]:
        groups = _groups(results, lambda r: f"{r['delay_s']:.1f}", radii)
        lines = ["| Delay ms | " + " | ".join(f"Success {r:g} m (paper)" for r in radii) + " | t_gate s |",
                 "|---" * (len(radii) + 2) + "|"]
        for d in LATENCY_DELAYS:
            g = groups.get(f"{d:.1f}")
            if g is None:
                continue
            cells = [f"{_fmt(g['success'][rkey(r)])} ({PAPER['latency'][rkey(r)][f'{d:.1f}']:.2f})" for r in radii]
            lines.append(f"| {d * 1000:.0f} | " + " | ".join(cells) + f" | {_fmt(g['t_gate_mean_s'])} |")
        by_motion = _groups(results, lambda r: f"{r['motion']} @ {r['delay_s'] * 1000:.0f} ms", radii)
        lines += ["", "| Motion @ delay | " + " | ".join(f"Success {r:g} m" for r in radii) + " |",
                  "|---" * (len(radii) + 1) + "|"]
        for name, g in by_motion.items():
            lines.append(f"| {name} | " + " | ".join(_fmt(g["success"][rkey(r)]) for r in radii) + " |")
        groups.update({f"by_motion/{k}": v for k, v in by_motion.items()})
        return groups, "\n".join(lines)

    return Suite("latency", jobs, [0.5, 1.0, 2.0], report, ["trajectories", "latency"])


def suite_vrel(cfg: Config, runs: int | None = None) -> Suite:
    n = _per(runs or 80, 2 * len(VREL_ESTIMATES))
    knot_speed = cfg.sim.gates.knot_top_speed * 5.0 / cfg.sim.gates.d_knot  # same omega, d_knot = 5
    jobs = []
    for dist, timeout in ((30.0, 30.0), (150.0, 60.0)):
        base = {"sim": {"scenario": {"distance_min": dist, "distance_max": dist, "timeout": timeout},
                        "gates": {"d_knot": 5.0, "knot_top_speed": knot_speed}}}
        for est in VREL_ESTIMATES:
            over = base if est == "true" else deep({"guidance": {"v_rel_bar": float(est)}}, base)
            c = with_overrides(cfg, over)
            ctrl = "pn_true_vrel" if est == "true" else "pn"
            jobs += [Job(c, RunSpec("knot", seed=int(dist) * 1000 + i, controller=ctrl),
                         {"start_m": dist, "v_rel_bar": est}) for i in range(n)]

    def report(results: list[dict], radii: list[float]) -> tuple[dict, str]:
        groups = _groups(results, lambda r: f"{r['start_m']:.0f}m/{r['v_rel_bar']}", radii)
        lines = ["| Start | top speed m/s (paper) | v_rel knowledge | d_center m (paper) | Success 1 m |",
                 "|---|---|---|---|---|"]
        for dist in ("30m", "150m"):
            for est in VREL_ESTIMATES:
                g = groups.get(f"{dist}/{est}")
                if g is None:
                    continue
                pm, ps = PAPER["vrel"][dist][est]
                label = "perfect knowledge" if est == "true" else f"estimate {est} m/s"
                lines.append(
                    f"| {dist} | {_fmt(g['top_speed_mean_mps'], 1)} ({PAPER['vrel']['top_speed_mps'][dist]:.0f}) | "
                    f"{label} | {_fmt(g['d_center_mean_m'])} ± {_fmt(g['d_center_std_m'])} ({pm:.2f} ± {ps:.2f}) | "
                    f"{_fmt(g['success']['1.0'])} |")
        return groups, "\n".join(lines)

    return Suite("vrel", jobs, [0.5, 1.0, 2.0], report, ["trajectories"])


def suite_baseline(cfg: Config, runs: int | None = None, seed: int = 0) -> Suite:
    n = _per(runs or 120, 4)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 3]))
    ours = with_overrides(cfg, {"guidance": {"gamma_bar": 3.5}})
    jobs = []
    for k, (label, motion, key) in enumerate((("linear", "linear_fast", "linear_fast_speed"),
                                              ("planar", "planar", "planar_top_speed"))):
        for i in range(n):
            speed = float(rng.uniform(1.25, 5.0))
            over = {"sim": {"gates": {key: speed}}}
            for ctrl, base in (("baseline", cfg), ("pn", ours)):
                jobs.append(Job(with_overrides(base, over), RunSpec(motion, seed=k * 1000 + i, controller=ctrl),
                                {"motion_class": label, "controller": ctrl, "gate_speed_mps": speed}))

    def report(results: list[dict], radii: list[float]) -> tuple[dict, str]:
        groups = _groups(results, lambda r: f"{r['motion_class']}/{r['controller']}", radii)
        lines = ["| Gate motion | PN accel. baseline, velocity known (paper) | PN-informed, ours (paper) | "
                 "t_gate s baseline / ours | failures baseline / ours (0.5 m) |", "|---|---|---|---|---|"]
        for label in ("linear", "planar"):
            b, o = groups.get(f"{label}/baseline"), groups.get(f"{label}/pn")
            if b is None or o is None:
                continue
            pb = PAPER["baseline"][label]
            lines.append(
                f"| {label} | {_fmt(b['success']['0.5'])} ({pb['baseline']:.2f}) | {_fmt(o['success']['0.5'])} "
                f"({pb['pn']:.2f}) | {_fmt(b['t_gate_mean_s'])} / {_fmt(o['t_gate_mean_s'])} | "
                f"{_reasons(b, '0.5')} / {_reasons(o, '0.5')} |")
        return groups, "\n".join(lines)

    return Suite("baseline", jobs, [0.5, 1.0, 2.0], report, ["trajectories"])


def deep(a: dict, b: dict) -> dict:
    from companion.configbase import deep_merge

    return deep_merge(b, a)


def _reasons(g: dict, r: str) -> str:
    f = g.get("failures", {}).get(r, {})
    return ", ".join(f"{k} {v}" for k, v in sorted(f.items())) or "-"


def build_suite(name: str, cfg: Config, runs: int | None = None, seed: int = 0) -> Suite:
    if name not in SUITES:
        raise ValueError(f"eval: unknown suite {name!r} (use one of: {', '.join(SUITES)})")
    cfg = with_overrides(cfg, {"sim": {"seed": seed}})
    if name == "table1":
        return suite_table1(cfg, runs)
    if name == "latency":
        return suite_latency(cfg, runs)
    if name == "vrel":
        return suite_vrel(cfg, runs)
    return suite_baseline(cfg, runs, seed)


def run_suite(name: str, cfg: Config, *, runs: int | None = None, seed: int = 0, n_jobs: int = 2,
              progress: bool = True, camera: str = "geometric", protocol: str = "engagement") -> dict:
    """Run a suite; returns the JSON-able result (per-run, groups, total, markdown, paper)."""
    suite = build_suite(name, cfg, runs, seed)
    suite.jobs = [Job(j.cfg, replace(j.spec, camera=camera, protocol=protocol), j.group) for j in suite.jobs]
    t0 = time.perf_counter()
    results = run_jobs(suite.jobs, suite.radii, n_jobs, progress, desc=name)
    wall = time.perf_counter() - t0
    groups, md = suite.report(results, suite.radii)
    total = aggregate(results, suite.radii)
    md += "\n\n" + setpoint_table(groups, total)
    sim_s = sum(r["sim_time_s"] for r in results)
    return {
        "suite": name,
        "seed": seed,
        "radii": suite.radii,
        "total": total,
        "groups": groups,
        "markdown": md,
        "paper": PAPER[name],
        "wall_time_s": wall,
        "sim_time_s": sim_s,
        "jobs": n_jobs,
        "camera": camera,
        "protocol": protocol,
        "config": config_as_dict(cfg),
        "runs": results,
    }


def setpoint_table(groups: dict[str, dict], total: dict) -> str:
    """Commanded attitude per group (companion.metrics over each run's engagement): the largest tilt over
    the runs, and the mean roll-setpoint oscillation (RMS rate; amplitude and frequency of the dominant line)."""
    lines = ["| Group | max tilt deg | roll-setpoint RMS rate deg/s | roll osc. amplitude deg | roll osc. Hz |",
             "|---|---|---|---|---|"]
    for name, g in [*groups.items(), ("total", total)]:
        if "max_tilt_deg" not in g:
            continue
        lines.append(f"| {name} | {_fmt(g['max_tilt_deg'], 1)} | {_fmt(g['roll_osc_rms_rate_dps_mean'], 1)} | "
                     f"{_fmt(g['roll_osc_amp_deg_mean'], 1)} | {_fmt(g['roll_osc_freq_hz_mean'], 2)} |")
    return "\n".join(lines)


# -- Bayesian tuning (paper IV-D) ----------------------------------------------------------------------

REWARDS = {"dt": (10.0, 3.0, 0.0), "d": (0.0, 5.0, 3.0)}  # (c_t, c_d, c) of eq:meth_bo_reward
PAPER_TUNED = {"dt": {"k_pn": 2.10, "gamma_bar": 21.05}, "d": {"k_pn": 1.11, "gamma_bar": 8.91}}
TUNE_MOTIONS = ("linear_slow", "linear_fast", "planar", "knot")  # the paper leaves out stationary


def run_reward(run: dict, reward: str) -> float:
    """eq:meth_bo_reward ``max(0, c_t / t_gate - c_d d_center + c)``; a run that never crossed scores 0."""
    c_t, c_d, c = REWARDS[reward]
    if not run["crossed"]:
        return 0.0
    return max(0.0, c_t / run["t_gate_s"] - c_d * run["d_center_m"] + c)


def tune(cfg: Config, *, iterations: int = 25, init_points: int = 5, reward: str = "dt", runs_per_motion: int = 2,
         seed: int = 0, n_jobs: int = 2, progress: bool = True, confirm_top: int = 3, confirm_runs: int = 4,
         protocol: str = "engagement") -> dict:
    """Bayesian optimisation of (k_pn, gamma_bar) as in paper V-A: GP with a Matern 2.5 kernel
    (bayes_opt's default), upper-confidence-bound acquisition, k_pn in [0.3, 3], gamma_bar in [5, 30] deg,
    each iteration ``runs_per_motion`` runs of every moving-gate motion (fresh initial conditions).
    Then the ``confirm_top`` best points are flown again (``confirm_runs`` per motion, fresh seeds) and the
    best pooled reward wins (the paper reports the best iteration, which rewards luck with 8 runs)."""
    from bayes_opt import BayesianOptimization, acquisition
    from tqdm import tqdm

    if reward not in REWARDS:
        raise ValueError(f"tune: unknown reward {reward!r} (use one of: {', '.join(REWARDS)})")
    bounds = {"k_pn": (0.3, 3.0), "gamma_bar": (5.0, 30.0)}
    opt = BayesianOptimization(f=None, pbounds=bounds, random_state=seed, verbose=0, allow_duplicate_points=True,
                               acquisition_function=acquisition.UpperConfidenceBound(kappa=2.576))
    rng = np.random.default_rng(np.random.SeedSequence([seed, 4]))
    cfg = with_overrides(cfg, {"sim": {"seed": seed}})
    history = []
    for it in tqdm(range(init_points + iterations), desc="tune", unit="iter", disable=not progress, file=sys.stderr):
        if it < init_points:
            params = {k: float(rng.uniform(*b)) for k, b in bounds.items()}
        else:
            params = {k: float(v) for k, v in opt.suggest().items()}
        c = with_overrides(cfg, {"guidance": params})
        jobs = [Job(c, RunSpec(m, seed=it * 100 + k * 10 + i, protocol=protocol), {"motion": m})
                for k, m in enumerate(TUNE_MOTIONS) for i in range(runs_per_motion)]
        runs = run_jobs(jobs, [1.0], n_jobs, progress=False)
        target = float(np.mean([run_reward(r, reward) for r in runs]))
        opt.register(params=params, target=target)
        history.append({"iteration": it, **params, "reward": target,
                        "success_1m": float(np.mean([r["success"]["1.0"] for r in runs])), **setpoint_metrics(runs)})
    # The best single iteration saw 2 runs per motion: its reward is partly luck. Re-fly the best few on fresh
    # initial conditions and keep the one that holds up (mean over both samples).
    top = sorted(history, key=lambda h: h["reward"], reverse=True)[:confirm_top]
    for k, h in enumerate(top):
        c = with_overrides(cfg, {"guidance": {"k_pn": h["k_pn"], "gamma_bar": h["gamma_bar"]}})
        jobs = [Job(c, RunSpec(m, seed=100_000 + k * 1000 + j * 10 + i, protocol=protocol), {"motion": m})
                for j, m in enumerate(TUNE_MOTIONS) for i in range(confirm_runs)]
        runs = run_jobs(jobs, [1.0], n_jobs, progress=False)
        n0, n1 = runs_per_motion, confirm_runs
        h["confirm_reward"] = float(np.mean([run_reward(r, reward) for r in runs]))
        h["confirm_success_1m"] = float(np.mean([r["success"]["1.0"] for r in runs]))
        h["pooled_reward"] = (n0 * h["reward"] + n1 * h["confirm_reward"]) / (n0 + n1)
    best = max(top or history, key=lambda h: h.get("pooled_reward", h["reward"]))
    md = ("| reward | k_pn ours (paper) | gamma_bar deg ours (paper) | mean reward | success 1 m |\n"
          f"|---|---|---|---|---|\n| R_{reward} | {best['k_pn']:.2f} ({PAPER_TUNED[reward]['k_pn']:.2f}) | "
          f"{best['gamma_bar']:.2f} "
          f"({PAPER_TUNED[reward]['gamma_bar']:.2f}) | {best['reward']:.2f} | {best['success_1m']:.2f} |")
    return {"suite": "tune", "reward": reward, "seed": seed, "protocol": protocol, "best": best, "history": history,
            "markdown": md,
            "paper": PAPER_TUNED[reward], "config": config_as_dict(cfg)}


# -- plots -------------------------------------------------------------------------------------------


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


# -- command line -------------------------------------------------------------------------------------


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "eval", help="run an evaluation suite of the paper on the in-process simulator",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("suite", choices=(*SUITES, "tune"),
                   help="which study to run (tune: Bayesian optimisation of k_pn and gamma_bar, paper IV-D)")
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
    p.add_argument("--autopilot", choices=("in-process", "px4"), default="in-process",
                   help="px4: table1 in real time on PX4 SITL (SIH) with the complete app, one PX4 instance per "
                   "--jobs (companion/px4sitl/evaluate.py)")
    p.add_argument("--px4-dir", default=None, metavar="DIR", help="PX4 SITL build (default px4.sitl_dir, "
                   "$PX4_SITL_DIR)")
    p.add_argument("--motions", default=None, metavar="M1,M2", help="only these gate motions (--autopilot px4)")
    add_config_arguments(p)
    p.set_defaults(func=_cmd_eval)


def _cmd_eval(args: argparse.Namespace) -> int:
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
    if args.autopilot == "px4":
        from companion.px4sitl.evaluate import cmd_eval_px4

        return cmd_eval_px4(args, cfg, out_dir)
    try:
        res = run_suite(args.suite, cfg, runs=args.runs, seed=args.seed, n_jobs=min(args.jobs, os.cpu_count() or 1),
                        progress=not args.no_progress, camera=args.camera, protocol=args.protocol)
    except ValueError as e:  # e.g. the rendered camera's detector model is missing
        print(f"companion eval: {e}", file=sys.stderr)
        return 2
    json_path = args.json if args.json is not None else out_dir / "results.json"
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(res, indent=1, default=_json_default))
    cmd = "companion eval " + " ".join(sys.argv[2:]) if len(sys.argv) > 2 else f"companion eval {args.suite}"
    md = (f"## {args.suite}\n\nCommand: `{cmd}`  \nProtocol: {args.protocol}. "
          f"Runs: {len(res['runs'])}, seed {args.seed}, "
          f"{res['sim_time_s']:.0f} s simulated in {res['wall_time_s']:.1f} s wall on {res['jobs']} process(es). "
          f"Ours first, the paper's in brackets.\n\n{res['markdown']}\n")
    (out_dir / "table.md").write_text(md)
    print(md)
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
               protocol=args.protocol)
    json_path = args.json if args.json is not None else out_dir / "results.json"
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(res, indent=1, default=_json_default))
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


def write_tuned_overlay(path: Path, best: dict, reward: str, config_files: list[str], seed: int, iterations: int,
                        init_points: int, runs_per_motion: int, protocol: str = "engagement") -> None:
    """A config overlay with the tuned values that includes the --config files the tuning ran with, so one
    ``--config PATH`` reproduces the tuned vehicle (``include`` paths are relative to the overlay)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    inc = [os.path.relpath(Path(f).resolve(), path.parent.resolve()) for f in config_files]
    c_t, c_d, c = REWARDS[reward]
    lines = [f"# Bayesian tuning result, reward R_{reward} (c_t {c_t:g}, c_d {c_d:g}, c {c:g}), paper IV-D / V-A.",
             f"# companion eval tune --reward {reward} --seed {seed} --iterations {iterations} --init-points "
             f"{init_points} --protocol {protocol} ({runs_per_motion} runs per moving-gate motion per iteration)"
             + "".join(f" --config {f}" for f in config_files),
             f"# best: reward {best['reward']:.3f} (confirmation {best.get('confirm_reward', float('nan')):.3f}), "
             f"success 1 m {best['success_1m']:.2f} (confirmation {best.get('confirm_success_1m', float('nan')):.2f})"]
    if inc:
        lines += ["include:"] + [f"  - {i}" for i in inc]
    lines += ["guidance:", f"  k_pn: {best['k_pn']:.3f}", f"  gamma_bar: {best['gamma_bar']:.3f} deg", ""]
    path.write_text("\n".join(lines))


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, tuple):
        return list(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


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
