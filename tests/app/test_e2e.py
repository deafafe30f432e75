"""End to end through the real mavsdk over UDP: arm, take off, acquire, fly through a moving gate
(linear fast), pass, hand back, land, disarm. The flight log proves each step; the simulated PX4's
own event list confirms it independently."""

from __future__ import annotations

import numpy as np
import pytest
from flighthelpers import make_config, pilot_takes_off, run_flight, wait_state

from companion.app.states import Reason
from companion.flightlog import gate_crossings, read_flight

pytestmark = pytest.mark.timeout(150)


def _mode_during(f, state: str) -> set[str]:
    st = f.states
    t0 = next(float(r["t"]) for r in st if r["to_state"] == state)
    t1 = next(float(r["t"]) for r in st if float(r["t"]) > t0)
    tel = f["telemetry"]
    # ENGAGE starts offboard: PX4 switches at once but reports it in its 1 Hz heartbeat (0.2 s stream first).
    sel = (tel["t"] > t0 + 1.3) & (tel["t"] < t1)
    return set(tel["flight_mode"][sel])


def test_fly_through_moving_gate_end_to_end(sim, tmp_path):
    cfg = make_config(tmp_path, sim.url_for_mavsdk)
    reason, folder, summary = run_flight(cfg)
    assert reason is Reason.OK, summary
    f = read_flight(folder)
    assert f.state_path() == ["CONNECT", "PREFLIGHT", "ARM", "TAKEOFF", "ACQUIRE", "ENGAGE", "PASS", "RECOVER",
                              "HANDBACK", "LAND", "SAFE_LANDED"]
    assert f.summary["outcome"] == "SAFE_LANDED" and f.summary["exit_code"] == 0
    assert f.config["app"]["synthetic"]["motion"] == "linear_fast"
    # The outcome from ground truth: the gate flown through, the camera's pass confirmed.
    assert f.summary["truth"]["through"] == 1 and f.summary["truth"]["gates"][0]["through"]
    assert [p["status"] for p in f.summary["passes"]] == ["confirmed"] and f.summary["gates_passed"] == 1
    assert f.summary["verdict"] == "ground truth: 1 gate(s) flown through"

    # Each step in the telemetry PX4 reported: armed, its own take-off, OFFBOARD while we flew, HOLD, LAND.
    tel = f["telemetry"]
    assert np.nanmax(tel["armed"]) == 1 and tel["armed"][-1] == 0
    assert _mode_during(f, "ENGAGE") == {"OFFBOARD"}
    # PX4 reports OFFBOARD up to a heartbeat (1 s) after the request: the frame loop keeps perceiving meanwhile
    # (awaited, that wait blinded perception at every engagement: the tracker lost the gate, real PX4 re-acquired
    # clutter). Frames flowed between ENGAGE and the first OFFBOARD report, ~30 a second.
    t_engage = next(float(r["t"]) for r in f.states if r["to_state"] == "ENGAGE")
    t_offboard = float(tel["t"][(tel["t"] > t_engage) & (tel["flight_mode"] == "OFFBOARD")][0])
    det_t = f["detections"]["t"]
    during = ((det_t > t_engage) & (det_t < t_offboard)).sum()
    assert during >= int(10 * (t_offboard - t_engage)), (during, t_offboard - t_engage)
    assert "OFFBOARD" not in _mode_during(f, "LAND")
    assert tel["landed_state"][-1] == "ON_GROUND"
    # IMU at rest on the ground before arming: specific force ~ -g along body down.
    assert np.nanmedian(tel["acc_d"][:5]) == pytest.approx(-9.81, abs=0.3)

    # The gate moved (linear fast, 5 m/s) and the vehicle crossed its plane inside the ring.
    gate = f["gate"]
    ok = np.isfinite(gate["gate_n"])
    moved = np.hypot(np.diff(gate["gate_n"][ok][[0, -1]]), np.diff(gate["gate_e"][ok][[0, -1]]))[0]
    dur = gate["t"][ok][-1] - gate["t"][ok][0]
    assert moved / dur == pytest.approx(5.0, rel=0.05)
    crossings = gate_crossings(f)
    assert len(crossings) == 1, crossings
    assert crossings[0].through, crossings[0]
    t_pass = next(float(r["t"]) for r in f.states if r["to_state"] == "PASS")
    t_recover = next(float(r["t"]) for r in f.states if r["to_state"] == "RECOVER")
    assert t_pass - 0.5 <= crossings[0].t <= t_recover + 0.2  # "passed" is declared around the real crossing

    # Setpoints: finite, thrust never 0, PN while engaged; level hover thrust in RECOVER.
    sp = f["setpoints"]
    for c in ("roll_deg", "pitch_deg", "yaw_deg", "thrust"):
        assert np.isfinite(sp[c]).all()
    assert sp["thrust"].min() >= cfg.airframe.thrust_min - 1e-9
    rec = sp["state"] == "RECOVER"
    assert rec.any() and np.allclose(sp["roll_deg"][rec], 0) and np.allclose(sp["pitch_deg"][rec], 0)
    assert (sp["ctrl_mode"][sp["state"] == "ENGAGE"] == "pn").mean() > 0.9
    assert len(f["detections"]) >= len(sp)

    # Independent witness: the simulated PX4's own event list, in order.
    ev = [e for _, e in sim.events]
    keys = ["arm", "takeoff", "mode:OFFBOARD:command", "mode:HOLD:command", "land", "touchdown", "disarm:auto_land"]
    idx = [next(i for i, e in enumerate(ev) if e.startswith(k)) for k in keys]
    assert idx == sorted(idx), ev
    assert not any(e.startswith("failsafe") for e in ev)


def test_next_gate_in_view_is_engaged(sim, tmp_path):
    """Two stationary gates in a row: pass, recover, engage the next, pass, then land."""
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.synthetic.count=2", "app.synthetic.motion=stationary")
    reason, folder, summary = run_flight(cfg)
    assert reason is Reason.OK, summary
    f = read_flight(folder)
    path = f.state_path()
    assert path[path.index("ENGAGE"):] == ["ENGAGE", "PASS", "RECOVER", "ENGAGE", "PASS", "RECOVER", "HANDBACK",
                                           "LAND", "SAFE_LANDED"]
    assert f.summary["gates_passed"] == 2
    crossings = gate_crossings(f)
    assert len(crossings) == 2 and all(c.through for c in crossings), crossings


def test_pilot_start_waits_for_the_pilots_hover(sim, tmp_path):
    """app.start=pilot: the app never arms; it waits, engages from the pilot's hover, and hands back to HOLD."""
    import asyncio

    async def pilot(app) -> None:
        await wait_state(app, "WAIT_PILOT")
        await asyncio.sleep(1.0)
        assert not sim.armed  # the app did not arm
        await asyncio.get_running_loop().run_in_executor(None, pilot_takes_off, sim, 5.0)

    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.start=pilot")
    reason, folder, summary = run_flight(cfg, pilot)
    assert reason is Reason.OK, summary
    f = read_flight(folder)
    assert f.state_path() == ["CONNECT", "PREFLIGHT", "WAIT_PILOT", "ACQUIRE", "ENGAGE", "PASS", "RECOVER",
                              "HANDBACK", "SAFE_HOLD"]
    assert f.states[-1]["reason"] == "PX4 holds; the pilot lands"
    assert sim.mode == "HOLD" and sim.armed
    ev = [e for _, e in sim.events]
    assert ev.count("arm") == 1 and any(e.startswith("mode:OFFBOARD") for e in ev)
    assert len(gate_crossings(f)) == 1


def _detector_missing() -> str | None:
    from companion.app.assemble import detector_available
    from companion.config import load_config

    return detector_available(load_config())


@pytest.mark.skipif(_detector_missing() is not None, reason="the shipped gate detector (ONNX) is not available")
def test_rendered_frames_through_the_detector_end_to_end(sim, tmp_path):
    """The image path: rendered frames -> detector pipeline -> controller, through mavsdk, to a pass."""
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.synthetic.render=image",
                      "app.synthetic.motion=linear_slow")
    reason, folder, summary = run_flight(cfg)
    f = read_flight(folder)
    assert reason is Reason.OK, summary
    assert "PASS" in f.state_path() and f.state_path()[-1] == "SAFE_LANDED"
    assert len(gate_crossings(f)) == 1
    assert summary["frame_to_setpoint_ms"]["n"] > 50


def test_intercept_pulls_up_before_impact(sim, tmp_path):
    """on_close=pull_up (intercept): at time-to-contact 1.5 s, brake nose-up and climb; never reach the target.

    At ~10 m/s, 35 deg nose-up brakes at g tan(35 deg) ~ 6.9 m/s^2: ~7 m plus ~3 m of attitude lag,
    inside the ~15 m left at the trigger.
    """
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.on_close=pull_up", "app.close_trigger=ttc",
                      "app.ttc_threshold=1.5", "app.pull_up_pitch=35", "app.synthetic.motion=stationary")
    reason, folder, summary = run_flight(cfg)
    assert reason is Reason.OK, summary
    f = read_flight(folder)
    path = f.state_path()
    assert path[path.index("ENGAGE"):] == ["ENGAGE", "RECOVER", "HANDBACK", "LAND", "SAFE_LANDED"]
    assert f.states[path.index("RECOVER")]["reason"].startswith("pull-up: time-to-contact")
    sp = f["setpoints"]
    rec = sp["state"] == "RECOVER"
    assert np.allclose(sp["pitch_deg"][rec], cfg.app.pull_up_pitch) and np.allclose(sp["roll_deg"][rec], 0.0)
    # Independent check from the logged truth: the vehicle never came within 1.5 m of the target's centre.
    tr, gate = f["truth"], f["gate"]
    c = np.array([gate["gate_n"][0], gate["gate_e"][0], gate["gate_d"][0]])
    p = np.column_stack([tr["n"], tr["e"], tr["d"]])
    assert np.linalg.norm(p - c, axis=1).min() > 2.0
    assert gate_crossings(f) == [] or not any(c.through for c in gate_crossings(f))
    # The outcome is the intercept's (issue 19): the judge's clearance of the target's box after the pull-up, which
    # the logged truth confirms independently (its rows are stamped up to 50 ms late: centimetres here). The
    # verdict is judged at the hand-back, summary.json's record at the flight's end (the landing too).
    (ic,) = summary["truth"]["intercepts"]
    assert summary["verdict"].startswith("intercept: pulled up") and not ic["impact"]
    judged = float(summary["verdict"].split("cleared by ")[1].split(" m")[0])
    n = np.array([gate["normal_n"][0], gate["normal_e"][0], gate["normal_d"][0]])
    u = np.array([-n[1], n[0], 0.0]) / np.hypot(n[0], n[1])  # horizontal, in the target's (vertical) plane
    half_w, half_h = (0.5 * x for x in cfg.sim.target.size(cfg.app.synthetic.radius))
    q = p - c
    d = np.sqrt(np.maximum(np.abs(q @ u) - half_w, 0.0) ** 2 + np.maximum(np.abs(q[:, 2]) - half_h, 0.0) ** 2
                + (q @ n) ** 2)
    after = tr["t"] >= f.states[path.index("RECOVER")]["t"]
    to_handback = after & (tr["t"] <= f.states[path.index("HANDBACK")]["t"])
    assert judged == pytest.approx(float(d[to_handback].min()), abs=0.3)
    assert ic["clearance_m"] == pytest.approx(float(d[after].min()), abs=0.3) and ic["clearance_m"] <= judged + 0.01
