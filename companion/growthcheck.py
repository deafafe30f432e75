"""Does the engaged box grow as our own acceleration towards it says a ring of the configured size must? Pure.

Why: on real PX4 SITL (SIH quad, 2026-12-07, run040 of seed 1) the app acquired an 85x90 px box of background
above a 40 px ring 25 m away, and flew at it for 3.6 s: the box kept its size while the vehicle accelerated to
7 m/s towards it. A ring of radius ``r`` seen ``s`` px wide is ``d = 2 f r / s`` away (85 px: 12 m); flying 10 m
towards it, its box must more than double. A far object's box (a wall, a cloud of texture, a disc behind the
ring) keeps its size: its true range is many times what its size says. Neither the shape and size rules (one
box) nor the target lock (a box against the previous ones) can see that; only our own motion can.

Model, from the engagement's start ``t0``: the range the box says, ``d_i = 2 f r / s_i`` (boxes not cut by the
border), against ``S_i``, the distance our own acceleration has moved us along the line of sight since ``t0``
(the accelerometer rotated to the world, gravity added back, integrated from zero to a velocity, whose part
along the box's line of sight is integrated to a distance). Two explanations, either of which passes the box:

* a gate that keeps its distance but for our motion, the vehicle starting from hover (the first engagement):
  ``k_static = (d_start - d_now) / S_now`` (medians of the first and of the last 5 boxes);
* a gate moving at any constant speed along the line of sight, from any starting speed:
  ``d_i = c0 + c1 (t_i - t0) - k S_i`` by least squares, ``k_moving = k``.

For the configured ring ``k`` is 1 (a gate ``x`` times larger than configured: ``1 / x``); for an object ``D`` m
away whose box says ``d`` it is ``d / D``. Judged while our own acceleration has moved us between ``min_push`` and
``max_push`` m (early: where the accelerometer's integral is good and a gate has had little time to move):
when both are below ``min_scale`` the box is not the configured target. Either alone refuses rings (on 50 real-PX4
SIH flights, 2026-12-07: a linear-fast gate recedes along the turning line of sight, ``k_static`` down to 0.15;
the fit's ``k_moving`` is unstable when the detector's box stalls for a few frames, down to -4); together the
least is 0.71 on the rings and 0.10 on the background box. Without acceleration (an engagement begun at
cruise) ``S`` stays small and nothing is judged. Once it fails the object stays refused for the engagement: the
caller counts it as no box (coast, then TARGET_LOST), never a pass.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from perception.los import CameraModel, los_world
from perception.types import BoundingBox

G = 9.81
_GRAVITY_NED = np.array([0.0, 0.0, G])  # m/s^2, added back to the accelerometer's specific force (world NED)


@dataclass(frozen=True, slots=True)
class GrowthParams:
    focal_px: float  # camera focal length, px
    gate_radius: float  # m; 0 = unknown: no check
    width: int  # image size, px
    height: int
    min_push: float = 4.0  # m our own acceleration must have moved us along the LOS before judging
    max_push: float = 10.0  # m: judged no more after it has moved us this far
    min_scale: float = 0.3  # k below this: not the configured target (a gate up to 1/this x the configured size passes)
    min_samples: int = 10  # uncut boxes in the fit at least
    edge_px: float = 3.0  # a box edge this near the border is cut: its size says no range
    max_dt: float = 0.5  # s; a longer gap between frames is not integrated across

    @classmethod
    def from_config(cls, cfg: object) -> GrowthParams:
        from companion.config import camera_model

        v = cfg.app.verify  # type: ignore[attr-defined]
        cam = camera_model(cfg.camera)  # type: ignore[attr-defined]
        return cls(float(cam.K[0, 0]), float(cfg.guidance.gate_radius), cam.width, cam.height,  # type: ignore
                   float(v.growth_min_push), float(v.growth_max_push), float(v.growth_min_scale))


class GrowthCheck:
    """``reset()`` when an engagement begins; ``update(...)`` every ENGAGE frame with the box the engagement
    would use; "" while the box may be the configured target, else why not (and from then on)."""

    def __init__(self, params: GrowthParams, camera: CameraModel) -> None:
        self.p = params
        self.camera = camera
        self.reset()

    def reset(self) -> None:
        self._t0: float | None = None
        self._t: float | None = None
        self._v = np.zeros(3)  # m/s, velocity our own acceleration added since t0 (world NED)
        self._s = 0.0  # m, distance it moved us
        self._a_prev: list[float] | None = None  # the last frame's a_ned, m/s^2
        self._l: np.ndarray | None = None  # NED unit LOS of the last box
        self._rows: list[tuple[float, float, float]] = []  # (t - t0, range the box says, S) of uncut boxes
        self._s_min = math.inf  # the least S of the rows (what "pushed" counts from)
        self.failed = ""
        self.scale: tuple[float, float] | None = None  # the last (k_static, k_moving) judged (diagnostics)

    def update(self, t: float, box: BoundingBox | None, R_ned_frd: np.ndarray,
               accel_frd: np.ndarray | None, los_ned: np.ndarray | None = None) -> str:
        """``los_ned``: the box's world LOS through this check's camera when the caller has it (the engagement
        passes the target lock's, the same vector), else computed here."""
        if self.failed:
            return self.failed
        p = self.p
        if p.gate_radius <= 0.0 or accel_frd is None or not math.isfinite(t):
            return ""
        if box is not None:
            self._l = los_world(self.camera, box.cx, box.cy, R_ned_frd) if los_ned is None else los_ned
        if self._l is None:
            return ""
        a_ned = R_ned_frd @ np.asarray(accel_frd, dtype=float)
        a_ned += _GRAVITY_NED  # in place: the same sums as adding a new array (every frame)
        # The trapezoids' element-by-element arithmetic in floats (IEEE, the same as numpy's element by element);
        # the velocity is an array again only for its products with the LOS (numpy's dot, kept).
        a = ax, ay, az = a_ned.tolist()
        isf = math.isfinite
        if not (isf(ax) and isf(ay) and isf(az)):
            return ""
        if self._t0 is None:
            self._t0 = self._t = t
            self._a_prev = a
        else:
            assert self._t is not None and self._a_prev is not None
            dt = t - self._t
            if not (0.0 < dt <= p.max_dt):
                self._t, self._a_prev = t, a  # a gap: not integrated across (S is then an under-estimate)
                return ""
            v0 = float(self._v.dot(self._l))
            (vx, vy, vz), (px, py, pz) = self._v.tolist(), self._a_prev
            # trapezoids: velocity (world), then distance along the LOS (without a box: the last one)
            self._v = np.array((vx + 0.5 * (px + ax) * dt, vy + 0.5 * (py + ay) * dt, vz + 0.5 * (pz + az) * dt))
            self._s += 0.5 * (v0 + float(self._v.dot(self._l))) * dt
            self._t, self._a_prev = t, a
        if box is None:
            return ""
        x0, y0, x1, y1 = box.xyxy
        e = p.edge_px
        if x0 <= e or y0 <= e or x1 >= p.width - e or y1 >= p.height - e:
            return ""  # cut: its size is not the ring's
        size = max(box.w, box.h)
        if size <= 0.0:
            return ""
        if self._s > p.max_push:
            return ""
        d = 2.0 * p.focal_px * p.gate_radius / size
        self._rows.append((t - self._t0, d, self._s))
        self._s_min = min(self._s_min, self._s)
        pushed = self._s - self._s_min
        if len(self._rows) < p.min_samples or pushed < p.min_push:
            return ""
        # Judged: the rows as an array only now (every frame, it grew with the engagement and was mostly unread).
        tau, dd, ss = np.array(self._rows).T
        first, last = slice(0, 5), slice(-5, None)
        k_static = (float(np.median(dd[first])) - float(np.median(dd[last]))) / max(
            float(np.median(ss[last])) - float(np.median(ss[first])), 1e-6)
        c, *_ = np.linalg.lstsq(np.c_[np.ones(len(tau)), tau, -ss], dd, rcond=None)
        k_moving = float(c[2])
        self.scale = (k_static, k_moving)
        k = max(k_static, k_moving)
        if k < p.min_scale:
            self.failed = (f"not the target (growth): box {size:.0f} px says {d:.1f} m, but our own acceleration "
                           f"moved us {pushed:.1f} m towards it and its size followed {max(k, 0.0):.2f} of that "
                           f"(a ring of the configured size, still or moving: 1; below {p.min_scale:.2f}: "
                           "something farther than its size says)")
        return self.failed
