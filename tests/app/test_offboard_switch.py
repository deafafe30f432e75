"""The engagement steers while PX4's switch to OFFBOARD is still unconfirmed.

PX4 accepts OFFBOARD ~0.2 s after the first setpoint but reports it in its 1 Hz heartbeat: on PX4 1.15 SITL the app
saw the switch 0.3-1.3 s after its first setpoint (479 engagements: median 0.6 s, 27 over 1 s). Before, the
engagement stood still meanwhile and MAVSDK resent the first setpoint: the vehicle flew that attitude open loop,
the gate could leave the view, and the first step after the switch found the box lost for over
``safety.target_lost_timeout`` (TARGET_LOST on real PX4). Now each frame's setpoint reaches PX4 during the switch.
"""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from flighthelpers import make_config, run_flight, wait_state

from companion.app.states import Reason
from companion.flightlog import read_flight

pytestmark = pytest.mark.timeout(150)


def test_setpoints_follow_the_engagement_while_px4_switches_to_offboard(sim, tmp_path):
    cfg = make_config(tmp_path, sim.url_for_mavsdk)
    seen: list[tuple[float, tuple[float, ...]]] = []  # (sim time received, attitude + thrust) PX4 had, polled

    async def watch(app) -> None:
        await wait_state(app, "ENGAGE", timeout=60.0)
        while not app.link.offboard_active:  # the app has not seen PX4 report OFFBOARD yet
            t, q, thrust = sim.last_setpoint()
            if q is not None and (not seen or seen[-1][0] != t):
                seen.append((t, (*np.round(q, 9), round(thrust, 9))))
            await asyncio.sleep(0.01)

    reason, folder, summary = run_flight(cfg, alongside=watch)
    assert reason is Reason.OK, summary
    f = read_flight(folder)
    ev = f["events"]
    t_started = next(float(t) for t, x in zip(ev["t"], ev["text"], strict=True) if x == "link offboard_started")
    t_engage = next(float(r["t"]) for r in f.states if r["to_state"] == "ENGAGE")
    sp = f["setpoints"]
    during = (sp["t"] >= t_engage) & (sp["t"] < t_started)
    # One setpoint per frame from the engagement's first: the stream waits 0.2 s before asking, so >= 5 frames.
    assert during.sum() >= 5, (during.sum(), t_started - t_engage)
    assert len(np.unique(np.round(sp["pitch_deg"][during], 6))) >= 3  # PN steered: not one setpoint repeated
    # And PX4 received them: several different setpoints arrived before the app saw OFFBOARD (old: only the first,
    # resent by MAVSDK).
    assert len({v for _, v in seen}) >= 3, seen
