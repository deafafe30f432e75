"""Link outages and app stalls at the worst moments (issue #22): the simulated PX4 frozen with SIGSTOP while
the app arms or checks, PX4's own offboard-loss failsafe after a short drop, the app itself frozen. Each ends in
a named state that is true of the vehicle (checked against the simulated PX4's own state), with its exit code.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest
from flighthelpers import make_config, run_flight
from simproc import SimProcess

from companion.app.states import Reason
from companion.flightlog import read_flight

pytestmark = pytest.mark.timeout(150)


@pytest.fixture
def simproc() -> Iterator[SimProcess]:
    s = SimProcess()
    try:
        yield s
    finally:
        s.stop()


def _freeze_at(method: str, sim: SimProcess, seconds: float):
    """Freeze the simulated PX4 just as the app calls ``link.<method>``: the command goes out into the outage."""

    async def side(app) -> None:
        real = getattr(app.link, method)

        async def frozen(*a, **kw):
            sim.freeze(seconds)
            return await real(*a, **kw)

        setattr(app.link, method, frozen)

    return side


def test_link_outage_while_arming_never_says_not_armed_of_an_armed_vehicle(simproc, tmp_path):
    """Before: ``ARM -> ABORT_NOT_ARMED ... safe end failed (IllegalTransition: ARM -> SAFE_FAILSAFE_LINK ...)``,
    exit 16, while PX4 armed on resume (the ARM command waited in the socket) and stayed armed 4-10 s."""
    cfg = make_config(tmp_path, simproc.url)
    reason, folder, summary = run_flight(cfg, _freeze_at("arm", simproc, 2.0))
    f = read_flight(folder)
    last = f.states[-1]
    assert "IllegalTransition" not in last["reason"] and "safe end failed" not in last["reason"], last
    assert reason is Reason.LINK_LOST and summary["exit_code"] == 16, summary
    # PX4 armed when it resumed (the arm command was delivered late); the app disarmed it and says so.
    assert "arm" in simproc.events(), simproc.events()
    st = simproc.state()
    assert st["armed"] == "0", st
    assert "disarm:command" in simproc.events()
    assert last["to_state"] == "SAFE_LANDED" and "disarmed" in last["reason"], last
    assert "armed" in last["reason"] and summary["outcome"] == "SAFE_LANDED"
    # Still disarmed a while later: nothing of ours armed it again.
    time.sleep(1.0)
    assert simproc.state()["armed"] == "0"
    assert all(t.truncated_rows == 0 for t in f.tables.values())


def test_link_outage_in_preflight_ends_not_armed_without_an_illegal_transition(simproc, tmp_path):
    cfg = make_config(tmp_path, simproc.url)
    reason, folder, summary = run_flight(cfg, _freeze_at("failsafe_params", simproc, 2.5))
    f = read_flight(folder)
    last = f.states[-1]
    assert "IllegalTransition" not in last["reason"], last
    assert reason is Reason.LINK_LOST and summary["exit_code"] == 16, (summary, last)
    assert last["to_state"] == "ABORT_NOT_ARMED" and f.state_path()[-2:] == ["PREFLIGHT", "ABORT_NOT_ARMED"]
    st = simproc.state()
    assert st["armed"] == "0" and "arm" not in simproc.events(), st


def test_short_link_drop_in_engage_is_px4s_failsafe_not_a_pilot(sim, tmp_path):
    """Issue #22: a 1.2 s drop (> COM_OF_LOSS_T 1 s, < link_lost_timeout 1.5 s) in ENGAGE: PX4's offboard-loss
    failsafe switched to Position mode and the app named ``SAFE_PILOT ... the pilot has the vehicle in POSCTL``
    (exit 15), with no pilot anywhere."""
    import asyncio

    from flighthelpers import wait_state

    async def side(app) -> None:
        await wait_state(app, "ENGAGE")
        await asyncio.sleep(1.0)
        sim.drop_link(True)
        await asyncio.sleep(1.2)
        sim.drop_link(False)

    reason, folder, summary = run_flight(make_config(tmp_path, sim.url_for_mavsdk), side)
    f = read_flight(folder)
    last = f.states[-1]
    ev = [e for _, e in sim.events]
    assert "failsafe:offboard_loss" in ev and "mode:POSCTL:failsafe" in ev, ev  # PX4's failsafe, truly
    assert not any(e.endswith(":pilot") for e in ev)  # and no pilot
    assert reason is Reason.AUTOPILOT_MODE and summary["exit_code"] == 33, (summary, last)
    assert last["to_state"] == "AUTOPILOT" and "pilot" not in last["reason"].split(";")[-1], last
    assert "offboard-loss failsafe" in last["reason"] and "POSCTL" in last["reason"], last
    assert sim.mode == "POSCTL" and sim.armed  # what the app named is what the vehicle does
    assert all(t.truncated_rows == 0 for t in f.tables.values())
