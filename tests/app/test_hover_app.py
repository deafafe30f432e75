"""The app estimates the hover thrust in flight (hover.estimate) on a vehicle heavier than PX4's parameter says:
simulated PX4 over real mavsdk, true hover thrust 0.6, MPC_THR_HOVER left at 0.5."""

from __future__ import annotations

import numpy as np
import pytest
from flighthelpers import FAST_PX4, make_config, run_flight

from companion.app.states import Reason
from companion.config import load_config
from companion.flightlog import read_flight
from companion.sim.px4 import SimPX4

pytestmark = pytest.mark.timeout(150)


def test_app_flies_with_the_hover_thrust_it_estimates(tmp_path):
    heavy = load_config([], ["sim.seed=7", "sim.quad.hover_thrust=0.6", "sim.quad.thrust_to_weight=1.67"])
    px4 = SimPX4(heavy, px4_params={**FAST_PX4, "MPC_THR_HOVER": 0.5})  # a stale parameter
    px4.start()
    try:
        cfg = make_config(tmp_path, px4.url_for_mavsdk, "hover.estimate=true", "app.synthetic.motion=stationary")
        reason, folder, summary = run_flight(cfg)
    finally:
        px4.stop()
    assert reason is Reason.OK, summary
    f = read_flight(folder)
    hv = f["hover"]
    assert len(hv) > 10
    assert hv["hover_thrust"][-1] == pytest.approx(0.6, abs=0.03)  # from 0.5, within a 5 % band of the truth
    # The samples agree with the model the estimate stands for: a_up = g / hover * u (within noise and lag).
    resid = hv["a_up"] - 9.81 / hv["hover_thrust"][-1] * hv["u_cmd"]
    assert abs(float(np.median(resid))) < 0.5
    texts = [str(t) for t in f["events"]["text"]]
    assert any(t.startswith("hover thrust 0.500 from MPC_THR_HOVER") for t in texts)
    assert any("estimated from the IMU" in t for t in texts)
    # The setpoints after the estimate carry the new hover thrust: RECOVER holds level at hover x scale.
    sp = f["setpoints"]
    rec = sp["thrust"][sp["state"] == "RECOVER"]
    assert rec.size and rec[-1] == pytest.approx(min(1.0, hv["hover_thrust"][-1] * cfg.app.recover_thrust_scale),
                                                 rel=0.05)
