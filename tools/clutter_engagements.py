"""Engagements of clutter in the in-process rendered study: each frame's box the engagement used, against the
rendered gate's true box (perception/simcamera.py ``last_truth``), tallied by companion/engagetally.py.

    PYTHONPATH=. python tools/clutter_engagements.py --runs 20 --seed 0 [--set app.verify.enabled=false ...]

Runs the same jobs as ``companion eval table1 --camera rendered --runs N --seed S --jobs 1`` (one process) with
two read-only hooks: the rendered camera keeps its truth box per capture time, the engagement's step hands its
phase, events and used box to the tally. Prints success and the tally as JSON.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace

import numpy as np

from companion.config import load_config
from companion.engagement import Engagement
from companion.engagetally import EngagementTally, total
from companion.evaluation.pool import _work
from companion.evaluation.suites import build_suite
from perception.simcamera import RenderedCamera


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    a = ap.parse_args()
    cfg = load_config([], a.overrides)
    truths: dict[float, np.ndarray] = {}
    tally: list[EngagementTally] = []
    cap0, step0 = RenderedCamera.capture, Engagement.step

    def capture(self, t, *args, **kw):  # type: ignore[no-untyped-def]
        box = cap0(self, t, *args, **kw)
        tb = self.last_truth
        truths[round(t, 6)] = np.array([tb.xyxy]) if tb is not None else np.zeros((0, 4))
        return box

    def step(self, t, *args, **kw):  # type: ignore[no-untyped-def]
        d = step0(self, t, *args, **kw)
        end = f"{d.phase.value} {d.reason.name if d.reason else ''}".strip() if d.changed and d.phase.done else ""
        tally[-1].add(d.phase.value, d.events, self.used_box, truths.get(round(t, 6)), end)
        return d

    RenderedCamera.capture, Engagement.step = capture, step  # type: ignore[method-assign]
    suite = build_suite("table1", cfg, a.runs, a.seed)
    per, ok = [], 0
    for i, j in enumerate(suite.jobs):
        j = replace(j, spec=replace(j.spec, camera="rendered"))
        tally.append(EngagementTally(min_spell=cfg.app.acquire_frames))
        truths.clear()
        _, res = _work((i, j, suite.radii))
        d = tally[-1].finish()
        d["success"] = bool(res["success"]["1.0"])  # Table I's 1 m gate
        d["seed"], d["motion"] = res.get("seed"), res.get("motion")
        per.append(d)
        ok += d["success"]
    tot = total(per)
    wrong_runs = [(d["motion"], d["seed"]) for d in per if d["begun_on_wrong"] or d["passes_claimed_wrong"]]
    print(json.dumps({"runs": len(per), "success_1m": ok, "total": tot, "runs_with_wrong": wrong_runs,
                      "per_run": [{k: d[k] for k in ("motion", "seed", "success", "engagements", "begun_on_wrong",
                                                     "engaged_frames_wrong", "passes_claimed_wrong", "ends")}
                                  for d in per]}, indent=1, default=str))


if __name__ == "__main__":
    main()
