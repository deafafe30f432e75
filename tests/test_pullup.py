"""The pull-up planner (companion/pullup.py) and the altitude floor with a planned pull-up (companion/limits.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import Config
from companion.limits import SafetyLimits
from companion.pullup import (
    Expansion,
    G,
    PullUpParams,
    PullUpPlanner,
    Situation,
    Size,
    arrest_loss,
    box_size,
    fly,
    situation,
)
from perception.types import BoundingBox

P = PullUpParams(f_max=2.0 * G, max_tilt=math.radians(25.0), response=0.35, width=2.5, height=3.0, margin=1.5,
                 fx=500.0, fy=500.0, floor=2.0, frame_dt=1 / 30)


def _integrate(s: Situation, tilt: float, delay: float, p: PullUpParams) -> float:
    """Independent check: Euler-integrate the same point mass at 0.1 ms, least distance to the plate's edge."""
    dt = 1e-4
    x, z, vx, vz = s.gap, s.above, -s.closing, s.climb_rate
    t, best = 0.0, math.inf
    top = 0.5 * p.height
    while True:
        d = math.hypot(max(x, 0.0), max(z - top, 0.0)) if z > top else (max(x, 0.0) if z >= -top else math.inf)
        best = min(best, d)
        if x <= 0.0 or vx >= 0.0 or t > 10.0:
            return best
        if t >= delay + p.response:
            vx += p.f_max * math.sin(tilt) * dt
            vz += (p.f_max * math.cos(tilt) - G) * dt
        x += vx * dt
        z += vz * dt
        t += dt


@pytest.mark.parametrize("gap,closing,above,climb,tilt", [
    (11.0, 11.0, 0.0, 0.0, 0.0), (11.0, 11.0, 0.0, 0.0, math.radians(25)), (8.0, 12.0, 1.0, -2.0, 0.2),
    (20.0, 6.0, -0.5, -1.0, 0.4), (3.0, 12.0, 0.0, 0.0, 0.0)])
def test_fly_matches_integration(gap: float, closing: float, above: float, climb: float, tilt: float) -> None:
    s = Situation(gap / closing, gap, gap, closing, above, climb)
    m = fly(s, tilt, 0.05, P, samples=400)
    assert m.clearance == pytest.approx(_integrate(s, tilt, 0.05, P), abs=0.03)


def test_todays_trigger_is_too_late_and_the_planner_fires_in_time() -> None:
    """The gate pass's time-to-contact of 0.25 s (the old pull-up trigger) leaves no clearance; the planner fires
    while the best pull-up still clears the top by the margin."""
    closing = 11.0
    late = Situation(0.25, 0.25 * closing, 0.25 * closing, closing, 0.0, 0.0)
    assert max(fly(late, a, 0.0, P).clearance for a in (0.0, 0.2, 0.4)) < 0.2
    planner = PullUpPlanner(P)
    fired_at = None
    for k in range(120):  # a 2.5 x 3 m target closing from 40 m at 11 m/s, level, on the LOS
        t = k / 30
        rng = 40.0 - closing * t
        b = BoundingBox(320, 240, P.fx * 2.5 / rng, P.fy * 3.0 / rng, 0.9, t)
        ttc = rng / closing
        if planner.decide(t, b, ttc, np.array([1.0, 0.0, 0.0]), 10.0, 0.0) is not None:
            fired_at = rng
            break
    assert fired_at is not None and fired_at > 0.25 * closing + 5.0
    s = situation(Size(P.fx * 2.5 / fired_at, P.fy * 3.0 / fired_at, False, False), fired_at / closing,
                  np.array([1.0, 0.0, 0.0]), 0.0, P)
    assert s is not None and s.range == pytest.approx(fired_at)
    assert fly(s, planner.fired.tilt, 0.0, P).clearance >= P.margin - 0.3  # fired at most a frame late


def test_expansion_ignores_a_cut_side() -> None:
    """A box cut by the top border: its height is stuck, its width grows; the time-to-contact is the width's."""
    e = Expansion()
    ttc = math.inf
    for k in range(12):
        t = k / 30
        rng = 12.0 - 10.0 * t
        w = 500 * 2.5 / rng
        ttc = e.update(t, box_size(BoundingBox.from_xyxy(320 - w / 2, 0.0, 320 + w / 2, 200.0, 0.9, t), P, None))
    assert ttc == pytest.approx((12.0 - 10.0 * 11 / 30) / 10.0, rel=0.1)


def _feed(lim: SafetyLimits, alt_end: float, rate: float, arrest) -> object:
    """Half a second of samples ending at alt_end; the first abort, if any."""
    for k in range(16):
        out = lim.floor(k / 30, alt_end + rate * (k - 15) / 30, arrest)
        if out is not None:
            return out
    return None


def test_floor_with_a_planned_pull_up() -> None:
    """Sinking 4 m/s at 5 m: the 1 s look-ahead trips (a dive at a ground target is forbidden); with the pull-up
    planned the floor uses the altitude after its sink arrest (4 x 0.35 + 16 / (2 x 9.81) = 2.2 m lost: 2.8 m, above
    the 2 m floor) and lets the engagement go on; at 4 m the arrest would bottom out at 1.8 m: it trips."""
    cfg = Config()
    arrest = lambda rate: arrest_loss(rate, 0.0, P)  # noqa: E731
    assert arrest(-4.0) == pytest.approx(4.0 * 0.35 + 16.0 / (2 * G))
    # Into a pull-up, only the response still to come counts (0.1 s in: 0.25 s of it left; all of it: none).
    assert arrest_loss(-4.0, 0.0, P, elapsed=0.1) == pytest.approx(4.0 * 0.25 + 16.0 / (2 * G))
    assert arrest_loss(-4.0, 0.0, P, elapsed=1.0) == pytest.approx(16.0 / (2 * G))
    assert arrest_loss(2.0, 0.0, P) == 0.0  # climbing: nothing to arrest
    assert _feed(SafetyLimits(cfg.safety), 5.0, -4.0, None) is not None
    assert _feed(SafetyLimits(cfg.safety), 5.0, -4.0, arrest) is None
    low = _feed(SafetyLimits(cfg.safety), 4.0, -4.0, arrest)
    assert low is not None and "pull-up" in low.detail
    assert _feed(SafetyLimits(cfg.safety), 1.9, 0.0, arrest) is not None  # below the floor: always


def test_angular_size_does_not_grow_with_the_attitude() -> None:
    """The same target (its rays fixed) seen at the image centre and near the corner after a rotation: the pixel
    box grows (the projection stretches it), the angular size does not."""
    from companion.config import CameraConfig
    from perception.los import CameraModel

    cam = CameraModel.from_config(CameraConfig())
    f = float(cam.K[0, 0])
    p = PullUpParams(P.f_max, P.max_tilt, P.response, P.width, P.height, P.margin, f, f, P.floor, P.frame_dt)
    half = math.atan(1.25 / 20.0)  # a 2.5 m wide target at 20 m

    def box_at(yaw: float) -> BoundingBox:
        u = [cam.K[0, 2] + f * math.tan(yaw + s * half) for s in (-1, 1)]
        return BoundingBox.from_xyxy(u[0], 230.0, u[1], 250.0, 0.9, 0.0)

    centre, edge = box_at(0.0), box_at(math.radians(28.0))
    assert edge.w > 1.1 * centre.w
    assert box_size(edge, p, cam).w == pytest.approx(box_size(centre, p, cam).w, rel=1e-6)
    assert box_size(centre, p, cam).w == pytest.approx(2 * f * math.tan(half), rel=1e-6)


def test_a_banked_image_is_not_an_expansion() -> None:
    """A 2.5 x 3 m rectangle 20 m away seen with the image rolled 20 deg: its axis-aligned box is W cos + H sin
    wide and W sin + H cos high (larger than level); turned back, the sizes are the level ones."""
    from companion.config import CameraConfig
    from companion.frames import R_from_euler_ned_deg, quat_wxyz_from_R
    from companion.pullup import image_roll
    from perception.los import CameraModel

    cam = CameraModel.from_config(CameraConfig())
    roll = image_roll(quat_wxyz_from_R(R_from_euler_ned_deg(20.0, 0.0, 0.0)), cam)
    assert abs(roll) == pytest.approx(math.radians(20.0), abs=1e-9)
    c, s = math.cos(roll), abs(math.sin(roll))
    w, h = P.fx * 2.5 / 20.0, P.fy * 3.0 / 20.0
    level = box_size(BoundingBox(320, 240, w, h, 0.9, 0.0), P, None)
    banked = box_size(BoundingBox(320, 240, w * c + h * s, w * s + h * c, 0.9, 0.0), P, None, roll)
    assert (banked.w, banked.h) == pytest.approx((level.w, level.h), rel=1e-9)
    assert (level.w, level.h) == pytest.approx((w, h), rel=1e-9)
