"""Operator-confirmed engagement end to end: the real mavsdk reads RC_CHANNELS from the simulated PX4 (its RC
transmitter switch), the app waits with the candidate until the switch is turned on, and turning it off during
the engagement stops it in Hold."""

from __future__ import annotations

import asyncio

import pytest
from flighthelpers import make_config, run_flight

from companion.app.states import Reason
from companion.flightlog import read_flight

pytestmark = pytest.mark.timeout(150)

OFF, ON = 1000, 2000


def _rc(ch7: int) -> list[int]:
    return [1500, 1500, 1000, 1500, 1000, 1000, ch7, 1000]


def test_engages_only_when_confirmed_and_withdrawal_holds(sim, tmp_path):
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.engage=confirm", "app.confirm.rc_channel=7")
    sim.set_rc(_rc(ON))  # a switch left ON at start confirms nothing: it must be turned on for the candidate
    marks: dict[str, float] = {}

    async def operator(app):
        loop = asyncio.get_running_loop()
        while app.core is None or not app.core.engagement.awaiting:
            await asyncio.sleep(0.02)
        marks["awaiting"] = app.clock()
        await asyncio.sleep(1.0)  # the candidate is shown; the switch is still on from the start: no engagement
        assert app.core.phase.value == "ACQUIRE"
        sim.set_rc(_rc(OFF))
        await asyncio.sleep(0.4)
        sim.set_rc(_rc(ON))
        marks["on"] = app.clock()
        t0 = loop.time()
        while app.core.phase.value != "ENGAGE":
            assert loop.time() - t0 < 5.0, "never engaged after the switch was turned on"
            await asyncio.sleep(0.02)
        await asyncio.sleep(0.5)
        sim.set_rc(_rc(OFF))
        marks["off"] = app.clock()

    reason, folder, summary = run_flight(cfg, operator)
    assert reason is Reason.NOT_CONFIRMED, summary
    f = read_flight(folder)
    path = f.state_path()
    assert "ENGAGE" in path and path[-1] == "SAFE_HOLD", path
    ev = [str(e) for e in f["events"]["text"]]
    assert any("candidate awaiting confirmation" in e for e in ev), ev
    assert any("confirmed by the operator" in str(r["reason"]) for r in f.states if r["to_state"] == "ENGAGE")
    assert any("withdrew the confirmation" in str(r["reason"]) for r in f.states), f.states
    # held in ACQUIRE for 1 s with the switch on from the start; engaged only after it was turned off and on
    assert marks["awaiting"] + 1.0 < marks["on"] < marks["off"]
    # the simulated PX4's own witness: it was commanded to Hold after offboard
    pev = [e for _, e in sim.events]
    i_off = next(i for i, e in enumerate(pev) if e.startswith("mode:OFFBOARD:command"))
    assert any(e.startswith("mode:HOLD:command") for e in pev[i_off:]), pev
