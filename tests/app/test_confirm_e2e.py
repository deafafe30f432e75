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


USER_1 = 31010  # MAV_CMD_USER_1: app.confirm.command's default
ACCEPTED, TEMPORARILY_REJECTED = 0, 1


async def _until(pred, what: str, timeout: float = 10.0) -> None:
    """Bounded wait for a condition of the flight (generous: a loaded CI machine)."""
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    while not pred():
        assert loop.time() - t0 < timeout, f"timed out waiting for {what}"
        await asyncio.sleep(0.02)


def test_ground_station_confirms_and_withdraws(sim, tmp_path):
    """No RC at all: the ground station's COMMAND_LONG (forwarded by PX4 to the companion's ids) confirms the
    candidate, each command is acknowledged, and its withdraw ends the engagement in Hold."""
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.engage=confirm")
    sim.set_gcs(True)
    marks: dict[str, object] = {}

    async def operator(app):
        await _until(lambda: app.core is not None, "the flight loop")
        await _until(lambda: app.core.engagement.awaiting, "a candidate awaiting confirmation", 30.0)
        await asyncio.sleep(1.0)  # shown, nobody confirms: no engagement
        marks["phase_unconfirmed"] = app.core.phase.value
        marks["acks_before"] = list(sim.gcs_acks)
        sim.gcs_command(USER_1, 1.0)
        await _until(lambda: app.core.phase.value == "ENGAGE", "ENGAGE after the ground station's confirm")
        await _until(lambda: len(sim.gcs_acks) >= 1, "the confirm's COMMAND_ACK")
        await asyncio.sleep(0.5)
        sim.gcs_command(USER_1, 0.0)
        await _until(lambda: len(sim.gcs_acks) >= 2, "the withdraw's COMMAND_ACK")

    reason, folder, summary = run_flight(cfg, operator)
    assert marks["phase_unconfirmed"] == "ACQUIRE" and marks["acks_before"] == []
    assert sim.gcs_acks[:2] == [(USER_1, ACCEPTED), (USER_1, ACCEPTED)], sim.gcs_acks
    assert reason is Reason.NOT_CONFIRMED, summary
    f = read_flight(folder)
    path = f.state_path()
    assert "ENGAGE" in path and path[-1] == "SAFE_HOLD", path
    ev = [str(e) for e in f["events"]["text"]]
    assert any("ground-station confirm from 255/190: ACCEPTED" in e for e in ev), ev
    assert any("ground-station withdraw from 255/190: ACCEPTED" in e for e in ev), ev
    assert any("withdrawn from the ground station" in e for e in ev), ev
    assert any("confirmed by the operator" in str(r["reason"]) for r in f.states if r["to_state"] == "ENGAGE")
    pev = [e for _, e in sim.events]
    i_off = next(i for i, e in enumerate(pev) if e.startswith("mode:OFFBOARD:command"))
    i_cmd = next(i for i, e in enumerate(pev) if e == f"gcs_command:{USER_1}:1")
    assert i_cmd < i_off, "offboard was commanded before the ground station confirmed"
    assert any(e.startswith("mode:HOLD:command") for e in pev[i_off:]), pev


def test_ground_station_confirm_lapses_when_it_goes_silent(sim, tmp_path):
    """A GCS confirmation lasts while that ground station is heard: its HEARTBEATs stop -> withdrawn, Hold."""
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.engage=confirm", "app.confirm.gcs_max_age=1.0")
    sim.set_gcs(True)

    async def operator(app):
        await _until(lambda: app.core is not None, "the flight loop")
        await _until(lambda: app.core.engagement.awaiting, "a candidate awaiting confirmation", 30.0)
        sim.gcs_command(USER_1, 1.0)
        await _until(lambda: app.core.phase.value == "ENGAGE", "ENGAGE after the ground station's confirm")
        sim.set_gcs(False)  # the ground station drops out while the vehicle engages

    reason, folder, summary = run_flight(cfg, operator)
    assert reason is Reason.NOT_CONFIRMED, summary
    f = read_flight(folder)
    assert f.state_path()[-1] == "SAFE_HOLD", f.state_path()
    ev = [str(e) for e in f["events"]["text"]]
    assert any("confirmation withdrawn: ground station (255, 190) not heard" in e for e in ev), ev


def test_parse_command_takes_only_ours_addressed_to_us():
    import json
    from types import SimpleNamespace

    from companion.app.gcsconfirm import ack_message, parse_command

    def msg(command=USER_1, target=(1, 195), p1=1.0, sender=(255, 190)):
        f = {"command": command, "param1": p1, "target_system": target[0], "target_component": target[1]}
        return SimpleNamespace(system_id=sender[0], component_id=sender[1], fields_json=json.dumps(f))

    cmd = parse_command(msg(), (1, 195), USER_1, 5.0)
    assert (cmd.t, cmd.param1, cmd.sysid, cmd.compid) == (5.0, 1.0, 255, 190)
    assert parse_command(msg(command=31011), (1, 195), USER_1, 5.0) is None  # another command
    assert parse_command(msg(target=(1, 1)), (1, 195), USER_1, 5.0) is None  # PX4's, not ours
    assert parse_command(msg(p1=None), (1, 195), USER_1, 5.0).param1 != 0.0  # NaN: refused later (DENIED)
    bad = SimpleNamespace(system_id=255, component_id=190, fields_json="{")
    assert parse_command(bad, (1, 195), USER_1, 5.0) is None
    assert ack_message(cmd, USER_1, 1) == {"command": USER_1, "result": 1, "progress": 0, "result_param2": 0,
                                           "target_system": 255, "target_component": 190}
