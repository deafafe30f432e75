"""Pre-flight summary and confirmation: shown before arming, logged; no confirmation -> a named ground abort
(nothing armed), through the real mavsdk and, for the stdin prompt, a real ``companion fly`` process."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys

import pytest
from flighthelpers import make_config

from companion.app.main import fly
from companion.app.states import Reason
from companion.flightlog import read_flight

pytestmark = pytest.mark.timeout(120)


def test_summary_is_shown_and_no_confirmation_aborts_on_the_ground(sim, tmp_path):
    shown: list[str] = []

    async def operator(text: str) -> bool:
        shown.append(text)
        return False  # the operator says no

    cfg = make_config(tmp_path, sim.url_for_mavsdk)
    reason, folder, summary = asyncio.run(asyncio.wait_for(
        fly(cfg, plot=False, handle_signals=False, confirm=operator), 60.0))
    assert reason is Reason.NOT_CONFIRMED and summary["exit_code"] == 25
    assert summary["outcome"] == "ABORT_NOT_ARMED"
    assert not any(e.startswith(("arm", "takeoff", "mode")) for _, e in sim.events)  # nothing commanded
    assert not sim.armed and sim.setpoint_count == 0
    text = shown[0]
    for key in ("link", "autopilot", "vehicle", "failsafe", "hover thrust", "camera", "detector", "PN", "envelope",
                "safety"):
        assert f"\n{key}" in text, key
    assert "mode HOLD" in text and "armable True" in text and "0.500 from PX4 MPC_THR_HOVER" in text
    assert "COM_OF_LOSS_T" in text
    f = read_flight(folder)
    assert f.state_path() == ["CONNECT", "PREFLIGHT", "ABORT_NOT_ARMED"]
    assert "did not confirm" in f.states[-1]["reason"]
    pre = json.loads((folder / "preflight.json").read_text())
    assert pre["hover_thrust"]["source"] == "PX4 MPC_THR_HOVER" and pre["armable"]["armable"] is True
    assert pre["failsafe"]["values"]["COM_OF_LOSS_T"] == pytest.approx(sim.param("COM_OF_LOSS_T"))
    assert any(str(t).startswith("preflight: NOT confirmed") for t in f["events"]["text"])


def test_companion_fly_asks_on_stdin_and_a_no_is_a_named_ground_abort(sim, tmp_path):
    res = subprocess.run(
        [sys.executable, "-m", "companion.cli", "fly", "--url", sim.url_for_mavsdk, "--geometric", "--no-plot",
         "--log-dir", str(tmp_path / "flights"), "--set", "link.connect_timeout=10"],
        input="no\n", capture_output=True, text=True, timeout=90)
    assert res.returncode == int(Reason.NOT_CONFIRMED), res.stderr[-2000:]
    assert "PRE-FLIGHT SUMMARY" in res.stderr and "Type 'yes'" in res.stderr
    assert "NOT_CONFIRMED" in res.stderr
    assert not sim.armed and not any(e.startswith("arm") for _, e in sim.events)
