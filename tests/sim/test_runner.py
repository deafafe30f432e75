"""Closed-loop runs of the in-process simulator: determinism, outcomes, latency, what the controller sees."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import Config
from companion.controller import PNController
from companion.sim.runner import RunSpec, bench_sim, run_once, with_overrides
from perception.types import BoundingBox

CFG = Config()
RADII = [0.5, 1.0, 2.0]


def test_same_seed_same_run_and_different_seed_different_run():
    a = run_once(CFG, RunSpec("planar", 7), record=True)
    b = run_once(CFG, RunSpec("planar", 7), record=True)
    c = run_once(CFG, RunSpec("planar", 8))
    assert a.as_dict(RADII) == b.as_dict(RADII)
    assert np.array_equal(a.trajectory.arrays()["p"], b.trajectory.arrays()["p"])
    assert a.as_dict(RADII) != c.as_dict(RADII)
    # The suite seed (sim.seed) changes the run too.
    d = run_once(with_overrides(CFG, {"sim": {"seed": 1}}), RunSpec("planar", 7))
    assert d.distance != a.distance


def test_initial_condition_follows_the_paper():
    for seed in range(10):
        r = run_once(CFG, RunSpec("stationary", seed), record=True)
        tr = r.trajectory
        assert 20.0 <= r.distance <= 30.0 and abs(r.angle) <= 10.0
        assert math.isclose(np.linalg.norm(tr.v[0]), 10.0, rel_tol=1e-9)
        los = tr.gate[0] - tr.p[0]
        ang = math.degrees(math.acos(los @ tr.v[0] / np.linalg.norm(los) / 10.0))
        assert ang <= 10.0 + math.degrees(math.atan2(1.0, 20.0)) + 1e-6  # + gate height offset
        assert tr.box[0] is not None  # the first frame sees the gate


def test_stationary_gate_noise_free_is_flown_through_the_centre():
    cfg = with_overrides(CFG, {"sim": {"camera": {"pixel_noise": 0.0},
                                       "sensors": {"attitude_noise": 0.0, "attitude_bias": 0.0}}})
    for seed in range(3):
        o = run_once(cfg, RunSpec("stationary", seed)).outcome
        assert o.crossed and o.d_center < 0.2
        assert 1.0 < o.t_gate < 5.0


def test_failure_reasons():
    t = run_once(with_overrides(CFG, {"sim": {"scenario": {"timeout": 0.5}}}), RunSpec("stationary", 0))
    assert t.outcome.reason == "timeout" and not t.outcome.crossed and t.as_dict(RADII)["failure"]["2.0"] == "timeout"
    f = run_once(with_overrides(CFG, {"sim": {"camera": {"drop_prob": 1.0}}}),
                 RunSpec("stationary", 0, protocol="controller"))
    assert f.outcome.reason == "fov_lost" and 1.0 < f.sim_time < 1.2
    # Model error: the true vehicle needs 0.9 to hover, the controller believes 0.5: it sinks from 1 m.
    low = {"sim": {"scenario": {"altitude_min": 1.0, "altitude_max": 1.0, "gate_height_offset": 0.0},
                   "quad": {"hover_thrust": 0.9}}}
    g = run_once(with_overrides(CFG, low), RunSpec("stationary", 0, protocol="controller"))
    assert g.outcome.reason == "ground"


def test_engagement_ends_are_the_runs_failure_reasons():
    # No box ever: the engagement never leaves ACQUIRE and lands at acquire_timeout (no target).
    f = run_once(with_overrides(CFG, {"sim": {"camera": {"drop_prob": 1.0}}, "app": {"acquire_timeout": 0.5}}),
                 RunSpec("stationary", 0))
    assert f.outcome.reason == "no_target" and not f.outcome.crossed and 0.5 < f.sim_time < 0.6
    assert f.engagement["end"] == "LAND NO_TARGET" and f.max_tilt_deg != f.max_tilt_deg  # no setpoint: NaN
    # Below the altitude floor once engaged: an abort, not a flight into the ground.
    low = {"sim": {"scenario": {"altitude_min": 1.0, "altitude_max": 1.0, "gate_height_offset": 0.0}}}
    g = run_once(with_overrides(CFG, low), RunSpec("stationary", 0))
    assert g.outcome.reason == "altitude_floor" and g.engagement["end"] == "ABORT ALTITUDE_FLOOR"
    # Boxes stop once engaged: target lost after safety.target_lost_timeout.
    # A gate too fast to catch leaves the view once engaged: target lost (safety.target_lost_timeout).
    h = run_once(with_overrides(CFG, {"sim": {"gates": {"linear_fast_speed": 40.0}}}), RunSpec("linear_fast", 0))
    assert h.outcome.reason == "target_lost" and not h.outcome.crossed and h.engagement["end"] == "ABORT TARGET_LOST"


@pytest.mark.parametrize("drag_compensation", [0.0, 1.0])
def test_engagement_protocol_passes_straight_and_confirms_it(drag_compensation: float):
    cfg = with_overrides(CFG, {"guidance": {"drag_compensation": drag_compensation}})
    r = run_once(cfg, RunSpec("stationary", 1), record=True)
    assert r.outcome.crossed and r.outcome.success(1.0)
    tr = r.trajectory
    modes = [m for m in dict.fromkeys(tr.mode)]
    assert modes == ["init", "ACQUIRE", "ENGAGE", "PASS", "RECOVER"][1 - ("init" in modes) * 1:]
    assert r.engagement["pass_status"] == "confirmed" and r.engagement["t_close_s"] < r.outcome.t_gate
    # In PASS the command is constant (no held bank that PN was flying): the straight pass.
    i = [k for k, m in enumerate(tr.mode) if m == "PASS"]
    assert len({(tr.roll_sp[k], tr.pitch_sp[k], tr.thrust[k]) for k in i}) == 1
    if drag_compensation == 0.0:  # no drag estimate: level pass, wings level about the LOS
        assert abs(tr.roll_sp[i[0]]) < 1e-6 or abs(abs(tr.roll_sp[i[0]]) - 180.0) < 1e-6
    else:
        # With the accelerometer's drag the pass cancels it and keeps the velocity: towards a stationary gate the
        # drag is along the flight, so the bank is a fraction of a degree (not PN's), and the speed holds.
        assert abs(tr.roll_sp[i[0]]) < 1.0
        v0, v1 = np.linalg.norm(tr.v[i[0]]), np.linalg.norm(tr.v[i[-1]])
        assert abs(v1 - v0) < 0.05 * v0


def test_latency_delays_the_first_setpoint_by_the_delay():
    r0 = run_once(CFG, RunSpec("stationary", 1, protocol="controller"), record=True)
    assert r0.trajectory.mode[0] == "pn"
    cfg = with_overrides(CFG, {"sim": {"camera": {"delay": 0.1}}})
    r = run_once(cfg, RunSpec("stationary", 1, protocol="controller"), record=True)
    assert r.trajectory.mode[:3] == ["init"] * 3 and r.trajectory.mode[3] == "pn"
    # The engagement: acquire_frames boxes after the first arrives, it engages.
    e = run_once(cfg, RunSpec("stationary", 1), record=True)
    n = CFG.app.acquire_frames
    assert e.trajectory.mode[:3] == ["init"] * 3 and e.trajectory.mode[3:3 + n - 1] == ["ACQUIRE"] * (n - 1)
    assert e.trajectory.mode[3 + n - 1] == "ENGAGE"


def test_controller_gets_only_time_box_and_attitude(monkeypatch):
    seen = []
    orig = PNController.step

    def spy(self, *args, **kwargs):
        seen.append((args, kwargs))
        return orig(self, *args, **kwargs)

    monkeypatch.setattr(PNController, "step", spy)
    cfg = with_overrides(CFG, {"sim": {"camera": {"delay": 0.1}}})
    r = run_once(cfg, RunSpec("linear_fast", 2, protocol="controller"))
    assert len(seen) == r.frames - 3  # three frames still in flight at the end
    run_once(cfg, RunSpec("linear_fast", 2))  # the engagement steps the controller the same way
    for args, kwargs in seen:
        # Time, box, attitude, the accelerometer (specific force, body FRD) and the current time: no position,
        # no velocity.
        assert not kwargs and len(args) == 5
        t, box, q, acc, now = args
        assert isinstance(t, float) and (box is None or isinstance(box, BoundingBox))
        assert isinstance(q, np.ndarray) and q.shape == (4,) and math.isclose(np.linalg.norm(q), 1.0)
        assert isinstance(acc, np.ndarray) and acc.shape == (3,)
        assert np.all(np.isfinite(acc)) and np.linalg.norm(acc) < 40.0
        assert now == pytest.approx(t + 0.1)  # the frame's age is its delay
        if box is not None:
            assert box.t == t  # the capture time of the frame, 100 ms before it arrived
    ts = [a[0] for a, _ in seen[:len(seen) // 2]]
    assert np.allclose(np.diff(ts), 1 / 30)


def test_baseline_and_true_vrel_controllers_run():
    for ctrl in ("baseline", "pn_true_vrel"):
        o = run_once(CFG, RunSpec("linear_slow", 0, controller=ctrl, protocol="controller")).outcome
        assert o.crossed or o.reason in ("fov_lost", "timeout", "ground")
        e = run_once(CFG, RunSpec("linear_slow", 0, controller=ctrl))
        assert e.outcome.crossed or e.outcome.reason in ("target_lost", "timeout", "ground", "handback")
        assert e.engagement["end"] != "ACQUIRE"  # it engaged


def test_bad_spec_is_one_clear_error():
    with pytest.raises(ValueError, match="unknown gate motion 'spiral'"):
        run_once(CFG, RunSpec("spiral", 0))
    with pytest.raises(ValueError, match="unknown controller 'lqr'"):
        run_once(CFG, RunSpec("planar", 0, controller="lqr"))


def test_bench_sim_reports_speed():
    out = bench_sim(2.0, CFG)
    assert out["sim_speed_x_realtime"] > 0 and out["sim_seconds"] >= 2.0 and out["integration_hz"] >= 200


def test_delayed_box_comes_with_the_attitude_of_its_capture_time():
    base = {"sim": {"camera": {"delay": 0.2}}}
    at_capture = run_once(with_overrides(CFG, base), RunSpec("planar", 4))
    at_arrival = run_once(with_overrides(CFG, {"sim": {"camera": {"delay": 0.2, "attitude_at_capture": False}}}),
                          RunSpec("planar", 4))
    assert at_capture.as_dict(RADII) != at_arrival.as_dict(RADII)
    # Without delay capture and arrival coincide: the option changes nothing.
    a = run_once(CFG, RunSpec("planar", 4))
    b = run_once(with_overrides(CFG, {"sim": {"camera": {"attitude_at_capture": False}}}), RunSpec("planar", 4))
    assert a.as_dict(RADII) == b.as_dict(RADII)


def test_recorded_imu_and_baro_follow_the_truth():
    cfg = with_overrides(CFG, {"sim": {"sensors": {"accel_noise": 0.0, "accel_bias": 0.0, "baro_noise": 0.0}}})
    r = run_once(cfg, RunSpec("stationary", 0), record=True)
    tr = r.trajectory
    acc = np.array(tr.accel)
    # In flight the accelerometer reads thrust minus drag: along body z, g on average (altitude is held),
    # and drag backwards (-x) at ~10 m/s: (0.05 * 10 + 0.011 * 100) / 2 = 0.8 m/s^2.
    assert np.all(acc[:, 2] > 3.0) and 9.0 < acc[:, 2].mean() < 11.5
    assert np.all(acc[:, 0] < -0.5)
    offset = np.array(tr.baro) - np.array(tr.p)[:, 2]
    assert np.allclose(offset, offset[0]) and abs(offset[0]) < 3.0  # a constant per-run baro bias


MODEL = __import__("pathlib").Path(__file__).resolve().parents[2] / "perception" / "models" / "gate_detector.onnx"


@pytest.mark.slow
@pytest.mark.skipif(not MODEL.exists(), reason="the shipped detector model is not built yet")
def test_rendered_camera_closes_the_loop_through_the_real_detector():
    cfg = with_overrides(CFG, {"sim": {"scenario": {"timeout": 1.0}}})
    r = run_once(cfg, RunSpec("stationary", 0, camera="rendered"))
    assert r.frames_with_box > 0.5 * r.frames


def test_unknown_camera_is_one_clear_error():
    with pytest.raises(ValueError, match="unknown camera 'lidar'"):
        run_once(CFG, RunSpec("planar", 0, camera="lidar"))


def test_true_vrel_ablation_feeds_the_true_closing_speed(monkeypatch):
    import companion.guidance as guidance

    seen: list[float] = []
    orig = guidance.pn_demand_xyz  # the controller's per-frame form of pn_demand

    def spy(lambda_dot, n, k_pn, v_rel_bar):
        seen.append(v_rel_bar)
        return orig(lambda_dot, n, k_pn, v_rel_bar)

    monkeypatch.setattr(guidance, "pn_demand_xyz", spy)
    fixed = with_overrides(CFG, {"guidance": {"closing_speed": "fixed"}})
    run_once(fixed, RunSpec("stationary", 3))
    assert set(seen) == {CFG.guidance.v_rel_bar}  # the paper: a constant
    seen.clear()
    run_once(CFG, RunSpec("stationary", 3, protocol="controller"))  # PN until the gate plane: the lag cap acts
    assert max(seen) <= CFG.guidance.v_rel_bar and min(seen) < CFG.guidance.v_rel_bar  # estimate: lowered near the gate
    seen.clear()
    r = run_once(CFG, RunSpec("stationary", 3, controller="pn_true_vrel"), record=True)
    # Closing speed to a stationary gate = speed along the LOS: starts at 10 cos(angle) m/s and grows.
    assert seen[0] == pytest.approx(10.0 * math.cos(math.radians(r.angle)), abs=0.3)
    assert max(seen) > seen[0] + 1.0


def test_per_run_setpoint_metrics_match_the_recorded_setpoints():
    from companion.metrics import oscillation, tilt_deg

    r = run_once(CFG, RunSpec("planar", 3), record=True)
    tr = r.trajectory
    roll, pitch = np.array(tr.roll_sp), np.array(tr.pitch_sp)
    cmd = np.isfinite(roll)  # no setpoint while acquiring (PX4 holds); then one per frame (no delay)
    n = CFG.app.acquire_frames
    assert not cmd[:n - 1].any() and cmd[n - 1:].all()
    roll, pitch, t = roll[cmd], pitch[cmd], np.array(tr.t)[cmd]
    # Independent: the tilt of the held command, frame by frame (the same commands, each at least once).
    expect = np.degrees(np.arccos(np.cos(np.radians(roll)) * np.cos(np.radians(pitch)))).max()
    assert r.max_tilt_deg == pytest.approx(expect, abs=1e-9)
    assert r.max_tilt_deg == pytest.approx(float(tilt_deg(roll, pitch).max()), abs=1e-9)
    assert r.roll_osc == oscillation(t, roll)
    d = r.as_dict(RADII)
    assert d["max_tilt_deg"] == r.max_tilt_deg and d["roll_osc_amp_deg"] == r.roll_osc.amplitude_deg
    assert 0.0 <= d["max_tilt_deg"] < 90.0 and d["roll_osc_rms_rate_dps"] >= 0.0


@pytest.mark.parametrize("motion,seed", [("stationary", 3), ("planar", 3001), ("knot", 7)])
def test_recording_a_run_does_not_change_it(motion, seed):
    """Plots come from recorded runs and the suites from unrecorded ones: they must be the same flight (the
    logged barometer once drew from the sensors' noise stream and shifted every later attitude draw)."""
    cfg = Config()
    spec = RunSpec(motion, seed=seed)
    plain, rec = run_once(cfg, spec), run_once(cfg, spec, record=True)
    assert rec.trajectory is not None and len(rec.trajectory.baro) == rec.frames
    assert plain.outcome.as_dict([1.0]) == rec.outcome.as_dict([1.0])
    assert (plain.frames, plain.frames_with_box, plain.engagement) == (rec.frames, rec.frames_with_box,
                                                                        rec.engagement)
    assert plain.roll_osc == rec.roll_osc
