"""The scorer on constructed crossings."""

from __future__ import annotations

import math

import numpy as np

from companion.sim.scoring import PlaneCrossingScorer, RunOutcome, aggregate

N = np.array([-1.0, 0.0, 0.0])  # the vehicle starts west of the gate (x < gate x)


def fly(scorer, p0, v, gate_fn, dt=1 / 30, t_end=10.0):
    t = 0.0
    while t <= t_end:
        out = scorer.update(t, np.asarray(p0) + np.asarray(v) * t, gate_fn(t))
        if out is not None:
            return out
        t += dt
    return None


def test_straight_crossing_offset_from_the_centre():
    gate = np.array([20.0, 0.0, 10.0])
    out = fly(PlaneCrossingScorer(N), [0.0, 0.3, 10.4], [8.0, 0.0, 0.0], lambda t: gate)
    assert out.crossed and out.reason is None
    assert math.isclose(out.t_gate, 20.0 / 8.0, rel_tol=1e-9)
    assert math.isclose(out.d_center, math.hypot(0.3, 0.4), rel_tol=1e-9)
    assert out.success(1.0) and out.success(0.51) and not out.success(0.5)
    assert out.failure(0.5) == "missed" and out.failure(1.0) is None


def test_oblique_crossing_and_moving_gate():
    # Vehicle along (10, 2, 0) m/s, gate moving north at 5 m/s from (30, -4, 10); plane x = 30.
    out = fly(PlaneCrossingScorer(N), [0.0, 0.0, 10.0], [10.0, 2.0, 0.0], lambda t: np.array([30.0, -4 + 5 * t, 10.0]))
    t_cross = 3.0
    assert math.isclose(out.t_gate, t_cross, rel_tol=1e-9)
    # At t = 3: vehicle y = 6, gate y = 11: 5 m apart.
    assert math.isclose(out.d_center, 5.0, rel_tol=1e-9)
    assert np.allclose(out.crossing_point, [30.0, 6.0, 10.0])


def test_gate_plane_moving_along_its_normal():
    # Gate approaches the vehicle at 2 m/s along x: relative closing 12 m/s over 24 m -> t = 2 s.
    out = fly(PlaneCrossingScorer(N), [0.0, 0, 0], [10.0, 0, 0], lambda t: np.array([24.0 - 2.0 * t, 0.1, 0]))
    assert math.isclose(out.t_gate, 2.0, rel_tol=1e-9)
    assert math.isclose(out.d_center, 0.1, rel_tol=1e-9)


def test_no_crossing_from_behind_or_when_flying_away():
    gate = np.array([20.0, 0.0, 10.0])
    assert fly(PlaneCrossingScorer(N), [30.0, 0, 10], [-8.0, 0, 0], lambda t: gate, t_end=5) is None
    assert fly(PlaneCrossingScorer(N), [0.0, 0, 10], [-8.0, 0, 0], lambda t: gate, t_end=5) is None


def test_aggregate_rates_and_means():
    outs = [RunOutcome(True, 2.0, 0.2, None, top_speed=12.0), RunOutcome(True, 4.0, 1.5, None, top_speed=14.0),
            RunOutcome(False, None, None, "fov_lost", top_speed=11.0),
            RunOutcome(False, None, None, "timeout", top_speed=3.0)]
    radii = [1.0, 2.0]
    agg = aggregate([o.as_dict(radii) for o in outs], radii)
    assert agg["success"] == {"1.0": 0.25, "2.0": 0.5}
    assert agg["t_gate_mean_s"] == 3.0 and math.isclose(agg["d_center_mean_m"], 0.85)
    assert agg["top_speed_mps"] == 14.0
    assert agg["failures"]["1.0"] == {"missed": 1, "fov_lost": 1, "timeout": 1}
    assert agg["failures"]["2.0"] == {"fov_lost": 1, "timeout": 1}


def test_aggregate_setpoint_metrics_max_tilt_and_mean_oscillation():
    radii = [1.0]
    runs = [RunOutcome(True, 2.0, 0.2, None).as_dict(radii) for _ in range(3)]
    runs[0].update(max_tilt_deg=30.0, roll_osc_rms_rate_dps=10.0, roll_osc_amp_deg=2.0, roll_osc_freq_hz=1.0)
    runs[1].update(max_tilt_deg=55.0, roll_osc_rms_rate_dps=20.0, roll_osc_amp_deg=4.0, roll_osc_freq_hz=2.0)
    runs[2].update(max_tilt_deg=None, roll_osc_rms_rate_dps=None, roll_osc_amp_deg=None, roll_osc_freq_hz=None)
    agg = aggregate(runs, radii)
    assert agg["max_tilt_deg"] == 55.0  # the largest over runs, not a mean
    assert agg["roll_osc_rms_rate_dps_mean"] == 15.0 and agg["roll_osc_amp_deg_mean"] == 3.0
    assert agg["roll_osc_freq_hz_mean"] == 1.5  # runs without a figure are left out, not counted as zero
