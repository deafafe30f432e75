"""After take-off the app compares the thrust PX4 commands in its hover (ATTITUDE_TARGET) with the configured
airframe and PX4's MPC_THR_HOVER, says it in one line and flies PX4's value when it is off by more than 10 %
(issue 20; companion/vehiclematch.py). Simulated PX4 over the real mavsdk."""

from __future__ import annotations

import asyncio
import io
import json
import math

import pytest
from flighthelpers import FAST_PX4, FLIGHT_TIMEOUT, make_config, pilot_takes_off

from companion.app.session import fly
from companion.app.states import Reason
from companion.config import load_config
from companion.flightlog import read_flight
from companion.sim.dynamics import QuadParams
from companion.sim.px4 import SimPX4
from companion.vehiclematch import (
    MIN_SAMPLES,
    SETTLE_S,
    WINDOW,
    ThrustSample,
    hover_after_takeoff,
    measured_hover,
    param_mismatches,
    vertical_thrust,
)

pytestmark = pytest.mark.timeout(150)


def _q_roll(deg: float) -> tuple[float, float, float, float]:
    h = math.radians(deg) / 2
    return (math.cos(h), math.sin(h), 0.0, 0.0)


def test_vertical_thrust_and_median():
    assert vertical_thrust(0.5, _q_roll(0.0)) == pytest.approx(0.5)
    assert vertical_thrust(0.5, _q_roll(60.0)) == pytest.approx(0.25)  # cos 60

    def hold(t: float, thrust: float, **kw: object) -> ThrustSample:
        base = {"mode": "HOLD", "landed": "IN_AIR", "alt": 5.0}
        return ThrustSample(t, thrust, _q_roll(0.0), **{**base, **kw})  # type: ignore[arg-type]

    # The first SETTLE_S of the hover (the climb's end) is left out.
    ok = [hold(0.0, 0.30)] + [hold(SETTLE_S + 0.1 * i, 0.40) for i in range(MIN_SAMPLES)]
    assert measured_hover(ok) == (pytest.approx(0.40), MIN_SAMPLES)
    # Not PX4's hover: after ``until`` (our setpoints while the mode PX4 reports still lags), OFFBOARD, the climb
    # (TAKING_OFF), on or near the ground.
    other = [hold(9.0, 0.9), hold(2.0, 0.9, mode="OFFBOARD"), hold(2.0, 0.1, landed="ON_GROUND"),
             hold(2.0, 0.8, landed="TAKING_OFF"), hold(2.0, 0.8, alt=0.2)]
    assert measured_hover(ok + other, until=5.0, ground=0.0) == (pytest.approx(0.40), MIN_SAMPLES)
    # Above the app's ground reference (raw barometric altitude), not above wherever the barometer first read:
    # 0.2 m over a ground at -4.9 m is 5.1 m up; with no ground known, PX4's IN_AIR decides.
    assert measured_hover([*ok, hold(2.0, 0.40, alt=0.2)], ground=-4.9) == (pytest.approx(0.40), MIN_SAMPLES + 1)
    assert measured_hover([*ok, hold(2.0, 0.40, alt=0.2)], ground=0.0) == (pytest.approx(0.40), MIN_SAMPLES)
    assert measured_hover([*ok, hold(2.0, 0.40, alt=None)]) == (pytest.approx(0.40), MIN_SAMPLES + 1)
    assert measured_hover(ok[:-1]) == (None, MIN_SAMPLES - 1)
    assert measured_hover(ok, need=WINDOW) == (None, MIN_SAMPLES)
    # The newest WINDOW only: the take-off's end swings, the hover after it counts.
    swing = [hold(0.1 * i, 0.30) for i in range(20)] + [hold(2.0 + 0.1 * i, 0.41) for i in range(WINDOW)]
    assert measured_hover(swing, until=1.95) == (pytest.approx(0.30), WINDOW)  # still the swing then
    assert measured_hover(swing, need=WINDOW) == (pytest.approx(0.41), WINDOW)


def test_the_line_the_decision_and_the_params():
    light = hover_after_takeoff(0.40, 12, 0.50, 0.50, 0.50, 0.50, "PX4 MPC_THR_HOVER", start_from_px4=True,
                                estimate_on=True)
    assert light.warning and light.flies == pytest.approx(0.40) and light.flies_source == "PX4 measured"
    assert light.line.startswith("WARNING hover thrust after take-off: PX4 commands 0.40")
    assert "configured 0.50 (PX4 MPC_THR_HOVER 0.50): the vehicle is 20% lighter than configured" in light.line
    assert "flying with PX4's measured value (0.40)" in light.line
    # Matched (within 10 %): no warning and the value in use stays (a matching vehicle flies as before).
    same = hover_after_takeoff(0.47, 12, 0.50, 0.50, 0.50, 0.50, "PX4 MPC_THR_HOVER", start_from_px4=True,
                               estimate_on=True)
    assert not same.warning and same.flies == 0.50 and "matches the configuration" in same.line
    off = hover_after_takeoff(0.60, 12, 0.50, 0.50, None, 0.50, "config", start_from_px4=False, estimate_on=False)
    assert off.warning and off.flies == 0.50 and "20% heavier" in off.line and "OFF" in off.line
    late = hover_after_takeoff(0.60, 12, 0.50, 0.50, None, 0.50, "config", start_from_px4=True, estimate_on=True,
                               too_late=True)
    assert late.flies == 0.50 and "the engagement had begun" in late.line
    # Within 10 % of the value in use (the estimate had moved): no change, whatever the configuration says.
    near = hover_after_takeoff(0.60, 12, 0.56, 0.50, None, 0.56, "config", start_from_px4=True, estimate_on=True)
    assert near.warning and near.flies == 0.56
    none = hover_after_takeoff(None, 2, 0.5, 0.5, None, 0.5, "config", start_from_px4=True, estimate_on=True)
    assert not none.warning and none.px4_commanded is None and "not measured" in none.line

    class Af:
        max_tilt, thrust_min = 50.0, 0.1
    lines = param_mismatches({"MPC_TILTMAX_AIR": 45.0, "MPC_THR_MIN": 0.1}, Af())
    assert len(lines) == 1 and "MPC_TILTMAX_AIR 45 deg, config airframe.max_tilt 50 deg" in lines[0]
    assert param_mismatches({"MPC_TILTMAX_AIR": None, "MPC_THR_MIN": 0.1004}, Af()) == []


def _fly(tmp_path, truth: list[str], *overrides: str):
    vehicle = load_config([], ["sim.seed=7", *truth])
    true_hover = QuadParams.from_config(vehicle).hover_thrust  # the independent figure: the sim's own vehicle
    px4 = SimPX4(vehicle, px4_params={**FAST_PX4, "MPC_THR_HOVER": 0.5})  # PX4's parameter left at its default
    px4.start()
    try:
        # 1.5 s of stable track before engaging (default 0.33 s): PX4's hover is measured within ACQUIRE on any
        # machine, so the test does not depend on how fast this one reaches the engagement.
        cfg = make_config(tmp_path, px4.url_for_mavsdk, "app.synthetic.motion=stationary", "app.acquire_frames=45",
                          *overrides)
        console = io.StringIO()
        reason, folder, summary = asyncio.run(asyncio.wait_for(
            fly(cfg, plot=False, handle_signals=False, stderr=console), FLIGHT_TIMEOUT))
    finally:
        px4.stop()
    return true_hover, reason, folder, summary, console.getvalue()


def test_a_lighter_vehicle_is_a_warning_with_the_right_figures(tmp_path):
    true_hover, reason, folder, summary, console = _fly(tmp_path, ["sim.quad.mass_scale=0.8"])
    assert true_hover == pytest.approx(0.40)
    assert reason is Reason.OK, summary
    r = summary["hover"]["after_takeoff"]
    assert r["px4_commanded"] == pytest.approx(true_hover, abs=0.01)  # PX4's hover = the sim's true vehicle
    assert r["configured"] == 0.5 and r["mpc_thr_hover"] == pytest.approx(0.5) and r["warning"]
    assert r["vs_configured"] == pytest.approx(true_hover / 0.5 - 1.0, abs=0.025)
    assert r["flies"] == pytest.approx(r["px4_commanded"]) and r["flies_source"] == "PX4 measured"
    line = r["line"]
    assert line.startswith("WARNING hover thrust after take-off: PX4 commands 0.40") and "20% lighter" in line
    assert f"companion: {line}" in console.splitlines()  # on the console
    events = [str(t) for t in read_flight(folder)["events"]["text"]]
    assert line in events
    on_disk = json.loads((folder / "summary.json").read_text())
    assert on_disk["hover"]["after_takeoff"]["px4_commanded"] == pytest.approx(r["px4_commanded"])
    assert on_disk["hover"]["preflight"]["hover_thrust"]["configured"] == 0.5


def test_a_matched_vehicle_is_no_warning(tmp_path):
    true_hover, reason, _, summary, console = _fly(tmp_path, [])
    assert reason is Reason.OK, summary
    r = summary["hover"]["after_takeoff"]
    assert r["px4_commanded"] == pytest.approx(true_hover, abs=0.01) and true_hover == pytest.approx(0.5)
    assert not r["warning"] and not r["line"].startswith("WARNING") and r["flies"] == 0.5
    assert "WARNING hover thrust" not in console and "hover thrust after take-off: PX4 commands 0.50" in console


def test_a_vehicle_already_hovering_when_the_app_starts_is_measured_too(tmp_path):
    """app.start=pilot with the vehicle in the air before the app connects (the PX4 studies, a pilot who took off
    first; the app is told the ground with safety.altitude_reference): the height is taken above that ground, not
    above the barometer's first reading in the air. The old rule measured nothing here (0 samples)."""
    from companion.sim.px4.wire import HOME_ALT

    vehicle = load_config([], ["sim.seed=7", "sim.quad.mass_scale=0.8"])
    true_hover = QuadParams.from_config(vehicle).hover_thrust
    px4 = SimPX4(vehicle, px4_params={**FAST_PX4, "MPC_THR_HOVER": 0.5})
    px4.start()
    try:
        pilot_takes_off(px4, 5.0)  # a ground station arms and takes off before the app starts, then POSCTL
        cfg = make_config(tmp_path, px4.url_for_mavsdk, "app.start=pilot", "app.synthetic.motion=stationary",
                          "app.acquire_frames=45", f"safety.altitude_reference={HOME_ALT}")
        console = io.StringIO()
        reason, _, summary = asyncio.run(asyncio.wait_for(
            fly(cfg, plot=False, handle_signals=False, stderr=console), FLIGHT_TIMEOUT))
    finally:
        px4.stop()
    assert "after_takeoff" in summary.get("hover", {}), (reason, summary, console.getvalue())
    r = summary["hover"]["after_takeoff"]
    assert r["px4_commanded"] == pytest.approx(true_hover, abs=0.01) and r["warning"], (r, console.getvalue())
    assert reason is Reason.OK, summary
