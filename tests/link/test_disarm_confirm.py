"""The disarm's confirmation waits for PX4's 1 Hz heartbeat (issue #22 on PX4 SITL).

PX4 reports its arming state only in the heartbeat, so a disarm that worked shows up to ~1 s after its ACK. The
ground end after an arm command sent into a link outage gave the whole budget to PX4's auto-disarm and left 1 s to
see our own disarm: a late heartbeat made the app name an ARMED vehicle that PX4 had disarmed. The link here is
the real VehicleLink with its mavsdk action replaced: the heartbeat is a timer, nothing else is faked.
"""

from __future__ import annotations

import asyncio
import time

import pytest

from companion.app.link import VehicleLink
from companion.config_app import LinkConfig

HEARTBEAT_LAG_S = 1.5  # after the ACK; < mode_timeout (3 s): a heartbeat PX4 sends late, not a lost one


class _Action:
    def __init__(self, link: VehicleLink, lag: float) -> None:
        self.link, self.lag, self.disarms = link, lag, 0

    async def disarm(self) -> None:
        self.disarms += 1
        asyncio.get_running_loop().call_later(self.lag, setattr, self.link, "_armed", False)


def _grounded_armed_link(lag: float) -> tuple[VehicleLink, _Action]:
    link = VehicleLink(LinkConfig(command_timeout=1.0, mode_timeout=3.0))
    link._system = object()  # connected, telemetry fresh: check_link passes
    link._armed, link._landed = True, "ON_GROUND"
    action = _Action(link, lag)
    link._action = action
    return link, action


@pytest.mark.timeout(30)
def test_ground_end_budget_sees_a_disarm_reported_by_a_late_heartbeat() -> None:
    """The budget the ground end gives (1 s of auto-disarm + command_timeout): our disarm goes out after ~1 s and
    its confirmation waits for the heartbeat. Before: CommandTimeout 'disarm: accepted but the vehicle is still
    armed' (a 1 s window for a 1.5 s heartbeat), and the app named the vehicle ARMED."""
    link, action = _grounded_armed_link(HEARTBEAT_LAG_S)

    async def body() -> float:
        t0 = time.monotonic()
        await link.wait_landed_and_disarm(timeout=1.0 + link.cfg.command_timeout)
        return time.monotonic() - t0

    took = asyncio.run(body())
    assert action.disarms == 1 and link.armed is False
    assert any(kind == "landed_and_disarmed" for _, kind, _ in link.events)
    # PX4's auto-disarm got its 1 s (no earlier disarm of ours), then ours and the heartbeat's lag.
    assert took >= 1.0 + HEARTBEAT_LAG_S - 0.05, took


@pytest.mark.timeout(30)
def test_auto_disarm_wait_leaves_room_for_our_own_disarm() -> None:
    """A budget of command_timeout only: our disarm at once (PX4's auto-disarm gets no wait of its own)."""
    link, action = _grounded_armed_link(0.2)

    async def body() -> float:
        t0 = time.monotonic()
        await link.wait_landed_and_disarm(timeout=link.cfg.command_timeout)
        return time.monotonic() - t0

    took = asyncio.run(body())
    assert action.disarms == 1 and link.armed is False
    assert took < link.cfg.command_timeout + 1.0, took  # not the old 5 s auto-disarm wait + 1 s
