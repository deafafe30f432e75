"""Shadow mode on the simulated PX4 through the real mavsdk: the pilot's vehicle (airborne, POSCTL) is never
commanded (no setpoint, no arming, mode or take-off command reaches the autopilot) while the whole pipeline runs
and its setpoints are logged, complete, beside the attitude the vehicle flew."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from flighthelpers import FAST_PX4, make_config
from pymavlink.dialects.v20 import common as mavlink

from companion.app.shadow import ReadOnlyLink, ShadowViolation, plot_shadow, shadow
from companion.config import load_config
from companion.flightlog import TOPICS, read_flight
from companion.sim.dynamics import QuadState
from companion.sim.px4 import SimPX4

pytestmark = pytest.mark.timeout(120)

# Requests for telemetry that mavsdk and the link make: they read, they never move the vehicle.
READ_ONLY_COMMANDS = {mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_CMD_REQUEST_MESSAGE,
                      mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES}


def test_shadow_sends_nothing_and_logs_everything(tmp_path):
    cfg_sim = load_config([], ["sim.seed=7"])
    start = QuadState(p=np.array([0.0, 0.0, 6.0]), on_ground=False)  # the pilot is flying, holding position
    px4 = SimPX4(cfg_sim, initial_state=start, initial_mode="POSCTL", px4_params=FAST_PX4)
    px4.start()
    try:
        cfg = make_config(tmp_path, px4.url_for_mavsdk, "app.start=pilot", "app.synthetic.motion=linear_fast",
                          "app.synthetic.distance=20", "app.engage=confirm")
        code, folder, summary = asyncio.run(asyncio.wait_for(
            shadow(cfg, duration=10.0, handle_signals=False, plot=False), 60.0))
        ev = [e for _, e in px4.events]
        assert px4.setpoint_count == 0
        assert px4.armed and px4.mode == "POSCTL"
    finally:
        px4.stop()
    assert code == 0, summary
    # The autopilot's own record: no arming, mode change, take-off or landing; only read-only requests.
    assert not [e for e in ev if e.startswith(("arm", "disarm", "mode", "takeoff", "land", "offboard"))], ev
    cmds = {int(e.split(":")[1]) for e in ev if e.startswith("command:")}
    assert cmds <= READ_ONLY_COMMANDS, cmds

    f = read_flight(folder)
    assert set(TOPICS) <= set(f.tables)  # every topic file is there
    assert f.state_path() == ["CONNECT", "SHADOW", "SHADOW_END"]
    assert f.summary["outcome"] == "SHADOW_END" and f.summary["setpoints_sent"] == 0
    assert f.summary["exit_code"] == 0 and f.summary["rows"]["setpoints"] == f.summary["setpoints_computed"]
    tel, det, sp = f["telemetry"], f["detections"], f["setpoints"]
    assert len(tel) > 100 and np.isfinite(tel["qw"]).mean() > 0.95  # the attitude the pilot flew, 20 Hz
    assert len(det) > 100 and (det["valid"] == 1).sum() > 30  # the gate was seen
    assert len(sp) > 10 and set(sp["state"]) == {"SHADOW"}  # computed, marked shadow
    assert any(str(m).startswith("ENGAGE/pn") for m in sp["ctrl_mode"])
    for c in ("roll_deg", "pitch_deg", "yaw_deg", "thrust"):
        assert np.isfinite(sp[c]).all()
    assert len(f["los"]) > 10
    assert any("shadow: ACQUIRE -> ENGAGE" in str(t) for t in f["events"]["text"])
    # app.engage confirm: shadow engages as auto would and notes where the flight would have asked the operator
    assert any("would have asked the operator to confirm" in str(t) for t in f["events"]["text"])
    png = plot_shadow(folder)
    assert png.stat().st_size > 10_000


def test_read_only_link_refuses_every_command():
    class Dummy:
        link_ok = True

        async def arm(self) -> None:  # pragma: no cover - must never be reached
            raise AssertionError("reached the vehicle")

    ro = ReadOnlyLink(Dummy())
    assert ro.link_ok is True
    for name in ("arm", "takeoff", "start_offboard", "set_setpoint", "land", "hold", "stop_offboard"):
        with pytest.raises(ShadowViolation):
            getattr(ro, name)
