"""The pull-up before a target (``app.on_close: pull_up``): when to pull up, and the manoeuvre flown. Pure.

The paper's end-to-end experiment flies at a truck and pulls up right before impact. A pull-up fired on the
gate pass's time-to-contact (0.25 s) leaves nothing to climb or brake with (0 of 60 cleared), so the decision
is made from what the vehicle can do:

* **the situation** from the image: the range from the target's configured size and the box
  (``range = f * size / pixels``, the larger of the width and height estimates: a cut box reads far, which
  only fires earlier), the closing speed = range / time-to-contact (the box's expansion,
  companion/limits.py CloseDetector), the height above the target's centre from the filtered LOS, and the
  climb rate from the barometer (or, without it, the LOS: the vehicle flies along it);
* **the manoeuvre**: after ``response`` s (attitude and thrust lag, frame latency) at the current velocity,
  full thrust ``f_max`` tilted back by ``tilt`` (brakes ``f_max sin tilt``, climbs ``f_max cos tilt - g``);
  closed form for the horizontal gap (when the vehicle is over the target's plane, or how short of it it
  stops) and the height then. The tilt is the best of a few up to ``app.pull_up_pitch`` (and the envelope);
* **the decision**: pull up when the best manoeuvre started ``lead`` later (the next frames) would clear the
  target's top by less than ``app.pull_up_margin``, or when the sink could no longer be arrested above the
  altitude floor: the planned pull-up is the floor's look-ahead (:func:`arrest_loss`, used by
  companion/limits.py SafetyLimits.floor), so a target standing on the ground is engaged down to where the
  pull-up must begin, not forbidden by a 1 s look-ahead at the dive's sink rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from companion.frames import R_from_euler_ned_deg, R_from_quat_wxyz
from companion.guidance import Setpoint

if TYPE_CHECKING:
    from companion.config import Config
    from perception.los import CameraModel
    from perception.types import BoundingBox

G = 9.81
FLOOR_MARGIN = 0.3  # m kept above the altitude floor by the planned sink arrest (baro noise, model error)
PERSIST = 2  # frames in a row the decision must say "now": one noisy time-to-contact is not a contact


@dataclass(frozen=True, slots=True)
class PullUpParams:
    f_max: float  # m/s^2, the largest mass-normalised thrust
    max_tilt: float  # rad, the largest tilt back (app.pull_up_pitch, within airframe.max_tilt)
    response: float  # s from the decision until the vehicle accelerates as planned
    width: float  # m, the target's size
    height: float
    margin: float  # m over the target's top
    fx: float  # px, focal lengths
    fy: float
    floor: float  # m, the altitude floor (baro above take-off)
    frame_dt: float  # s, the camera's frame period
    image_w: int = 640  # px
    image_h: int = 480

    @classmethod
    def from_config(cls, cfg: Config, f_max: float | None = None) -> PullUpParams:
        a = cfg.app
        r = cfg.guidance.gate_radius
        w = a.target_width if a.target_width > 0 else 2.0 * r
        h = a.target_height if a.target_height > 0 else w
        tilt = math.radians(min(a.pull_up_pitch, cfg.airframe.max_tilt))
        k = np.asarray(cfg.camera.K, float)
        return cls(cfg.airframe.f_max if f_max is None else f_max, tilt, a.pull_up_response, w, h,
                   a.pull_up_margin, float(k[0, 0]), float(k[1, 1]), cfg.safety.altitude_floor,
                   1.0 / cfg.camera.rate, cfg.camera.width, cfg.camera.height)

    @property
    def climb_accel(self) -> float:
        """m/s^2 upwards at full thrust, level."""
        return self.f_max - G


@dataclass(frozen=True, slots=True)
class Situation:
    """The geometry relative to the target, from the image (no truth)."""

    ttc: float  # s
    range: float  # m
    gap: float  # m, horizontal distance to the target's plane
    closing: float  # m/s, horizontal closing speed
    above: float  # m, the vehicle above the target's centre
    climb_rate: float  # m/s, up positive


@dataclass(frozen=True, slots=True)
class Manoeuvre:
    tilt: float  # rad back
    clearance: float  # m: over the top when over the target's plane, or the gap where the vehicle stops short
    t_over: float  # s from the decision to over the plane (inf: stops short)


CUT_PX = 3.0  # a box edge this close to the image border is cut (as companion/engagement.py cut_edge_px)


def cut_axes(box: BoundingBox, width: int, height: int) -> tuple[bool, bool]:
    """(width cut, height cut): the box touches a left/right or a top/bottom image border."""
    x0, y0, x1, y1 = box.xyxy
    return x0 <= CUT_PX or x1 >= width - CUT_PX, y0 <= CUT_PX or y1 >= height - CUT_PX


class Expansion:
    """Time-to-contact from the box's width and height separately, each only from frames where it is not cut by
    the image border: the close detector's larger side switches from a cut (stuck) height to the growing width
    as a target reaches the border, and its time-to-contact jumps up (a 2.5 x 3 m target read 3 s at 11 m)."""

    WINDOW_S = 0.3

    def __init__(self) -> None:
        self._w: list[tuple[float, float]] = []
        self._h: list[tuple[float, float]] = []

    def reset(self) -> None:
        self._w.clear()
        self._h.clear()

    def update(self, t: float, size: Size | None) -> float:
        """The smaller of the two sides' times-to-contact (inf when neither has a full window)."""
        if size is not None:
            if not size.cut_w:
                self._w.append((t, size.w))
            if not size.cut_h:
                self._h.append((t, size.h))
        return min(self._ttc(self._w, t), self._ttc(self._h, t))

    def _ttc(self, hist: list[tuple[float, float]], now: float) -> float:
        while hist and now - hist[0][0] > self.WINDOW_S:
            hist.pop(0)
        if len(hist) < 5 or hist[-1][0] - hist[0][0] < 0.6 * self.WINDOW_S or now - hist[-1][0] > 0.1:
            return math.inf
        t = np.array([a for a, _ in hist])
        v = np.array([b for _, b in hist])
        tm = float(t.mean())
        slope = float((t - tm) @ (v - v.mean())) / float((t - tm) @ (t - tm))
        if slope <= 0.0:
            return math.inf
        return max(0.0, float(v.mean()) / slope - (now - tm))


@dataclass(frozen=True, slots=True)
class Size:
    """The box's width and height as the target's angular size, in pixels of the image centre (f tan), and
    which of them the image border cuts. Angles, not pixels: a box near the image's edge is stretched by the
    projection, and the attitude swings at the engagement's start read as an expansion (a 31 m target
    "closing at 30 m/s" 0.2 s after engaging)."""

    w: float
    h: float
    cut_w: bool
    cut_h: bool


def image_roll(q_wxyz_ned_frd: np.ndarray, camera: CameraModel) -> float:
    """rad: how far the image is rolled from the horizon (the world's down direction against the image's)."""
    R = R_from_quat_wxyz(q_wxyz_ned_frd) @ camera.R_body_cam  # camera -> NED
    down = R.T @ np.array([0.0, 0.0, 1.0])  # world down in the camera frame (OpenCV: y down)
    return math.atan2(float(down[0]), float(down[1]))


def box_size(box: BoundingBox, p: PullUpParams, camera: CameraModel | None, roll: float = 0.0) -> Size:
    """The target's angular width and height from its box. With the image rolled by ``roll`` an upright W x H
    rectangle's axis-aligned box is W cos + H sin wide and W sin + H cos high: each side is turned back into the
    target's own width (height) with the known aspect, or a bank reads as an expansion (on PX4 SIH a banked start
    read a receding target 46 m away as closing at 36 m/s)."""
    cw, ch = cut_axes(box, p.image_w, p.image_h)
    c, sn, k = abs(math.cos(roll)), abs(math.sin(roll)), p.height / p.width
    if camera is None:
        w, h = box.w, box.h
    else:
        x0, y0, x1, y1 = box.xyxy

        def span(a: tuple[float, float], b: tuple[float, float], f: float) -> float:
            cosang = float(np.clip(camera.ray_cam(*a) @ camera.ray_cam(*b), -1.0, 1.0))
            return 2.0 * f * math.tan(0.5 * math.acos(cosang))

        w, h = span((x0, box.cy), (x1, box.cy), p.fx), span((box.cx, y0), (box.cx, y1), p.fy)
    return Size(w / (c + k * sn), k * h / (sn + k * c), cw, ch)


def situation(size: Size, ttc: float, los_enu: np.ndarray | None, climb_rate: float | None,
              p: PullUpParams) -> Situation | None:
    """The situation, or None when the image cannot tell (no expansion yet, no LOS)."""
    if not (math.isfinite(ttc) and ttc > 0.0) or los_enu is None or size.w <= 1.0 or size.h <= 1.0:
        return None
    # A cut side reads the target farther than it is: use the whole one(s); both cut, the larger estimate.
    ests = [e for e, cut in ((p.fx * p.width / size.w, size.cut_w), (p.fy * p.height / size.h, size.cut_h))
            if not cut]
    rng = max(ests) if ests else max(p.fx * p.width / size.w, p.fy * p.height / size.h)
    los = np.asarray(los_enu, float) / float(np.linalg.norm(los_enu))
    horiz = math.sqrt(max(1e-6, 1.0 - los[2] ** 2))
    gap = rng * horiz
    vz = climb_rate if climb_rate is not None and math.isfinite(climb_rate) else rng / ttc * float(los[2])
    return Situation(ttc, rng, gap, gap / ttc, -rng * float(los[2]), vz)


def _track(s: Situation, tilt: float, t0: float, p: PullUpParams, t: float) -> tuple[float, float]:
    """(horizontal gap, height above the centre) t s after the decision, the manoeuvre acting from t0."""
    ax, az = p.f_max * math.sin(tilt), p.f_max * math.cos(tilt) - G
    u = max(0.0, t - t0)
    return (s.gap - s.closing * t + 0.5 * ax * u * u, s.above + s.climb_rate * t + 0.5 * az * u * u)


def fly(s: Situation, tilt: float, delay: float, p: PullUpParams, samples: int = 16) -> Manoeuvre:
    """The planned pull-up started ``delay`` s from now (closed form, point mass, drag ignored: it only helps).

    The clearance is the least distance between the planned track and the target's edge (the plate seen edge-on:
    the segment of the target's height at gap 0) up to the moment the vehicle is over the target's plane, or
    stops short of it."""
    t0 = delay + p.response
    ax = p.f_max * math.sin(tilt)
    top = 0.5 * p.height
    closing = max(s.closing, 1e-9)
    if s.gap <= closing * t0:  # over the plane before the manoeuvre acts
        t_end = t_over = s.gap / closing
    else:
        g0 = s.gap - closing * t0
        if ax <= 1e-9:
            t_over = t0 + g0 / closing
            t_end = t_over
        else:
            disc = closing**2 - 2.0 * ax * g0
            t_over = math.inf if disc < 0.0 else t0 + (closing - math.sqrt(disc)) / ax
            t_end = t0 + closing / ax if disc < 0.0 else t_over  # braked to a stop short of the plane
    clear = math.inf
    for k in range(samples + 1):
        gap, z = _track(s, tilt, t0, p, t_end * k / samples)
        gap = max(gap, 0.0)
        clear = min(clear, math.hypot(gap, z - top) if z > top else (gap if z >= -top else math.hypot(gap, z + top)))
    return Manoeuvre(tilt, clear, t_over)


def best(s: Situation, delay: float, p: PullUpParams, n: int = 6) -> Manoeuvre:
    """The tilt (0 .. max_tilt, n steps) that clears the top by the most."""
    tilts = [p.max_tilt * k / (n - 1) for k in range(n)] if n > 1 else [0.0]
    return max((fly(s, a, delay, p) for a in tilts), key=lambda m: m.clearance)


def arrest_loss(climb_rate: float, delay: float, p: PullUpParams, elapsed: float = 0.0) -> float:
    """Height lost (m, >= 0) before a sink is arrested by a pull-up started ``delay`` s from now at full thrust,
    level: the floor's look-ahead while a pull-up is planned. ``elapsed``: s since a pull-up began (its response
    is partly over: counting all of it again tripped the floor 4 frames into pull-ups that bottomed out above it)."""
    sink = max(0.0, -climb_rate)
    return sink * (delay + max(0.0, p.response - elapsed)) + sink * sink / (2.0 * max(p.climb_accel, 0.1))


@dataclass(frozen=True, slots=True)
class Fire:
    why: str
    tilt: float  # rad back
    duration: float  # s of full-thrust pull-up


class PullUpPlanner:
    """Per engagement: each frame of ENGAGE, "pull up now?"; then the pull-up's setpoints."""

    def __init__(self, params: PullUpParams, camera: CameraModel | None = None) -> None:
        self.p = params
        self.camera = camera  # box -> angular size (None: pixels, a pinhole near the image centre)
        self._count = 0
        self.last: Manoeuvre | None = None
        self.fired: Fire | None = None
        self.t_fire = 0.0
        self.levelled = False  # the engagement has levelled the vehicle after the flown pull-up
        self.expansion = Expansion()

    def reset(self) -> None:
        self.expansion.reset()
        self._count = 0
        self.last = None
        self.fired = None
        self.levelled = False

    def decide(self, t: float, box: BoundingBox | None, ttc: float, los_enu: np.ndarray | None,
               altitude: float | None, climb_rate: float | None, q_wxyz_ned_frd: np.ndarray | None = None
               ) -> Fire | None:
        """A Fire when the pull-up must start now (for ``PERSIST`` frames in a row), else None. ``q``: the attitude
        at the frame (the image's roll), when known."""
        p = self.p
        lead = PERSIST * p.frame_dt  # the decision holds from the next frames on: plan as if started then
        why = ""
        m: Manoeuvre | None = None
        roll = image_roll(q_wxyz_ned_frd, self.camera) if q_wxyz_ned_frd is not None and self.camera else 0.0
        size = box_size(box, p, self.camera, roll) if box is not None else None
        own = self.expansion.update(t, size)
        ttc = own if math.isfinite(own) else ttc
        s = situation(size, ttc, los_enu, climb_rate, p) if size is not None else None
        if s is not None:
            m = best(s, lead, p)
            self.last = m
            if m.clearance < p.margin:
                why = (f"{s.range:.1f} m at {s.closing:.1f} m/s (time-to-contact {ttc:.2f} s): a pull-up later "
                       f"would clear the top by {m.clearance:.1f} m < {p.margin:.1f} m")
        if not why and altitude is not None and climb_rate is not None and math.isfinite(altitude):
            low = altitude - arrest_loss(climb_rate, lead, p)
            if low < p.floor + FLOOR_MARGIN:
                why = (f"sinking {-climb_rate:.1f} m/s at {altitude:.1f} m: a pull-up later would bottom out at "
                       f"{low:.1f} m, floor {p.floor:.1f} m")
        self._count = self._count + 1 if why else 0
        if self._count < PERSIST:
            return None
        tilt = m.tilt if m is not None else 0.0
        self.fired = Fire(why, tilt, self._duration(s, tilt, climb_rate))
        self.t_fire = t
        return self.fired

    def _duration(self, s: Situation | None, tilt: float, climb_rate: float | None) -> float:
        """s of full thrust: until the sink is arrested and (when the target is known) until the climb has
        gained the height over the top plus the margin, at most until over the target; then level (the climb
        rate carries on)."""
        p = self.p
        az = max(p.f_max * math.cos(tilt) - G, 0.1)
        vz = climb_rate if climb_rate is not None and math.isfinite(climb_rate) else 0.0
        t = p.response + max(0.0, -vz) / az
        if s is not None:
            need = 0.5 * p.height + p.margin - s.above  # height to gain over the centre
            # vz u + az u^2 / 2 = need (after the response at vz)
            need -= vz * p.response
            if need > 0.0:
                u = (-vz + math.sqrt(vz * vz + 2.0 * az * need)) / az
                t = max(t, p.response + u)
            if math.isfinite(self.last.t_over if self.last else math.inf):
                t = min(t, self.last.t_over + 0.3) if self.last else t
        return max(t, 0.5)

    def setpoint(self, t: float, yaw_deg: float, hover_thrust: float) -> Setpoint | None:
        """The pull-up's setpoint at t (nose up by the planned tilt, full thrust), None once it is flown."""
        f = self.fired
        if f is None or t - self.t_fire > f.duration:
            return None
        pitch = math.degrees(f.tilt)
        thrust = min(1.0, hover_thrust * self.p.f_max / G)
        return Setpoint(0.0, pitch, yaw_deg, thrust, R_from_euler_ned_deg(0.0, pitch, yaw_deg))
