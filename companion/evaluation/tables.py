"""The Markdown and JSON of ``companion eval``: number formatting, the tables every suite adds to its own
(commanded attitude; frame-to-setpoint latency on PX4), the page header of table.md, JSON encoding."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from companion.config import Config


def fmt(x: float | None, nd: int = 2) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{nd}f}"


def reasons(g: dict, r: str) -> str:
    f = g.get("failures", {}).get(r, {})
    return ", ".join(f"{k} {v}" for k, v in sorted(f.items())) or "-"


def setpoint_table(groups: dict[str, dict], total: dict) -> str:
    """Commanded attitude per group (companion.metrics over each run's engagement): the largest tilt over
    the runs, and the mean roll-setpoint oscillation (RMS rate; amplitude and frequency of the dominant line)."""
    lines = ["| Group | max tilt deg | roll-setpoint RMS rate deg/s | roll osc. amplitude deg | roll osc. Hz |",
             "|---|---|---|---|---|"]
    for name, g in [*groups.items(), ("total", total)]:
        if "max_tilt_deg" not in g:
            continue
        lines.append(f"| {name} | {fmt(g['max_tilt_deg'], 1)} | {fmt(g['roll_osc_rms_rate_dps_mean'], 1)} | "
                     f"{fmt(g['roll_osc_amp_deg_mean'], 1)} | {fmt(g['roll_osc_freq_hz_mean'], 2)} |")
    return "\n".join(lines)


def _by_motion(results: list[dict]) -> list[tuple[str, list[dict]]]:
    """(motion, its runs) in first-seen order, then ("total", every run)."""
    groups: dict[str, list[dict]] = {}
    for r in results:
        groups.setdefault(r.get("motion", "?"), []).append(r)
    return [*groups.items(), ("total", results)]


def latency_table(results: list[dict]) -> str:
    """PX4 runs: the app's frame-to-setpoint latency (from its summary) and how its flights ended, by motion."""
    lines = ["| Gate motion | runs | frame->setpoint p50 ms (mean) | p95 ms (max) | app outcomes |",
             "|---|---|---|---|---|"]
    for name, rs in _by_motion(results):
        p50 = [r["latency_p50_ms"] for r in rs if r.get("latency_p50_ms") is not None]
        p95 = [r["latency_p95_ms"] for r in rs if r.get("latency_p95_ms") is not None]
        outcomes: dict[str, int] = {}
        for r in rs:
            k = str(r.get("reason") or r.get("end_reason"))
            outcomes[k] = outcomes.get(k, 0) + 1
        lines.append(f"| {name} | {len(rs)} | {np.mean(p50):.1f} | {np.max(p95):.1f} | "
                     f"{', '.join(f'{k} {v}' for k, v in sorted(outcomes.items()))} |" if p50 else
                     f"| {name} | {len(rs)} | - | - | {', '.join(f'{k} {v}' for k, v in sorted(outcomes.items()))} |")
    return "\n".join(lines)


def claims_table(results: list[dict], radius: str) -> str:
    """PX4 runs: the app's own word on the pass (``gates_passed_app``, a pass confirmed by the camera) against the
    truth (crossed within ``radius`` m of the centre), by motion: an outcome must be true of the vehicle."""
    lines = [f"| Gate motion | runs | through {radius} m (truth) | pass claimed | claimed and through | claimed, not "
             f"through | through, not claimed |", "|---|---|---|---|---|---|---|"]
    for name, rs in _by_motion(results):
        through = [bool((r.get("success") or {}).get(radius)) for r in rs]
        claimed = [(r.get("gates_passed_app") or 0) > 0 for r in rs]
        both = sum(c and t for c, t in zip(claimed, through, strict=True))
        lines.append(f"| {name} | {len(rs)} | {sum(through)} | {sum(claimed)} | {both} | {sum(claimed) - both} | "
                     f"{sum(through) - both} |")
    return "\n".join(lines)


# What the PX4 suites' times measure (their runs start in PX4's hover).
PX4_TIMES = {"table1": "t_gate: ENGAGE to the gate plane (runs start in hover 25 m away).",
             "intercept": "Duration: ENGAGE to the pull-up (runs start in hover 12 m up, the target 30-50 m ahead)."}


def suite_markdown(res: dict[str, Any], cmd: str, cfg: Config) -> str:
    """table.md: what ran (command, protocol or PX4 set-up, runs, seed, time) above the suite's tables."""
    if res.get("autopilot") == "px4":
        sih = cfg.px4.sih
        return (f"## {res['suite']} on PX4 SITL (SIH)\n\nCommand: `{cmd}`  \nReal PX4 v1.15 SITL, SIH vehicle "
                f"{sih.mass:g} kg, thrust-to-weight {sih.thrust_to_weight:.2f}, drag {sih.kdv:g} N/(m/s); "
                f"the complete app (start=pilot, hand back to Hold), camera {res['camera']}; scored by SIH's ground "
                f"truth. Runs: {len(res['runs'])}, seed {res['seed']}, {res['wall_time_s'] / 60:.1f} min wall on "
                f"{res['jobs']} PX4 instance(s). {PX4_TIMES.get(res['suite'], PX4_TIMES['table1'])} "
                f"Ours first, the paper's in brackets.\n\n{res['markdown']}\n")
    return (f"## {res['suite']}\n\nCommand: `{cmd}`  \nProtocol: {res['protocol']}. "
            f"Runs: {len(res['runs'])}, seed {res['seed']}, "
            f"{res['sim_time_s']:.0f} s simulated in {res['wall_time_s']:.1f} s wall on {res['jobs']} process(es). "
            f"Ours first, the paper's in brackets.\n\n{res['markdown']}\n")


def json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, tuple):
        return list(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
