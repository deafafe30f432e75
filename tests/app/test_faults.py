"""Fault flights through the real mavsdk over UDP: each ends in its named safe state, with its reason
in the log and as the exit code, and the log intact up to the fault."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from flighthelpers import make_config, run_flight, wait_state

from companion.app.states import Reason
from companion.flightlog import read_flight

pytestmark = pytest.mark.timeout(120)


def _end(folder):
    f = read_flight(folder)
    last = f.states[-1]
    return f, last["to_state"], last["reason"]


def _check_log_intact(f, until_state: str) -> None:
    """Every topic readable; telemetry and setpoints cover the flight up to the fault."""
    t_fault = next(float(r["t"]) for r in f.states if r["to_state"] == until_state)
    tel = f["telemetry"]
    assert len(tel) > 10 and tel["t"].max() >= t_fault - 0.2
    assert all(t.truncated_rows == 0 for t in f.tables.values())
    assert f.summary["exit_code"] == Reason[f.summary["reason"]].value


def test_arm_denied(sim, tmp_path):
    sim.deny_arming = True
    reason, folder, _ = run_flight(make_config(tmp_path, sim.url_for_mavsdk))
    f, end, why = _end(folder)
    assert reason is Reason.ARM_DENIED and end == "ABORT_NOT_ARMED"
    assert f.state_path() == ["CONNECT", "PREFLIGHT", "ARM", "ABORT_NOT_ARMED"]
    assert "arm" in why.lower() and f.summary["exit_code"] == 17
    assert not sim.armed and any(e.startswith("arm_denied") for _, e in sim.events)


def test_command_timeout_on_arm(sim, tmp_path):
    sim.silence_commands(True)
    reason, folder, _ = run_flight(make_config(tmp_path, sim.url_for_mavsdk, "link.command_timeout=1.5"))
    f, end, why = _end(folder)
    assert reason is Reason.COMMAND_TIMEOUT and end == "ABORT_NOT_ARMED", why
    assert f.state_path()[-2:] == ["ARM", "ABORT_NOT_ARMED"]
    assert "no answer" in why and not sim.armed


def test_offboard_denied(sim, tmp_path):
    sim.deny_offboard = True
    reason, folder, _ = run_flight(make_config(tmp_path, sim.url_for_mavsdk))
    f, end, why = _end(folder)
    assert reason is Reason.OFFBOARD_DENIED and end == "SAFE_HOLD", why
    assert f.state_path()[-3:] == ["ENGAGE", "HANDBACK", "SAFE_HOLD"]
    assert sim.mode == "HOLD" and sim.armed and not sim.landed
    assert any(e.startswith("offboard_denied") for _, e in sim.events)
    _check_log_intact(f, "HANDBACK")


def _after_engage(action, delay: float = 1.0):
    async def side(app) -> None:
        await wait_state(app, "ENGAGE")
        await asyncio.sleep(delay)
        action()

    return side


def test_link_loss_mid_flight(sim, tmp_path):
    reason, folder, _ = run_flight(make_config(tmp_path, sim.url_for_mavsdk),
                                   _after_engage(lambda: sim.drop_link(True)))
    f, end, why = _end(folder)
    assert reason is Reason.LINK_LOST and end == "SAFE_FAILSAFE_LINK", why
    assert f.state_path()[-2:] == ["ENGAGE", "SAFE_FAILSAFE_LINK"]
    # PX4's own offboard-loss failsafe took over (we stopped streaming; nothing reached it anyway).
    assert sim.wait_event("failsafe:offboard_loss", timeout=5.0) is not None
    _check_log_intact(f, "SAFE_FAILSAFE_LINK")


def test_pilot_takeover_mid_engagement(sim, tmp_path):
    reason, folder, _ = run_flight(make_config(tmp_path, sim.url_for_mavsdk),
                                   _after_engage(lambda: sim.pilot_takeover("POSCTL")))
    f, end, why = _end(folder)
    assert reason is Reason.PILOT_TAKEOVER and end == "SAFE_PILOT", why
    assert "POSCTL" in why
    # We stopped commanding: the pilot's mode stands, no mode command of ours after the takeover.
    ev = [e for _, e in sim.events]
    i = next(i for i, e in enumerate(ev) if e.startswith("mode:POSCTL"))
    assert not [e for e in ev[i + 1:] if e.startswith("mode:")], ev[i:]
    assert sim.mode == "POSCTL"
    n0 = sim.setpoint_count
    import time

    time.sleep(0.5)
    assert sim.setpoint_count == n0  # mavsdk is gone: no resends either
    _check_log_intact(f, "SAFE_PILOT")


@pytest.mark.parametrize(
    ("fault", "reason", "text"),
    [
        ("stall", Reason.PERCEPTION_STALL, "no fresh setpoint"),
        ("lose_target", Reason.TARGET_LOST, "no usable box"),
        ("nan_box", Reason.TARGET_LOST, "no usable box"),
    ],
)
def test_perception_faults_hand_over_to_hold(sim, tmp_path, fault, reason, text):
    cfg = make_config(tmp_path, sim.url_for_mavsdk, f"app.synthetic.fault={fault}", "app.synthetic.fault_after=1.5")
    got, folder, _ = run_flight(cfg)
    f, end, why = _end(folder)
    assert got is reason and end == "SAFE_HOLD", why
    assert f.state_path()[-3:] == ["ENGAGE", "HANDBACK", "SAFE_HOLD"]
    hb = next(r["reason"] for r in f.states if r["to_state"] == "HANDBACK")
    assert text in hb
    assert sim.mode == "HOLD" and sim.armed
    sp = f["setpoints"]
    for c in ("roll_deg", "pitch_deg", "yaw_deg", "thrust"):
        assert np.isfinite(sp[c]).all()  # a NaN box never becomes a NaN setpoint
    if fault == "nan_box":
        rej = [r for r in f["los"]["rejected"] if isinstance(r, str) and r.startswith("invalid box")]
        assert len(rej) >= 10
        assert any("nan" in r for r in rej) and any("-40" in r for r in rej) and any("5000" in r for r in rej)
        assert (f["detections"]["valid"] == 0).sum() >= len(rej)
    if fault == "stall":
        # The camera stopped: the last detection is >= stall timeout before the hand-over.
        t_hb = next(float(r["t"]) for r in f.states if r["to_state"] == "HANDBACK")
        assert t_hb - f["detections"]["t"].max() >= cfg.safety.perception_stall_timeout - 0.05
    _check_log_intact(f, "HANDBACK")


def test_los_jump_is_rejected_and_the_flight_goes_on(sim, tmp_path):
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.synthetic.fault=los_jump", "app.synthetic.fault_after=1.5")
    reason, folder, _ = run_flight(cfg)
    f, end, why = _end(folder)
    assert reason is Reason.OK and end == "SAFE_LANDED", why
    assert "PASS" in f.state_path()
    t_pass = next(float(r["t"]) for r in f.states if r["to_state"] == "PASS")
    los = f["los"]
    jumps = [t for t, r in zip(los["t"], los["rejected"], strict=True)
             if isinstance(r, str) and r.startswith("LOS jump") and t < t_pass]
    # Exactly the two injected frames, back to back (near the gate a clipped box may jump too: not counted).
    assert len(jumps) == 2 and jumps[1] - jumps[0] < 0.1


def test_altitude_floor(sim, tmp_path):
    # Floor above the take-off altitude: the first engaged frame is already below it.
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "safety.altitude_floor=7")
    reason, folder, _ = run_flight(cfg)
    f, end, why = _end(folder)
    assert reason is Reason.ALTITUDE_FLOOR and end == "SAFE_HOLD", why
    assert "below the floor 7.0 m" in why
    assert sim.mode == "HOLD"
    # Independent check: the truth the sim logged says the vehicle really was below 7 m at the abort.
    t_hb = next(float(r["t"]) for r in f.states if r["to_state"] == "HANDBACK")
    tr = f["truth"]
    assert -tr["d"][np.searchsorted(tr["t"], t_hb) - 1] < 7.0


def test_exception_in_perception(sim, tmp_path):
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.synthetic.fault=exception", "app.synthetic.fault_after=1.5")
    reason, folder, _ = run_flight(cfg)
    f, end, why = _end(folder)
    assert reason is Reason.EXCEPTION and end == "SAFE_HOLD", why
    assert "RuntimeError: injected perception failure" in why
    assert f.state_path()[-3:] == ["ENGAGE", "HANDBACK", "SAFE_HOLD"]
    assert sim.mode == "HOLD"
    _check_log_intact(f, "HANDBACK")


def test_max_engagement_time(sim, tmp_path):
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "safety.max_engagement_time=1.0")
    reason, folder, _ = run_flight(cfg)
    f, end, why = _end(folder)
    assert reason is Reason.MAX_ENGAGEMENT and end == "SAFE_HOLD", why
    t_eng = next(float(r["t"]) for r in f.states if r["to_state"] == "ENGAGE")
    t_hb = next(float(r["t"]) for r in f.states if r["to_state"] == "HANDBACK")
    assert 1.0 <= t_hb - t_eng <= 1.5
    assert sim.mode == "HOLD"


def test_no_autopilot_is_connect_failed(tmp_path):
    import socket

    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))  # a port with nobody speaking MAVLink on it
    try:
        cfg = make_config(tmp_path, f"udpout://127.0.0.1:{s.getsockname()[1]}", "link.connect_timeout=2")
        reason, folder, _ = run_flight(cfg)
    finally:
        s.close()
    f, end, why = _end(folder)
    assert reason is Reason.CONNECT_FAILED and end == "ABORT_NOT_ARMED", why
    assert f.state_path() == ["CONNECT", "ABORT_NOT_ARMED"] and "no autopilot" in why


def test_no_target_in_view_lands(sim, tmp_path):
    # The virtual gate is 60 m to the side: never in view. Nothing to engage -> land where we are.
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.synthetic.lateral_offset=60", "app.acquire_timeout=1.5")
    reason, folder, _ = run_flight(cfg)
    f, end, why = _end(folder)
    assert reason is Reason.NO_TARGET and end == "SAFE_LANDED", why
    assert f.state_path()[-4:] == ["TAKEOFF", "ACQUIRE", "LAND", "SAFE_LANDED"]
    assert "no stable track within 1.5 s" in f.states[-2]["reason"]
    assert (f["detections"]["valid"] == 0).all() and len(f["setpoints"]) == 0
    assert not sim.armed and sim.landed


def test_handover_unanswered_falls_back_to_px4_failsafe(sim, tmp_path):
    """Target lost, but PX4 answers no command: stop streaming so PX4's own offboard-loss failsafe acts."""
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.synthetic.fault=lose_target",
                      "app.synthetic.fault_after=1.5", "link.command_timeout=1.0")

    async def silence(app) -> None:
        await wait_state(app, "ENGAGE")
        await asyncio.sleep(1.0)
        sim.silence_commands(True)

    reason, folder, _ = run_flight(cfg, silence)
    f, end, why = _end(folder)
    assert reason is Reason.TARGET_LOST and end == "SAFE_FAILSAFE_LINK", why
    assert "offboard stop failed" in why and "no answer" in why
    assert f.state_path()[-3:] == ["ENGAGE", "HANDBACK", "SAFE_FAILSAFE_LINK"]
    assert sim.wait_event("failsafe:offboard_loss", timeout=5.0) is not None
    assert sim.wait_for(lambda: sim.mode == "HOLD", timeout=5.0)


def test_land_after_abort(sim, tmp_path):
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.synthetic.fault=lose_target", "app.synthetic.fault_after=1.0",
                      "safety.land_after_abort=true")
    reason, folder, _ = run_flight(cfg)
    f, end, why = _end(folder)
    assert reason is Reason.TARGET_LOST and end == "SAFE_LANDED", why
    assert f.state_path()[-4:] == ["ENGAGE", "HANDBACK", "LAND", "SAFE_LANDED"]
    assert f.summary["exit_code"] == Reason.TARGET_LOST.value  # landed safely, but the flight failed
    assert not sim.armed and sim.landed
