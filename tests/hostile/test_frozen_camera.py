"""The frozen-camera probe, end to end: rendered frames through the real detector, the app, real mavsdk
and the simulated PX4. The camera starts repeating its last image with fresh timestamps mid-engagement.

Before the frame checks, PN flew on the frozen box (the vehicle turned, the box did not, which reads as
LOS rate): pitch -86 deg at thrust 0.1, the altitude floor at 1.4 m falling at 12 m/s, touchdown, and a
"SAFE_HOLD: PX4 holds" report. Now: CAMERA_FAILED within the frozen timeout, PX4 holds high above the floor.
"""

from __future__ import annotations

import numpy as np
import pytest
from flighthelpers import make_config, run_flight

from companion.app.assemble import detector_available
from companion.app.states import Reason
from companion.config import load_config
from companion.flightlog import read_flight

pytestmark = [pytest.mark.timeout(180), pytest.mark.skipif(detector_available(load_config()) is not None,
                                                            reason="the shipped gate detector is not available")]


def test_frozen_camera_ends_in_a_named_abort_high_above_the_floor(sim, tmp_path):
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.synthetic.render=image", "app.synthetic.fault=freeze",
                      "app.synthetic.fault_after=1.2")
    reason, folder, summary = run_flight(cfg)
    f = read_flight(folder)
    path = f.state_path()
    assert reason is Reason.CAMERA_FAILED, (summary, path)
    assert path[-3:] == ["ENGAGE", "HANDBACK", "SAFE_HOLD"], path
    assert "camera frozen" in f.states[-1]["reason"] and summary["exit_code"] == Reason.CAMERA_FAILED.value
    assert sim.mode == "HOLD" and sim.armed and not sim.landed
    # Independent of the app: the simulator's own truth. The vehicle stayed high above the 2 m floor.
    alt = -f["truth"]["d"]
    t_hb = next(float(r["t"]) for r in f.states if r["to_state"] == "HANDBACK")
    assert alt[f["truth"]["t"] >= t_hb - 2.0].min() > cfg.safety.altitude_floor + 1.5
    truth = sim.truth()
    assert truth.p[2] > cfg.safety.altitude_floor + 1.5 and not truth.ground_contact  # ENU: z up
    # No setpoint flew on the frozen picture for long: nothing near the probe's -86 deg / 0.1 thrust dive.
    sp = f["setpoints"]
    assert np.abs(sp["pitch_deg"]).max() < 60.0 and sp["thrust"].min() > 0.1
