"""``eval intercept --autopilot px4`` (companion/evaluation/px4intercept.py): the runs PX4 flies are the
in-process suite's (same seeds, target speeds and start distances), as config overrides the app loads, and the
app's judge measures the target the synthetic camera draws. No PX4 here: the flights themselves are a measurement
(docs/intercept.md)."""

from __future__ import annotations

import pytest

from companion.app.outcome import GateJudge
from companion.config import load_config
from companion.evaluation.intercept import report_intercept, suite_intercept
from companion.evaluation.px4intercept import px4_intercept_runs


def test_px4_runs_are_the_in_process_suites_runs_as_app_configs():
    base = load_config([], [])
    runs, suite = px4_intercept_runs(base, 5, 3, "geometric")
    assert [g["group"] for g, _ in runs] == ["truck", "air", "ground", "truck", "air"]  # interleaved, no wind
    inproc = {j.spec.seed: j for j in suite_intercept(base, 8, 3).jobs}  # 2 per group: the same draws
    for g, ov in runs:
        j = inproc[g["seed"]]
        assert g["target_speed_mps"] == j.group["target_speed_mps"] and g["start_m"] == j.group["start_m"]
        cfg = load_config([], list(ov))
        assert cfg.app.on_close == "pull_up" and cfg.app.synthetic.motion == "recede"
        assert cfg.sim.gates.recede_speed == pytest.approx(j.cfg.sim.gates.recede_speed)
        assert cfg.app.synthetic.distance == pytest.approx(j.cfg.sim.scenario.distance_min)
        assert cfg.sim.target.on_ground is j.cfg.sim.target.on_ground is g["on_ground"]
        assert cfg.app.target_width == j.cfg.app.target_width == 2.5 and cfg.app.target_height == 3.0
        assert GateJudge.for_config(cfg).box == (2.5, 3.0)  # the judge measures the camera's rectangle
        assert abs(cfg.app.synthetic.height_offset) <= 1.0 and (not g["on_ground"] or
                                                                 cfg.app.synthetic.height_offset == 0.0)
    assert suite.report is report_intercept  # PX4's results tabled as the in-process ones
    with pytest.raises(ValueError, match="--camera geometric"):
        px4_intercept_runs(base, 5, 3, "rendered")
