"""The pre-flight summary compares the configured airframe's hover thrust with PX4's and says which it uses;
a large mismatch is a WARNING line (simulated PX4 over the real mavsdk)."""

from __future__ import annotations

import asyncio
import json

import pytest
from flighthelpers import FAST_PX4, make_config

from companion.app.session import fly
from companion.app.states import Reason
from companion.config import load_config
from companion.hover import hover_mismatch
from companion.sim.px4 import SimPX4

pytestmark = pytest.mark.timeout(120)


def test_hover_mismatch_line():
    assert hover_mismatch(0.5, 0.52, 0.52, True) is None  # 4 %: agrees
    assert hover_mismatch(0.5, None, 0.5, True) is None  # PX4's unknown: nothing to compare
    line = hover_mismatch(0.5, 0.403, 0.403, True)
    assert line is not None and "-19%" in line and "lighter" in line and "using 0.403" in line
    off = hover_mismatch(0.5, 0.625, 0.625, False)
    assert off is not None and "+25%" in off and "heavier" in off and "OFF" in off


def test_preflight_shows_a_hover_thrust_mismatch_with_px4(tmp_path):
    light = load_config([], ["sim.seed=7"])
    px4 = SimPX4(light, px4_params={**FAST_PX4, "MPC_THR_HOVER": 0.403})  # the 1.5 kg / T/W 2.5 vehicle
    px4.start()
    shown: list[str] = []

    async def operator(text: str) -> bool:
        shown.append(text)
        return False

    try:
        cfg = make_config(tmp_path, px4.url_for_mavsdk)
        reason, folder, _ = asyncio.run(asyncio.wait_for(
            fly(cfg, plot=False, handle_signals=False, confirm=operator), 60.0))
    finally:
        px4.stop()
    assert reason is Reason.NOT_CONFIRMED
    text = shown[0]
    assert "0.403 from PX4 MPC_THR_HOVER" in text and "config 0.500, PX4 0.403" in text
    warn = [ln for ln in text.splitlines() if "hover thrust mismatch" in ln]
    assert len(warn) == 1 and warn[0].lstrip().startswith("WARNING") and "using 0.403" in warn[0]
    pre = json.loads((folder / "preflight.json").read_text())
    assert pre["hover_thrust"]["configured"] == 0.5 and pre["hover_thrust"]["autopilot"] == pytest.approx(0.403)
    assert "mismatch" in pre["hover_thrust"]["mismatch"]
