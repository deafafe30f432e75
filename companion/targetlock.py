"""Is this box still the gate we engaged? Pure, per frame, from the box, the attitude and time only.

Why: on real PX4 (Table I, rendered frames through the shipped detector) 7 of 12 failed x500 runs had engaged
the gate correctly and then received, after a frame or two without a box, a box of something else: 4-11 times
the gate's size and tens of degrees away (background clutter). The controller steered at it and the close
detector took its size for the gate come near: "gate passed" 22-24 m before the gate. Whatever the perception
stage does (its own tracker, another tracker, a user's detector), the engagement must not take a box of another
object for the engaged gate.

A box continues the engaged target when, against the last box that did (``ref``):

* its size is one an approach explains: a ring of radius ``r`` seen ``s`` px wide is ``d = 2 f r / s`` away;
  closing at most ``v_max`` for ``dt`` it grows at most ``d / (d - v_max dt)`` (unbounded once ``v_max dt``
  reaches ``d``), times ``size_jitter`` for the detector's frame-to-frame noise; the same bound applies to a
  shrink (a ring turning edge-on, a box cut by the border). Without a gate size (``gate_radius`` 0) the growth
  bound is ``exp(max_growth_rate dt)``.
* its world-frame line of sight is within ``los_floor`` + half the reference box's angular size +
  ``rate dt`` of the reference's (the world LOS, so the vehicle's own rotation does not count), the rate being
  the LOS filter's limit ``max_los_rate`` or, near the gate, ``v_max / d`` for the least range ``d`` an approach
  leaves.

Anything else counts as no box: the controller coasts on its filter and the target-lost timeout runs, so a
target that really changed is an abort (TARGET_LOST), never a flight at another object. The bounds widen with
the time since the last good box, so the gate itself, found again after a gap, is taken back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from perception.fastinit import fast_init
from perception.los import CameraModel, los_world
from perception.types import BoundingBox


@dataclass(frozen=True, slots=True)
class LockParams:
    v_max: float  # m/s, the largest closing speed (guidance.v_rel_bar)
    gate_radius: float  # m; 0 = unknown (growth-rate bound instead)
    max_los_rate: float  # rad/s (los_filter.max_rate: faster is a jump for the LOS filter too)
    max_growth_rate: float = 4.0  # 1/s, box growth without a gate size (a time-to-contact of 0.25 s)
    size_jitter: float = 1.5  # frame-to-frame size noise of a detector (ring tilt, cut edges)
    los_floor: float = math.radians(8.0)  # rad: attitude error and timing (a 300 deg/s swing x 20 ms = 6 deg)


@fast_init
@dataclass(frozen=True, slots=True)
class LockCheck:
    ok: bool
    why: str = ""


class TargetLock:
    """``check(t, box, R_ned_frd)`` per frame of an engagement; ``reset()`` when a new target is engaged."""

    def __init__(self, params: LockParams, camera: CameraModel) -> None:
        self.p = params
        self.camera = camera
        self.rejected = 0  # boxes rejected since the last reset
        self.reset()

    def reset(self) -> None:
        self._ref: tuple[float, float, np.ndarray] | None = None  # (t, size px, world LOS)
        self.rejected = 0

    def size_bound(self, size_ref: float, dt: float) -> float:
        """The largest size ratio (either way) an approach explains in ``dt`` from a box ``size_ref`` px wide."""
        p = self.p
        dt = max(dt, 0.0)
        if p.gate_radius > 0.0:
            d = 2.0 * float(self.camera.K[0, 0]) * p.gate_radius / max(size_ref, 1e-6)
            close = p.v_max * dt
            growth = math.inf if close >= d else d / (d - close)
        else:
            growth = math.exp(min(p.max_growth_rate * dt, 50.0))
        return p.size_jitter * growth

    def angle_bound(self, size_ref: float, dt: float) -> float:
        """The largest world-LOS change in ``dt`` from a box ``size_ref`` px wide: the LOS filter's rate limit, or
        near the gate ``v_max / d`` (d the least range an approach leaves), whichever is larger."""
        p = self.p
        f = float(self.camera.K[0, 0])
        dt = max(dt, 0.0)
        rate = p.max_los_rate
        if p.gate_radius > 0.0:
            d_min = 2.0 * f * p.gate_radius / max(size_ref, 1e-6) - p.v_max * dt
            rate = math.inf if d_min <= 0.0 else max(rate, p.v_max / d_min)
        return min(math.pi, p.los_floor + math.atan(0.5 * size_ref / f) + rate * dt)

    def check(self, t: float, box: BoundingBox, R_ned_frd: np.ndarray) -> LockCheck:
        """Does ``box`` (captured at ``t``, attitude ``R_ned_frd`` then) continue the engaged target? A box that
        does becomes the reference."""
        size = max(box.w, box.h)
        los = los_world(self.camera, box.cx, box.cy, R_ned_frd)
        if self._ref is None:
            self._ref = (t, size, los)
            return LockCheck(True)
        t_ref, s_ref, l_ref = self._ref
        dt = t - t_ref
        ratio = size / max(s_ref, 1e-6)
        bound = self.size_bound(s_ref, dt)
        if max(ratio, 1.0 / max(ratio, 1e-9)) > bound:
            return self._reject(f"box {size:.0f} px vs {s_ref:.0f} px {dt:.2f} s before (an approach explains "
                                f"x{bound:.2f} at most)")
        ang = math.acos(max(-1.0, min(1.0, float(l_ref.dot(los)))))
        a_max = self.angle_bound(s_ref, dt)
        if ang > a_max:
            return self._reject(f"line of sight {math.degrees(ang):.0f} deg from the gate's {dt:.2f} s before "
                                f"(at most {math.degrees(a_max):.0f} deg)")
        self._ref = (t, size, los)
        return LockCheck(True)

    def _reject(self, why: str) -> LockCheck:
        self.rejected += 1
        return LockCheck(False, f"not the engaged gate: {why}")
