"""``eval ... --autopilot px4 --seed S``: each table seed flies its own scenarios (companion/evaluation/suites.py
``app_run_seed``). Before 2026-12-02 the PX4 runs took only the run's own seed, so tables flown with --seed 1, 2, 3
repeated seed 0's 30 scenarios (the same camouflaged run 0 failed in each)."""

from __future__ import annotations

from companion.config import load_config
from companion.evaluation.px4 import px4_jobs
from companion.evaluation.px4intercept import px4_intercept_runs


def _sim_seeds(overrides) -> list[int]:
    return [int(o.split("=", 1)[1]) for o in overrides if o.startswith("sim.seed=")]


def test_each_table_seed_flies_its_own_scenarios_and_seed_0_keeps_the_old_ones():
    cfg = load_config([], [])
    tables = {}
    for seed in (0, 1, 2):
        jobs, _ = px4_jobs("table1", cfg, 12, seed, ["stationary", "linear_slow", "planar"], "rendered")
        seeds = [s for j in jobs for s in _sim_seeds(j.overrides)]
        assert len(seeds) == len(jobs) == 12 and len(set(seeds)) == 12  # one per run, all different
        assert [j.group["sim_seed"] for j in jobs] == seeds  # the results say which scenario each run flew
        assert all(0 <= s < 2**31 for s in seeds)
        again, _ = px4_jobs("table1", cfg, 12, seed, ["stationary", "linear_slow", "planar"], "rendered")
        assert [s for j in again for s in _sim_seeds(j.overrides)] == seeds  # reproducible
        tables[seed] = seeds
        if seed == 0:  # the scenarios of every PX4 table flown so far
            assert seeds == [j.group["seed"] for j in jobs]
    assert not set(tables[0]) & set(tables[1]) and not set(tables[1]) & set(tables[2])


def test_px4_intercept_runs_also_mix_the_table_seed():
    cfg = load_config([], [])
    a = [_sim_seeds(ov)[0] for _, ov in px4_intercept_runs(cfg, 6, 0, "geometric")[0]]
    b = [_sim_seeds(ov)[0] for _, ov in px4_intercept_runs(cfg, 6, 3, "geometric")[0]]
    assert len(set(a)) == len(set(b)) == 6 and not set(a) & set(b)
