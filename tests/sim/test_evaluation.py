"""``companion eval``: suites end to end in quick mode (few runs), JSON and Markdown outputs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from companion.cli import main
from companion.config import Config
from companion.evaluation.pool import run_suite
from companion.evaluation.suites import build_suite


def test_table1_quick_end_to_end(tmp_path, capsys):
    out = tmp_path / "t1"
    js = tmp_path / "r.json"
    rc = main(["eval", "table1", "--runs", "5", "--jobs", "2", "--out", str(out), "--json", str(js),
               "--no-progress", "--seed", "3"])
    assert rc == 0
    res = json.loads(js.read_text())
    runs = res["runs"]
    assert len(runs) == 5 and sorted(r["motion"] for r in runs) == sorted(
        ["stationary", "linear_slow", "linear_fast", "planar", "knot"])
    # Aggregates recomputed from the per-run entries.
    for key in ("1.0", "2.0"):
        assert res["total"]["success"][key] == pytest.approx(np.mean([r["success"][key] for r in runs]))
    crossed = [r["t_gate_s"] for r in runs if r["crossed"]]
    assert res["total"]["t_gate_mean_s"] == pytest.approx(np.mean(crossed))
    for r in runs:
        assert r["crossed"] or r["failure"]["1.0"] in ("fov_lost", "timeout", "ground")
        if r["crossed"]:
            assert r["success"]["1.0"] == (r["d_center_m"] < 1.0)
            assert r["failure"]["1.0"] == (None if r["d_center_m"] < 1.0 else "missed")
    # Setpoint metrics: per run, the largest tilt over runs and mean oscillation per group and in total.
    assert res["total"]["max_tilt_deg"] == pytest.approx(max(r["max_tilt_deg"] for r in runs))
    assert res["total"]["roll_osc_rms_rate_dps_mean"] == pytest.approx(
        np.mean([r["roll_osc_rms_rate_dps"] for r in runs]))
    for g in res["groups"].values():
        assert g["max_tilt_deg"] <= res["total"]["max_tilt_deg"]
    md = (out / "table.md").read_text()
    assert "| stationary |" in md and "(0.93)" in md and "(4.32)" in md
    assert "max tilt deg" in md and "roll osc. amplitude deg" in md
    assert (out / "trajectories.png").stat().st_size > 10_000
    assert "table1" in capsys.readouterr().out


def test_parallel_and_serial_give_identical_results():
    cfg = Config()
    a = run_suite("latency", cfg, runs=12, seed=1, n_jobs=1, progress=False)
    b = run_suite("latency", cfg, runs=12, seed=1, n_jobs=2, progress=False)
    assert a["runs"] == b["runs"] and a["total"] == b["total"]
    assert sorted({r["delay_s"] for r in a["runs"]}) == [0.0, 0.1, 0.2, 0.3]
    assert set(a["groups"]) >= {"0.0", "0.1", "0.2", "0.3"}


def test_latency_plot_and_overrides(tmp_path):
    out = tmp_path / "lat"
    rc = main(["eval", "latency", "--runs", "12", "--jobs", "2", "--out", str(out), "--no-progress",
               "--set", "sim.wind.gust_std=1.0"])
    assert rc == 0
    res = json.loads((out / "results.json").read_text())
    assert res["config"]["sim"]["wind"]["gust_std"] == 1.0
    assert (out / "latency.png").stat().st_size > 10_000


def test_vrel_and_baseline_suites_build_the_papers_cells():
    cfg = Config()
    v = build_suite("vrel", cfg, runs=8)
    cells = {(j.group["start_m"], j.group["v_rel_bar"], j.spec.controller) for j in v.jobs}
    assert cells == {(d, e, "pn_true_vrel" if e == "true" else "pn") for d in (30.0, 150.0)
                     for e in ("30", "20", "10", "true")}
    for j in v.jobs:
        assert j.cfg.sim.gates.d_knot == 5.0 and j.spec.motion == "knot"
        assert j.cfg.sim.scenario.distance_min == j.cfg.sim.scenario.distance_max == j.group["start_m"]
        if j.group["v_rel_bar"] != "true":
            assert j.cfg.guidance.v_rel_bar == float(j.group["v_rel_bar"])
    b = build_suite("baseline", cfg, runs=8, seed=2)
    assert {j.spec.controller for j in b.jobs} == {"baseline", "pn"}
    for j in b.jobs:
        assert 1.25 <= j.group["gate_speed_mps"] <= 5.0
        if j.spec.controller == "pn":
            assert j.cfg.guidance.gamma_bar == 3.5
    # Paired: both controllers see the same gate speed and seed.
    pairs = {}
    for j in b.jobs:
        pairs.setdefault((j.spec.motion, j.spec.seed), set()).add(j.group["gate_speed_mps"])
    assert all(len(s) == 1 for s in pairs.values())


def test_baseline_quick_run():
    res = run_suite("baseline", Config(), runs=4, seed=0, n_jobs=2, progress=False)
    assert len(res["runs"]) == 4 and "| linear |" in res["markdown"] and "(0.35)" in res["markdown"]


def test_bad_arguments_are_one_line_errors(capsys):
    assert main(["eval", "table1", "--runs", "0"]) == 2
    assert "--runs must be >= 1" in capsys.readouterr().err
    assert main(["eval", "table1", "--runs", "1", "--set", "sim.camera.delay=5 parsecs"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "sim.camera.delay" in err[0]


def test_tune_quick_registers_every_evaluation():
    from companion.evaluation.tune import run_reward, tune

    res = tune(Config(), iterations=1, init_points=2, reward="d", runs_per_motion=1, seed=0, n_jobs=2,
               progress=False)
    assert len(res["history"]) == 3
    for h in res["history"]:
        assert 0.3 <= h["k_pn"] <= 3.0 and 5.0 <= h["gamma_bar"] <= 30.0
    assert res["best"]["reward"] == max(h["reward"] for h in res["history"])
    assert "(1.11)" in res["markdown"]
    # eq:meth_bo_reward by hand: R_d = max(0, 3 - 5 d), R_dt = max(0, 10 / t - 3 d).
    run = {"crossed": True, "t_gate_s": 2.5, "d_center_m": 0.2}
    assert run_reward(run, "d") == pytest.approx(2.0) and run_reward(run, "dt") == pytest.approx(3.4)
    assert run_reward({**run, "d_center_m": 1.0}, "d") == 0.0
    assert run_reward({"crossed": False}, "dt") == 0.0
