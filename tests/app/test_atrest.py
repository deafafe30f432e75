"""Land only at rest (companion/app/atrest.py): the tilt rule, and the wait on a link's attitude stream."""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from companion.app.atrest import RestWatch, tilt_of, wait_at_rest
from companion.app.linkerrors import LinkLost


def R_tilted(roll_deg: float, pitch_deg: float, yaw_deg: float = 0.0) -> np.ndarray:
    return Rotation.from_euler("ZYX", [yaw_deg, pitch_deg, roll_deg], degrees=True).as_matrix()


def test_tilt_is_the_angle_between_body_down_and_world_down() -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        roll, pitch, yaw = rng.uniform(-80, 80), rng.uniform(-80, 80), rng.uniform(-180, 180)
        R = R_tilted(roll, pitch, yaw)
        down_body_in_world = R @ np.array([0.0, 0.0, 1.0])
        expect = math.degrees(math.acos(np.clip(down_body_in_world @ np.array([0.0, 0.0, 1.0]), -1, 1)))
        assert math.degrees(tilt_of(R)) == pytest.approx(expect, abs=1e-9)
    assert math.degrees(tilt_of(R_tilted(180.0, 0.0))) == pytest.approx(180.0)  # upside down, not level


def test_rest_needs_the_whole_hold_time_level_and_restarts_on_a_tilt() -> None:
    w = RestWatch(math.radians(5.0), hold_s=1.0)
    # braking 15 deg nose-up for 2 s, then level with one 6 deg swing at 2.5 s
    seq = [(t, 15.0 if t < 2.0 else (6.0 if abs(t - 2.5) < 1e-9 else 1.0)) for t in np.arange(0.0, 4.01, 0.1)]
    first = next(t for t, pitch in seq if w.update(t, R_tilted(0.0, pitch, 90.0)))
    assert first == pytest.approx(3.6)  # level from 2.6 s (after the swing), for 1.0 s
    assert not RestWatch(math.radians(5.0), 1.0).update(0.0, R_tilted(0.0, 10.0))
    assert RestWatch(math.radians(5.0), 0.0).update(0.0, R_tilted(3.0, 3.0))  # hold 0: level now is enough


@dataclass
class _Att:
    R_ned_frd: np.ndarray


class _Telemetry:
    """The part of the link wait_at_rest reads, on a scripted clock: tilt(t) deg, or None (no attitude)."""

    def __init__(self, tilt, lost_after: float = math.inf) -> None:
        self.t, self.tilt, self.lost_after = 0.0, tilt, lost_after

    def clock(self) -> float:
        self.t += 0.05
        return self.t

    @property
    def attitude(self) -> _Att | None:
        d = self.tilt(self.t)
        return None if d is None else _Att(R_tilted(d, 0.0))

    def check_link(self) -> None:
        if self.t > self.lost_after:
            raise LinkLost("telemetry lost (test)")


def _wait(tel: _Telemetry, timeout: float = 15.0) -> tuple[bool, str]:
    return asyncio.run(wait_at_rest(tel, 5.0, 1.0, timeout, clock=tel.clock, poll=0.0))  # type: ignore[arg-type]


def test_waits_for_the_brake_to_end() -> None:
    tel = _Telemetry(lambda t: 20.0 if t < 3.0 else 0.5)
    level, said = _wait(tel)
    # level from 3 s, held 1 s
    assert level and said.startswith("held level") and 4.0 <= tel.t <= 4.0 + 3 * 0.05, (said, tel.t)


def test_lands_anyway_after_the_timeout_and_says_why() -> None:
    tel = _Telemetry(lambda t: 8.0)  # a steady 8 deg (wind)
    level, said = _wait(tel, timeout=5.0)
    assert not level and said == "not level 5 s after the hand-back (tilt 8.0 deg); landing anyway", said
    assert 5.0 <= tel.t <= 5.1
    assert _wait(_Telemetry(lambda t: None), timeout=1.0) == (False, "not level 1 s after the hand-back (no "
                                                             "attitude); landing anyway")


def test_a_lost_link_is_raised_not_waited_out() -> None:
    with pytest.raises(LinkLost):
        _wait(_Telemetry(lambda t: 20.0, lost_after=2.0))
