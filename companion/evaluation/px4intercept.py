"""``companion eval intercept --autopilot px4``: the intercept suite's runs as app flights on PX4 SIH, and their
score from SIH's truth (issue 19).

The runs are the in-process suite's (companion/evaluation/intercept.py: same seeds, target speeds and start
distances) for the groups PX4 can fly here: ``truck``, ``air`` and ``ground`` (SIH flies without wind: the
``wind`` group and the evasive rows stay in-process). Each is one flight of the complete app with the synthetic
camera (companion/app/synthcam.py: a 2.5 x 3 m rectangle, receding, in the air or standing on the ground; the
geometric box: the renderer draws rings) from PX4's hover 12 m up (companion/evaluation/px4.py's start points;
in-process a ground intercept starts 4-8 m up).

Scored by ground truth with the one pull-up scorer (companion/scoring.py ``PullUpScorer``), twice:

* live, by the app's judge (companion/app/outcome.py, SIH's truth as it arrived): its numbers are the flight's
  summary.json ``truth.intercepts`` and its verdict the flight's exit code;
* again here from the flight log (truth.csv, every 50 ms, and gate.csv on the log's clock), independently of
  the live samples: ``rescored_*`` keys. Where the two disagree about "cleared" (>= 1 m) the run is flagged.

The keys are the in-process runs' (``pullup_*``, ``engagement_end``) so report_intercept tables both alike.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.evaluation.intercept import GOALS, INTERCEPT_GROUPS, TARGET_H, TARGET_W, suite_intercept
from companion.evaluation.suites import app_run_seed

if TYPE_CHECKING:
    from companion.config import Config
    from companion.flightlog import Flight

PX4_GROUPS = ("truck", "air", "ground")  # SIH flies without wind here


def px4_intercept_runs(cfg: Config, runs: int | None, seed: int, camera: str
                       ) -> tuple[list[tuple[dict[str, Any], tuple[str, ...]]], Any]:
    """[(group, config overrides)] of ``runs`` app flights (groups interleaved), and the suite (radii, report)."""
    if camera != "geometric":
        raise ValueError("eval intercept --autopilot px4: the rectangular target needs --camera geometric "
                         "(the renderer draws rings)")
    n = runs or 20
    per = math.ceil(n / len(PX4_GROUPS))
    suite = suite_intercept(cfg, per * len(INTERCEPT_GROUPS), seed)
    by = {g: [j for j in suite.jobs if j.group.get("group") == g] for g in PX4_GROUPS}
    order = [by[g][i] for i in range(per) for g in PX4_GROUPS if i < len(by[g])][:n]
    out = []
    for j in order:
        g = j.group
        # In the air: the target's centre within 1 m of the vehicle's height (in-process: +-1 m), from the seed.
        dz = 0.0 if g["on_ground"] else float(np.random.default_rng([seed, j.spec.seed]).uniform(-1.0, 1.0))
        ov = ("app.on_close=pull_up", f"app.target_width={TARGET_W}", f"app.target_height={TARGET_H}",
              f"guidance.gate_radius={0.5 * max(TARGET_W, TARGET_H)}", "sim.target.shape=rectangle",
              f"sim.target.width={TARGET_W}", f"sim.target.height={TARGET_H}",
              f"sim.target.on_ground={str(bool(g['on_ground'])).lower()}",
              f"sim.gates.recede_speed={g['target_speed_mps']}", "app.synthetic.motion=recede",
              f"app.synthetic.distance={g['start_m']}", f"app.synthetic.height_offset={dz}",
              "app.synthetic.render=geometric", f"sim.seed={app_run_seed(seed, j.spec.seed)}")
        out.append(({**g, "seed": j.spec.seed, "sim_seed": app_run_seed(seed, j.spec.seed), "height_offset_m": dz},
                    ov))
    return out, suite


def intercept_keys(f: Flight) -> dict[str, Any]:
    """A flight's intercept score in the in-process keys; {} for a flight not configured to pull up."""
    from companion.scoring import PullUpScorer

    if (f.config.get("app") or {}).get("on_close") != "pull_up":
        return {}  # not an intercept (Table I's flights keep their keys)
    s = f.summary
    truth = s.get("truth") if isinstance(s.get("truth"), dict) else {}
    icpt = truth.get("intercepts") or []
    states = s.get("states") or []
    # The engagement's end as the in-process runs name it: a hand-back, or the abort's reason.
    end = "HANDBACK" if "HANDBACK" in states else str(s.get("reason"))
    passes = s.get("passes") or []
    pulled = [p for p in passes if p.get("status") == "pulled_up"]
    base: dict[str, Any] = {"engagement_end": end, "app_verdict": s.get("verdict"), "app_reason": s.get("reason")}
    if not pulled:
        return {**base, "pullup_pulled_up": False}
    t0 = float(f.meta.get("t0_monotonic", 0.0))
    st = f.tables.get("states")
    t_engage = None
    if st is not None and len(st):
        eng = [float(t) for t, to in zip(st["t"], st["to_state"], strict=True) if to == "ENGAGE"]
        t_engage = eng[0] if eng else None
    t_pull = float(pulled[0]["t_end"]) - t0  # the pull-up on the log's clock (the frame clock is monotonic)
    r = icpt[0] if icpt else {}
    out = {**base, "pullup_pulled_up": True, "pullup_predicted_miss_m": r.get("predicted_miss_m"),
           "pullup_on_target": r.get("on_target"), "pullup_clearance_m": r.get("clearance_m"),
           "pullup_speed_at_pullup_mps": r.get("speed_at_pullup_mps"), "pullup_range_m": r.get("range_at_pullup_m"),
           # duration: ENGAGE (from PX4's hover) to the pull-up; in-process it is from the run's start
           "pullup_t_pullup_s": None if t_engage is None else t_pull - t_engage}
    tr, gt = f.tables.get("truth"), f.tables.get("gate")
    if tr is None or gt is None or not len(tr) or not len(gt):
        return out
    k = int(r.get("gate", 1))
    sel = gt["k"] == k
    tg = gt["t"][sel]
    if len(tg) < 2:
        return out
    normal = np.array([gt[c][sel][0] for c in ("normal_n", "normal_e", "normal_d")])
    inside = (tr["t"] >= tg[0]) & (tr["t"] <= tg[-1]) & np.isfinite(tr["n"]) & np.isfinite(tr["vn"])
    tt = tr["t"][inside]
    p = np.column_stack([tr[c][inside] for c in ("n", "e", "d")])
    v = np.column_stack([tr[c][inside] for c in ("vn", "ve", "vd")])
    c = np.column_stack([np.interp(tt, tg, gt[x][sel]) for x in ("gate_n", "gate_e", "gate_d")])
    cv = np.column_stack([np.interp(tt, tg, np.gradient(gt[x][sel], tg)) for x in ("gate_n", "gate_e", "gate_d")])
    w, h = float(r.get("width_m", TARGET_W)), float(r.get("height_m", TARGET_H))
    sc = PullUpScorer(normal, 0.5 * w, 0.5 * h)  # NED: its min_altitude is not used here
    for i in range(len(tt)):
        sc.update(float(tt[i]), p[i], v[i], c[i], cv[i], bool(tt[i] >= t_pull))
    after = tr["t"] >= (t_engage if t_engage is not None else -math.inf)
    d = sc.as_dict()
    out.update({"rescored_predicted_miss_m": d["predicted_miss_m"], "rescored_clearance_m": d["clearance_m"],
                "pullup_min_altitude_m": float(-np.max(tr["d"][after])) if after.any() else None})
    live, again = out["pullup_clearance_m"], d["clearance_m"]
    out["scores_agree"] = (live is not None and again is not None
                           and (live >= GOALS["cleared_m"]) == (again >= GOALS["cleared_m"]))
    return out
