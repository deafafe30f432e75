"""What each suite of ``companion eval`` runs and how it aggregates (paper section V-A).

``table1`` (Table I), ``latency`` (Fig. "robustness_latency"), ``vrel`` (Table "relative_velocity_estimation")
and ``baseline`` (Table III): each suite is a list of jobs (config, RunSpec, the group it belongs to) and a
report that aggregates the per-run results by group into the paper's table, with the paper's numbers
(``PAPER``) beside ours. Where the runs are flown is not this module's business: companion.evaluation.pool
(in process) or companion.evaluation.px4 (PX4 SITL), chosen by companion.evaluation.dispatch.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.evaluation.intercept import PAPER_INTERCEPT, suite_intercept
from companion.evaluation.stats import add_intervals, fmt_rate
from companion.evaluation.tables import fmt, reasons
from companion.sim.runner import RunSpec, with_overrides
from companion.sim.scoring import aggregate, rkey

if TYPE_CHECKING:
    from companion.config import Config

SUITES = ("table1", "latency", "vrel", "baseline", "intercept")

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
    "intercept": PAPER_INTERCEPT,  # companion/evaluation/intercept.py
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


# -- suites ------------------------------------------------------------------------------------------


def _per(runs: int, cells: int) -> int:
    return max(1, runs // cells)


def _groups(results: list[dict], key: Callable[[dict], str], radii: list[float]) -> dict[str, dict]:
    names: list[str] = []
    for r in results:
        if key(r) not in names:
            names.append(key(r))
    return {n: add_intervals(aggregate([r for r in results if key(r) == n], radii)) for n in names}


def app_run_seed(table_seed: int, run_seed: int) -> int:
    """The single ``sim.seed`` an app flight (PX4 SITL) runs on, for run ``run_seed`` of a table flown with
    ``--seed table_seed``: the in-process runner mixes both (SeedSequence([sim.seed, spec.seed])), the app takes
    one number. Seed 0 keeps the run's own seed (every PX4 table before 2026-12-02 flew those scenarios); other
    table seeds give other scenarios (before, ``--seed`` changed nothing on PX4: every seed flew seed 0's runs)."""
    if table_seed == 0:
        return run_seed
    return int(np.random.SeedSequence([table_seed, run_seed]).generate_state(1, np.uint32)[0] >> 1)


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
        total = add_intervals(aggregate(results, radii))
        for m in rows:
            g = total if m == "total" else groups.get(m)
            if g is None:
                continue
            lines.append(
                f"| {m} | {fmt_rate(g, '1.0')} ({p['success_1m'][m]:.2f}) | "
                f"{fmt_rate(g, '2.0')} ({p['success_2m'][m]:.2f}) | {fmt(g['t_gate_mean_s'])} "
                f"({p['t_gate_s'][m]:.2f}) | {fmt(g['d_center_mean_m'])} | {fmt(g['top_speed_mps'], 1)} | "
                f"{reasons(g, '1.0')} |")
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
            cells = [f"{fmt_rate(g, rkey(r))} ({PAPER['latency'][rkey(r)][f'{d:.1f}']:.2f})" for r in radii]
            lines.append(f"| {d * 1000:.0f} | " + " | ".join(cells) + f" | {fmt(g['t_gate_mean_s'])} |")
        by_motion = _groups(results, lambda r: f"{r['motion']} @ {r['delay_s'] * 1000:.0f} ms", radii)
        lines += ["", "| Motion @ delay | " + " | ".join(f"Success {r:g} m" for r in radii) + " |",
                  "|---" * (len(radii) + 1) + "|"]
        for name, g in by_motion.items():
            lines.append(f"| {name} | " + " | ".join(fmt_rate(g, rkey(r)) for r in radii) + " |")
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
                    f"| {dist} | {fmt(g['top_speed_mean_mps'], 1)} ({PAPER['vrel']['top_speed_mps'][dist]:.0f}) | "
                    f"{label} | {fmt(g['d_center_mean_m'])} ± {fmt(g['d_center_std_m'])} ({pm:.2f} ± {ps:.2f}) | "
                    f"{fmt_rate(g, '1.0')} |")
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
                f"| {label} | {fmt_rate(b, '0.5')} ({pb['baseline']:.2f}) | {fmt_rate(o, '0.5')} "
                f"({pb['pn']:.2f}) | {fmt(b['t_gate_mean_s'])} / {fmt(o['t_gate_mean_s'])} | "
                f"{reasons(b, '0.5')} / {reasons(o, '0.5')} |")
        return groups, "\n".join(lines)

    return Suite("baseline", jobs, [0.5, 1.0, 2.0], report, ["trajectories"])


def deep(a: dict, b: dict) -> dict:
    from companion.configbase import deep_merge

    return deep_merge(b, a)

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
    if name == "intercept":
        return suite_intercept(cfg, runs, seed)  # type: ignore[return-value]  # duck-typed Suite
    return suite_baseline(cfg, runs, seed)
