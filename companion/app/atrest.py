"""Land only once PX4's Hold has brought the vehicle to rest.

Why: a hand-back comes at speed (a pass at 5-14 m/s), and PX4's Land, commanded at once, descends while it flies
back to where it was commanded. On PX4 SITL (SIH quad, a linear-slow gate, 2026-12-07) Land was commanded 0.4 s
after a hand-back at 12 m/s; the estimate's height being 1-3 m off, the vehicle met the ground while still flying
back at 5 m/s, braking 46 deg tilted: a tip-over on a real airframe, and on SIH every later take-off of that
instance stayed on the ground (the CI take-off failures of 2026-12-06/07).

At rest is judged from the attitude alone (already in the control loop; no position estimate, which indoors there
may be none): PX4 brakes by tilting against the motion, so a vehicle it holds level for ``hold_s`` has stopped.
Steady wind tilts a hovering vehicle too: after ``timeout`` the app lands anyway, as PX4's own Land would, and says
so.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from companion.vehicle import VehicleTelemetry


def tilt_of(R_ned_frd: np.ndarray) -> float:
    """rad between the body's down axis and the world's."""
    return math.acos(max(-1.0, min(1.0, float(R_ned_frd[2, 2]))))


@dataclass
class RestWatch:
    """Pure: ``update(t, R_ned_frd)`` is True once the tilt stayed within ``tilt_max`` for ``hold_s``."""

    tilt_max: float  # rad
    hold_s: float  # s
    since: float | None = None  # when the tilt last came within tilt_max
    tilt: float = math.nan  # rad, the last one seen

    def update(self, t: float, R_ned_frd: np.ndarray) -> bool:
        self.tilt = tilt_of(R_ned_frd)
        if self.tilt > self.tilt_max:
            self.since = None
            return False
        if self.since is None:
            self.since = t
        return t - self.since >= self.hold_s


async def wait_at_rest(link: VehicleTelemetry, tilt_max_deg: float, hold_s: float, timeout: float,
                       clock: Callable[[], float] = time.monotonic, poll: float = 0.05) -> tuple[bool, str]:
    """Wait until PX4 holds the vehicle level (see the module's note), at most ``timeout`` s: (held level, what
    happened for the log). Level, not "at rest": a draggy airframe drifts on with PX4 holding it nearly level. A lost
    link raises (``link.check_link``), as in every other wait of a flight."""
    watch = RestWatch(math.radians(tilt_max_deg), hold_s)
    t0 = clock()
    while True:
        a = link.attitude
        now = clock()
        if a is not None and watch.update(now, a.R_ned_frd):
            return True, (f"held level {now - t0:.1f} s after the hand-back (tilt {math.degrees(watch.tilt):.1f} "
                          f"deg, within {tilt_max_deg:g} deg for {hold_s:g} s)")
        if now - t0 >= timeout:
            seen = "no attitude" if a is None else f"tilt {math.degrees(watch.tilt):.1f} deg"
            return False, f"not level {timeout:g} s after the hand-back ({seen}); landing anyway"
        link.check_link()
        await asyncio.sleep(poll)
