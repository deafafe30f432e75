"""``companion eval intercept``: the paper's end-to-end experiment (a receding truck, a pull-up before impact) in
the in-process simulator, scored by truth, with the evasive sinusoid gate as a reported row.

Groups (``--runs N``: N intercepts spread evenly over the four intercept groups, and as many runs again in each
evasive row as in one intercept group; every intercept draws its own target speed and start distance):

* ``truck``   the paper's: a 2.5 m x 3 m target standing on the ground, driving away at 8-10 m/s, the vehicle
              40 m behind (4-8 m up), ``app.on_close: pull_up``;
* ``air``     the same target in the air (the vehicle 10-20 m up, the target +-1 m of it), 6-10 m/s, 30-50 m;
* ``ground``  on the ground, 6-10 m/s, 30-50 m;
* ``wind``    air and ground alternating, 6-10 m/s, 30-50 m, 3 m/s mean wind from a random direction, 1 m/s gusts;
* ``evasive`` (reported, no goal) a 1 m ring swinging sideways at 3 m/s peak, 0.5 Hz (sinusoid), flown through;
  ``evasive_tilt70`` the same with the tilt envelope at 70 deg instead of 50 deg: what limits it.

Scores (companion/sim/scoring.py PullUpScorer, ground truth): *reached* = the predicted miss at the pull-up (the
vehicle's and the target's last velocities before it, extrapolated to the target's plane, distance from its
centre; the paper: 0.9 m) <= 0.9 m; *cleared* = the least distance between the vehicle and the target's box after
the pull-up (through the hand-back and 2 s of Hold) >= 1 m; top speed; duration (start to pull-up; the paper:
4.9 s); floor trips. Rates with 95 % Wilson intervals.

Jobs and the suite are duck-typed like companion/evaluation/suites.py's Job and Suite (the pool reads ``cfg``,
``spec``, ``group``; ``jobs``, ``radii``, ``report``): suites.py lists this suite and imports it, not the other
way round.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.stats import binomtest

from companion.sim.runner import RunSpec, with_overrides
from companion.sim.scoring import aggregate

if TYPE_CHECKING:
    from companion.config import Config

PAPER_INTERCEPT = {"predicted_miss_m": 0.9, "top_speed_mps": 23.6, "duration_s": 4.9}
GOALS = {"reached_m": 0.9, "reached_rate": 0.95, "cleared_m": 1.0, "cleared_rate": 1.0}
TARGET_W, TARGET_H = 2.5, 3.0  # m, the paper's truck seen from behind
INTERCEPT_GROUPS = ("truck", "air", "ground", "wind")
EVASIVE_GROUPS = ("evasive", "evasive_tilt70")


@dataclass
class Job:
    cfg: Config
    spec: RunSpec
    group: dict[str, Any]


@dataclass
class Suite:
    name: str
    jobs: list[Job]
    radii: list[float]
    report: Callable[[list[dict], list[float]], tuple[dict, str]]
    plots: list[str] = field(default_factory=list)


def wilson(k: int, n: int) -> tuple[float, float]:
    """95 % Wilson score interval of k successes in n."""
    if n == 0:
        return math.nan, math.nan
    ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    return float(ci.low), float(ci.high)


def truck_overrides(*, speed: float, distance: float, ground: bool, wind: tuple[float, float] | None = None
                    ) -> dict:
    """The config of one intercept run (a nested override dict)."""
    sim: dict[str, Any] = {
        "target": {"shape": "rectangle", "width": TARGET_W, "height": TARGET_H, "on_ground": ground},
        "gates": {"recede_speed": speed},
        "scenario": {"distance_min": distance, "distance_max": distance, "timeout": 30.0},
    }
    if ground:
        sim["scenario"].update({"altitude_min": 4.0, "altitude_max": 8.0})
    if wind is not None:
        sim["wind"] = {"mean": [wind[0], wind[1], 0.0], "gust_std": 1.0}
    return {"app": {"on_close": "pull_up", "target_width": TARGET_W, "target_height": TARGET_H},
            "guidance": {"gate_radius": 0.5 * max(TARGET_W, TARGET_H)}, "sim": sim}


def suite_intercept(cfg: Config, runs: int | None = None, seed: int = 0) -> Suite:
    n = max(1, (runs or 120) // len(INTERCEPT_GROUPS))  # --runs counts the intercepts; each evasive row adds n
    rng = np.random.default_rng(np.random.SeedSequence([seed, 19]))
    jobs: list[Job] = []
    for k, grp in enumerate(INTERCEPT_GROUPS):
        for i in range(n):
            if grp == "truck":
                speed, dist, ground = float(rng.uniform(8.0, 10.0)), 40.0, True
            else:
                speed, dist = float(rng.uniform(6.0, 10.0)), float(rng.uniform(30.0, 50.0))
                ground = grp == "ground" or (grp == "wind" and i % 2 == 1)
            wind = None
            if grp == "wind":
                a = float(rng.uniform(0.0, 2 * math.pi))
                wind = (3.0 * math.cos(a), 3.0 * math.sin(a))
            c = with_overrides(cfg, truck_overrides(speed=speed, distance=dist, ground=ground, wind=wind))
            jobs.append(Job(c, RunSpec("recede", seed=k * 1000 + i),
                            {"group": grp, "target_speed_mps": speed, "start_m": dist, "on_ground": ground,
                             "wind": wind is not None}))
    for k, grp in enumerate(EVASIVE_GROUPS):
        over: dict[str, Any] = {"app": {"on_close": "fly_through"},
                                "sim": {"gates": {"sinusoid_amplitude": 3.0 / (2 * math.pi * 0.5),
                                                  "sinusoid_frequency": 0.5}}}
        if grp == "evasive_tilt70":
            over["airframe"] = {"max_tilt": 70.0}
        c = with_overrides(cfg, over)
        jobs += [Job(c, RunSpec("sinusoid", seed=(10 + k) * 1000 + i), {"group": grp}) for i in range(n)]
    return Suite("intercept", jobs, [0.5, 1.0, 2.0], report_intercept)


def _rate(flags: list[bool]) -> str:
    k, n = sum(flags), len(flags)
    if n == 0:
        return "-"
    lo, hi = wilson(k, n)
    return f"{k}/{n} = {k / n:.2f} [{lo:.2f}, {hi:.2f}]"


def intercept_stats(rs: list[dict]) -> dict[str, Any]:
    """Per group: reached / cleared counts, misses, clearances, speeds, durations, floor trips."""
    miss = [r.get("pullup_predicted_miss_m") for r in rs]
    clear = [r.get("pullup_clearance_m") for r in rs]
    reached = [m is not None and m <= GOALS["reached_m"] for m in miss]
    # Cleared: pulled up, handed back (an abort during the pull-up leaves the rest to PX4: not counted as cleared),
    # never touched the ground, and the least distance to the target's box after the pull-up >= 1 m.
    cleared = [bool(r.get("pullup_pulled_up")) and c is not None and c >= GOALS["cleared_m"] and
               r.get("end_reason") != "ground" and r.get("engagement_end") == "HANDBACK"
               for r, c in zip(rs, clear, strict=True)]
    floor = [str(r.get("engagement_end", "")).endswith("ALTITUDE_FLOOR") for r in rs]
    ends: dict[str, int] = {}
    for r in rs:
        e = str(r.get("engagement_end"))
        ends[e] = ends.get(e, 0) + 1
    mv = [m for m in miss if m is not None]
    cv = [c for c in clear if c is not None]
    dur = [r["pullup_t_pullup_s"] for r in rs if r.get("pullup_t_pullup_s") is not None]
    return {
        "runs": len(rs), "reached": sum(reached), "cleared": sum(cleared), "floor_trips": sum(floor),
        "reached_ci": wilson(sum(reached), len(rs)), "cleared_ci": wilson(sum(cleared), len(rs)),
        "miss_median_m": float(np.median(mv)) if mv else None, "miss_max_m": float(max(mv)) if mv else None,
        "clearance_min_m": float(min(cv)) if cv else None,
        "clearance_median_m": float(np.median(cv)) if cv else None,
        "top_speed_mean_mps": float(np.mean([r["top_speed_mps"] for r in rs])) if rs else None,
        "top_speed_max_mps": float(max(r["top_speed_mps"] for r in rs)) if rs else None,
        "speed_at_pullup_mean_mps": float(np.mean([r["pullup_speed_at_pullup_mps"] for r in rs
                                                   if r.get("pullup_speed_at_pullup_mps") is not None]))
        if any(r.get("pullup_speed_at_pullup_mps") is not None for r in rs) else None,
        "duration_mean_s": float(np.mean(dur)) if dur else None, "ends": ends,
        "min_altitude_m": min((r["pullup_min_altitude_m"] for r in rs if r.get("pullup_min_altitude_m") is not None),
                              default=None),
        "_reached": reached, "_cleared": cleared,
    }


def _f(x: float | None, nd: int = 2) -> str:
    return "-" if x is None else f"{x:.{nd}f}"


def report_intercept(results: list[dict], radii: list[float]) -> tuple[dict, str]:
    p = PAPER_INTERCEPT
    groups: dict[str, dict] = {}
    lines = ["| Group | runs | reached: miss <= 0.9 m [95 % CI] | cleared >= 1 m [95 % CI] | miss median / max m "
             f"(paper {p['predicted_miss_m']}) | clearance min / median m | top speed mean / max m/s (paper "
             f"{p['top_speed_mps']}) | speed at pull-up m/s | duration s (paper {p['duration_s']}) | floor trips | "
             "lowest altitude m | ends |", "|---" * 12 + "|"]
    everything: list[dict] = []
    for grp in (*INTERCEPT_GROUPS, "all"):
        rs = [r for r in results if r.get("group") in INTERCEPT_GROUPS] if grp == "all" else [
            r for r in results if r.get("group") == grp]
        if not rs:
            continue
        if grp != "all":
            everything += rs
        st = intercept_stats(rs)
        groups[grp] = {**aggregate(rs, radii), **{k: v for k, v in st.items() if not k.startswith("_")}}
        lines.append(
            f"| {grp} | {st['runs']} | {_rate(st['_reached'])} | {_rate(st['_cleared'])} | "
            f"{_f(st['miss_median_m'])} / {_f(st['miss_max_m'])} | {_f(st['clearance_min_m'])} / "
            f"{_f(st['clearance_median_m'])} | {_f(st['top_speed_mean_mps'], 1)} / {_f(st['top_speed_max_mps'], 1)} | "
            f"{_f(st['speed_at_pullup_mean_mps'], 1)} | {_f(st['duration_mean_s'])} | {st['floor_trips']} | "
            f"{_f(st['min_altitude_m'])} | "
            f"{', '.join(f'{k} {v}' for k, v in sorted(st['ends'].items()))} |")
    if everything:
        st = groups["all"]
        ok_r = st["reached"] / st["runs"] >= GOALS["reached_rate"]
        ok_c = st["cleared"] == st["runs"]
        gf = sum(1 for r in everything if r.get("on_ground") and str(r.get("engagement_end", "")).endswith("FLOOR"))
        lines.append(f"\nGoals: reached in >= 95 %: {'met' if ok_r else 'NOT met'}; cleared >= 1 m in 100 %: "
                     f"{'met' if ok_c else 'NOT met'}; no floor trip on a ground target: "
                     f"{'met' if gf == 0 else f'NOT met ({gf})'}.")
    ev_lines = ["", "| Evasive gate (sinusoid 3 m/s, 0.5 Hz; 1 m ring, fly-through) | runs | success 1 m [95 % CI] | "
                "d_center mean m | max tilt deg | runs at the tilt limit | failures (1 m) |",
                "|---|---|---|---|---|---|---|"]
    for grp in EVASIVE_GROUPS:
        rs = [r for r in results if r.get("group") == grp]
        if not rs:
            continue
        g = aggregate(rs, radii)
        groups[grp] = g
        lim = 70.0 if grp.endswith("tilt70") else 50.0
        sat = sum(1 for r in rs if r.get("max_tilt_deg") is not None and r["max_tilt_deg"] >= lim - 0.5)
        fails = g.get("failures", {}).get("1.0", {})
        ev_lines.append(f"| {grp} (envelope {lim:.0f} deg) | {len(rs)} | "
                        f"{_rate([bool(r['success']['1.0']) for r in rs])} | {_f(g.get('d_center_mean_m'))} | "
                        f"{_f(g.get('max_tilt_deg'), 1)} | {sat} | "
                        f"{', '.join(f'{k} {v}' for k, v in sorted(fails.items())) or '-'} |")
    if len(ev_lines) > 3:
        lines += ev_lines
    return groups, "\n".join(lines)
