"""Is this box still the gate we engaged? Pure, per frame, from the box, the attitude and time only.

Why: on real PX4 (Table I, rendered frames through the shipped detector) 7 of 12 failed x500 runs had engaged
the gate correctly and then received, after a frame or two without a box, a box of something else: 4-11 times
the gate's size and tens of degrees away (background clutter). The controller steered at it and the close
detector took its size for the gate come near: "gate passed" 22-24 m before the gate. Whatever the perception
stage does (its own tracker, another tracker, a user's detector), the engagement must not take a box of another
object for the engaged gate.

A box continues the engaged target when, against the last box that did (``ref``):

* its size is one an approach explains: a ring of radius ``r`` seen ``s`` px wide is ``d = 2 f r / s`` away;
  closing at most ``v`` for ``dt`` it grows at most ``d / (d - v dt)`` (unbounded once ``v dt`` reaches
  ``d``), times ``size_jitter`` for the detector's frame-to-frame noise. ``v`` is ``v_max``, or, when the caller
  passes the closing-speed filter's range rate and its standard deviation (companion/closing.py, driven by the
  IMU through a gap), its upper value ``max(0, -d_dot) + speed_sigmas sigma`` (the larger of the one at the
  reference box and the one now, never above ``v_max``). A shrink (a ring turning edge-on, a box cut by the
  border) is bounded the same way with ``v_max`` always. Without a gate size (``gate_radius`` 0) the bound is
  ``exp(max_growth_rate dt)`` either way.
* it also grows no more than an approach explains from the boxes that continued the target in the last
  ``window_s`` (the median of what each explains: the detector's noise counted once, not compounded frame by
  frame, and one box drawn small does not refuse the ring). Found on real PX4 (SIH quad,
  linear-fast gate, 2026-12-07): the ring's box merged, over 6 frames, with background beside it, 103 -> 287 px
  in 0.18 s (x1.1-1.3 a frame, each within the frame-to-frame bound) while the true ring stayed ~110 px; its
  growth read as a time-to-contact of 0.18 s and the app claimed a pass 7.5 m from the gate.
* its world-frame line of sight is within ``los_floor`` + half the reference box's angular size +
  ``rate dt`` of the reference's (the world LOS, so the vehicle's own rotation does not count), the rate being
  the LOS filter's limit ``max_los_rate`` or, near the gate, ``v_max / d`` for the least range ``d`` an approach
  leaves.

Why the filter's speed: with ``v_max`` (15 m/s, the paper's bound for a fast x500) a gap of 0.96 s lets a gate
18 m away come to 3.8 m, so a box 7x the gate's passes. On real PX4 (SIH quad, 100 runs, 2026-12-06) a
linear-fast gate 53 px wide (18 m) slid out of view, and after 0.96 s a 154x335 px background box was taken for
it, flown at and claimed as passed about 11 m short of the gate; the filter had the vehicle closing at 3-4 m/s.

Anything else counts as no box: the controller coasts on its filter and the target-lost timeout runs, so a
target that really changed is an abort (TARGET_LOST), never a flight at another object. The bounds widen with
the time since the last good box, so the gate itself, found again after a gap, is taken back.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from perception.fastinit import fast_init
from perception.los import CameraModel, los_world
from perception.types import BoundingBox

if TYPE_CHECKING:
    from companion.config import Config


@dataclass(frozen=True, slots=True)
class LockParams:
    v_max: float  # m/s, the largest closing speed (guidance.v_rel_bar)
    gate_radius: float  # m; 0 = unknown (growth-rate bound instead)
    max_los_rate: float  # rad/s (los_filter.max_rate: faster is a jump for the LOS filter too)
    max_growth_rate: float = 4.0  # 1/s, box growth without a gate size (a time-to-contact of 0.25 s)
    size_jitter: float = 1.5  # frame-to-frame size noise of a detector (ring tilt, cut edges)
    los_floor: float = math.radians(8.0)  # rad: attitude error and timing (a 300 deg/s swing x 20 ms = 6 deg)
    speed_sigmas: float = 3.0  # the closing speed's upper value: the filter's estimate + this many std devs
    # s: growth is also bounded against every box that continued the target this long before. The detector's size
    # error (box / true box) between two frames <= 0.3 s apart, 40 real-PX4 SIH flights: in the 35 without a merge
    # p99.9 1.25x, at most 1.37x, within size_jitter; every pair beyond 1.4x was in the 5 with one.
    window_s: float = 0.3


@fast_init
@dataclass(frozen=True, slots=True)
class LockCheck:
    ok: bool
    why: str = ""


_OK = LockCheck(True)  # every accepted box's check (immutable): one object, not one a frame


class TargetLock:
    """``check(t, box, R_ned_frd)`` per frame of an engagement; ``reset()`` when a new target is engaged."""

    def __init__(self, params: LockParams, camera: CameraModel) -> None:
        self.p = params
        self.camera = camera
        self._f = float(camera.K[0, 0])  # px, the focal length (read every frame, up to a window's boxes a frame)
        self.rejected = 0  # boxes rejected since the last reset
        self.reset()

    @classmethod
    def from_config(cls, cfg: Config, camera: CameraModel) -> TargetLock:
        """The engagement's lock (guidance's v_rel_bar and gate radius, the LOS filter's rate limit), for the
        flight core and for whoever re-judges its logs (companion/logclutter.py)."""
        g = cfg.guidance
        return cls(LockParams(g.v_rel_bar, g.gate_radius, cfg.los_filter.max_rate,
                              float(cfg.perception.max_growth_rate)), camera)

    def reset(self) -> None:
        self._ref: tuple[float, float, np.ndarray, float] | None = None  # (t, size px, world LOS, closing m/s)
        self._recent: deque[tuple[float, float, float]] = deque()  # (t, size px, closing m/s), the last window_s
        self.rejected = 0

    @property
    def ref_los(self) -> np.ndarray | None:
        """The world LOS (NED unit vector) of the last box that continued the target, None after a reset."""
        return None if self._ref is None else self._ref[2]

    def closing_bound(self, closing: tuple[float, float] | None) -> float:
        """The largest closing speed (m/s) given the filter's (range rate, its std dev), or ``v_max`` without."""
        v_max = self.p.v_max
        if closing is None:
            return v_max
        d_dot, sigma = closing
        v = max(0.0, -d_dot) + self.p.speed_sigmas * max(sigma, 0.0)
        return v_max if not math.isfinite(v) else min(v_max, v)

    def size_bound(self, size_ref: float, dt: float, v: float | None = None) -> float:
        """The largest size ratio (either way) an approach explains in ``dt`` from a box ``size_ref`` px wide,
        closing at most ``v`` m/s (``v_max`` when None)."""
        p = self.p
        dt = max(dt, 0.0)
        if p.gate_radius > 0.0:
            d = 2.0 * self._f * p.gate_radius / max(size_ref, 1e-6)
            close = (p.v_max if v is None else v) * dt
            growth = math.inf if close >= d else d / (d - close)
        else:
            growth = math.exp(min(p.max_growth_rate * dt, 50.0))
        return p.size_jitter * growth

    def angle_bound(self, size_ref: float, dt: float, v: float | None = None) -> float:
        """The largest world-LOS change in ``dt`` from a box ``size_ref`` px wide: the LOS filter's rate limit, or
        near the gate ``v_max / d`` (d the least range closing at ``v`` leaves; the relative speed across the
        line of sight is bounded by ``v_max`` only), whichever is larger."""
        p = self.p
        f = self._f
        dt = max(dt, 0.0)
        rate = p.max_los_rate
        if p.gate_radius > 0.0:
            d_min = 2.0 * f * p.gate_radius / max(size_ref, 1e-6) - (p.v_max if v is None else v) * dt
            rate = math.inf if d_min <= 0.0 else max(rate, p.v_max / d_min)
        return min(math.pi, p.los_floor + math.atan(0.5 * size_ref / f) + rate * dt)

    def check(self, t: float, box: BoundingBox, R_ned_frd: np.ndarray,
              closing: tuple[float, float] | None = None) -> LockCheck:
        """Does ``box`` (captured at ``t``, attitude ``R_ned_frd`` then) continue the engaged target? A box that
        does becomes the reference. ``closing``: the closing-speed filter's (range rate m/s, its std dev m/s)
        as of the previous frame, None when there is none (the bounds use ``v_max``)."""
        size = max(box.w, box.h)
        los = los_world(self.camera, box.cx, box.cy, R_ned_frd)
        v_now = self.closing_bound(closing)
        if self._ref is None:
            self._ref = (t, size, los, v_now)
            self._remember(t, box, size, v_now)
            return _OK
        recent = self._recent
        while recent and t - recent[0][0] > self.p.window_s:
            recent.popleft()
        t_ref, s_ref, l_ref, v_ref = self._ref
        dt = t - t_ref
        v = max(v_ref, v_now)  # the speed may have grown in between: the IMU-driven filter says by how much
        ratio = size / max(s_ref, 1e-6)
        if ratio >= 1.0:
            bound = self.size_bound(s_ref, dt, v)
            if ratio > bound:
                return self._reject(f"box {size:.0f} px vs {s_ref:.0f} px {dt:.2f} s before (an approach at "
                                    f"{v:.1f} m/s explains x{bound:.2f} at most)")
            # Each bound is at least size_jitter x its box: within that of the window's smallest box, nothing to do.
            if recent and size > self.p.size_jitter * min(s_k for _, s_k, _ in recent):
                # The largest size each box of the window explains now; their median, so that one box the detector
                # drew small (a ring's box 0.66x its size for a frame, seen in process) does not refuse the ring.
                most = sorted((s_k * self.size_bound(s_k, t - t_k, max(v_k, v_now)), t_k, s_k, max(v_k, v_now))
                              for t_k, s_k, v_k in recent)
                cap, t_k, s_k, v_k = most[(len(most) - 1) // 2]
                if size > cap:
                    return self._reject(f"box {size:.0f} px vs {s_k:.0f} px {t - t_k:.2f} s before (the median of "
                                        f"the last {self.p.window_s:.1f} s; an approach at {v_k:.1f} m/s explains "
                                        f"x{cap / s_k:.2f} at most)")
        else:
            # A shrink also comes from a ring turning edge-on or leaving across a border, which no speed
            # bounds: it keeps the v_max bound.
            bound = self.size_bound(s_ref, dt)
            if 1.0 / max(ratio, 1e-9) > bound:
                return self._reject(f"box {size:.0f} px vs {s_ref:.0f} px {dt:.2f} s before (an approach explains "
                                    f"x{bound:.2f} at most)")
        ang = math.acos(max(-1.0, min(1.0, float(l_ref.dot(los)))))
        a_max = self.angle_bound(s_ref, dt, v)
        if ang > a_max:
            return self._reject(f"line of sight {math.degrees(ang):.0f} deg from the gate's {dt:.2f} s before "
                                f"(at most {math.degrees(a_max):.0f} deg)")
        self._ref = (t, size, los, v_now)
        self._remember(t, box, size, v_now)
        return _OK

    def _remember(self, t: float, box: BoundingBox, size: float, v: float) -> None:
        """A box that continued the target, for the window's growth bound; not one the image border cuts (the ring
        coming back into view grows by more than any approach)."""
        x0, y0, x1, y1 = box.xyxy
        cam, m = self.camera, 2.0
        if x0 > m and y0 > m and x1 < cam.width - m and y1 < cam.height - m:
            self._recent.append((t, size, v))

    def _reject(self, why: str) -> LockCheck:
        self.rejected += 1
        return LockCheck(False, f"not the engaged gate: {why}")
