"""Geometric camera: a circular gate seen from the vehicle's true pose -> pixel bounding box.

The gate centre and rim (a circle of radius r in the gate plane) are projected through the
camera model (intrinsics, distortion, mount). Two box models:

* ``clip=False`` (default, the paper's V-A measurement: "project the gate's ground truth
  position into the camera frame"): the box is centred on the projected gate centre, its size
  is the rim's pixel extent;
* ``clip=True`` (detector-like): the box is the extent of the part of the rim that is in the
  image, so a ring cut by the image border gives a biased centre, as a real detector's box
  would; a ring whose centre is outside the image but whose rim reaches into it still gives a
  (partial) box; near the pass the arcs in view fill the image, and a ring all around the image
  (the camera looks through it) gives none.

The rim's extent is exact (closed form for the projected circle) when the whole ring is in
front of an undistorted camera, else from 32 rim samples (cv2.projectPoints with distortion).
No box when the gate centre is behind the camera or outside the image (the FOV check; with
``clip``: when no part of the rim is in the image), when
the box is smaller than ``min_box`` pixels, or when the frame is dropped. Pixel noise is
added to the box centre and size: white (``pixel_noise``) or, opted in, the detector-like error model of
companion/sim/boxnoise.py (coloured, size-dependent, wrong targets and misses). Latency is the
runner's job (it delivers the box of a frame captured at t at t + delay).

A square or rectangular target (``use_rectangle``: half width along the plane's horizontal axis, half height
along its vertical one) is projected the same way from its outline (its edges sampled, so a target partly behind
the camera or cut by the border gives the extent of what is in view): its box is the rectangle's, not a ring's.
"""

from __future__ import annotations

import math
from functools import cache, lru_cache
from typing import Any

import cv2
import numpy as np

from companion.frames import F_FRD_FLU, cross_xyz
from companion.sim.boxnoise import PROFILES, DetectorNoise
from companion.sim.draws import NormalReadAhead
from perception.los import CameraModel
from perception.types import BoundingBox

_N_RIM = 32  # rim samples; the box of a 32-gon is within 0.5 % of the circle's


_ANG = np.linspace(0.0, 2 * math.pi, _N_RIM, endpoint=False)
_COS_SIN = np.column_stack((np.cos(_ANG), np.sin(_ANG)))
_ANG_FINE = np.linspace(0.0, 2 * math.pi, 4 * _N_RIM, endpoint=False)
_COS_SIN_FINE = np.column_stack((np.cos(_ANG_FINE), np.sin(_ANG_FINE)))  # the visible arc of a cut ring


def _rect_outline(per_edge: int = 16) -> np.ndarray:
    """(4 per_edge, 2) unit-square outline (+-1, +-1) sampled along its edges, in order (a closed polygon)."""
    s = np.linspace(-1.0, 1.0, per_edge, endpoint=False)
    one = np.ones_like(s)
    return np.vstack((np.column_stack((s, -one)), np.column_stack((one, s)), np.column_stack((-s, one)),
                      np.column_stack((-one, -s))))


_RECT_UNIT = _rect_outline()


@lru_cache(maxsize=64)
def _rim_basis(normal: tuple[float, float, float]) -> np.ndarray:
    """(2, 3): two unit vectors spanning the gate plane."""
    nrm = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    a = (0.0, 0.0, 1.0) if abs(nrm[2]) < 0.9 else (1.0, 0.0, 0.0)
    n0, n1, n2 = nrm.tolist()
    u = np.array(cross_xyz((n0, n1, n2), a))
    u /= np.linalg.norm(u)
    return np.array((u.tolist(), cross_xyz((n0, n1, n2), tuple(u.tolist()))))


@lru_cache(maxsize=64)
def _scaled_basis(normal: tuple[float, float, float], radius: float) -> np.ndarray:
    """``radius * _rim_basis(normal)`` (cached: the same gate every frame of a run)."""
    ab = radius * _rim_basis(normal)
    ab.flags.writeable = False
    return ab


def _normal_key(normal: Any) -> tuple[float, float, float]:
    """The gate normal as _rim_basis's cache key: ``tolist`` gives the same floats as ``float()`` of each element
    in one call (every frame; the generator it replaces was ~2 % of a simulator frame)."""
    return tuple(normal.tolist()) if isinstance(normal, np.ndarray) else tuple(float(c) for c in normal)


def rim_points(centre: np.ndarray, normal: np.ndarray, radius: float) -> np.ndarray:
    """_N_RIM points on the circle (world frame), shape (n, 3)."""
    basis = _rim_basis(_normal_key(normal))
    return centre + radius * (_COS_SIN @ basis)


def _ratio_extremes(a0: float, a1: float, a2: float, b0: float, b1: float, b2: float) -> tuple[float, float]:
    """min and max over theta of (a0 + a1 cos + a2 sin) / (b0 + b1 cos + b2 sin), denominator > 0.

    The derivative vanishes where P sin + Q cos + S = 0 with P = a0 b1 - a1 b0,
    Q = a2 b0 - a0 b2, S = a2 b1 - a1 b2: two angles theta = phi +- acos(-S / hypot(P, Q)).
    """
    p, q, s = a0 * b1 - a1 * b0, a2 * b0 - a0 * b2, a2 * b1 - a1 * b2
    h = math.hypot(p, q)
    if h < 1e-15:
        v = a0 / b0
        return v, v
    phi = math.atan2(p, q)  # P sin + Q cos = h cos(theta - phi)
    d = math.acos(max(-1.0, min(1.0, -s / h)))
    # The two angles written out (twice a frame): min/max of [v, w] as the builtins pick them (the first unless the
    # second is strictly smaller / larger), without a list and a loop.
    ct, st = math.cos(phi + d), math.sin(phi + d)
    v = (a0 + a1 * ct + a2 * st) / (b0 + b1 * ct + b2 * st)
    ct, st = math.cos(phi - d), math.sin(phi - d)
    w = (a0 + a1 * ct + a2 * st) / (b0 + b1 * ct + b2 * st)
    return (w if w < v else v), (w if w > v else v)


class GeometricCamera:
    """Projects a gate with the vehicle's *true* pose (ENU position, xyzw FLU->ENU attitude)."""

    def __init__(
        self,
        model: CameraModel,
        pixel_noise: float = 0.0,
        drop_prob: float = 0.0,
        min_box: float = 2.0,
        rng: np.random.Generator | None = None,
        clip: bool = False,
    ) -> None:
        self.model = model
        self.clip = bool(clip)
        self.pixel_noise = float(pixel_noise)
        self.drop_prob = float(drop_prob)
        self.min_box = float(min_box)
        self.rng = rng if rng is not None else np.random.default_rng(0)
        # camera (OpenCV) -> body FLU, fixed: body FRD -> FLU is F_FRD_FLU (self-inverse).
        self._R_flu_cam = F_FRD_FLU @ model.R_body_cam
        self._distorted = bool(model.dist.size and np.any(model.dist != 0.0))
        self.detector_noise: DetectorNoise | None = None  # set: the detector error model replaces pixel_noise
        self._ahead: NormalReadAhead | None = None  # read_ahead(): the pixel noise's normals
        self.rect: tuple[float, float] | None = None  # (half width, half height) of a rectangular target; None: ring
        self._wh = np.array([float(model.width), float(model.height)])  # the image's far corner, px
        K = model.K
        self._K2T, self._k2 = K[:2, :2].T, K[:2, 2]  # project's views of K (the same arrays, made once)
        # (fx, cx, fy, cy) of an undistorted camera without skew (the ring's closed-form extent), else None.
        self._pinhole: tuple[float, float, float, float] | None = (
            (float(K[0, 0]), float(K[0, 2]), float(K[1, 1]), float(K[1, 2]))
            if not self._distorted and K[0, 1] == 0.0 else None)

    def use_rectangle(self, width: float, height: float) -> None:
        """The target is a width x height rectangle (m) in the gate plane, not a ring."""
        self.rect = (0.5 * float(width), 0.5 * float(height))

    def use_detector_noise(self, noise: DetectorNoise) -> None:
        """Opt in to the detector-like box error (``sim.camera.noise_model: detector``) instead of white noise."""
        if self._ahead is not None:
            raise RuntimeError("GeometricCamera: read_ahead() is on; the detector noise would share its stream")
        self.detector_noise = noise

    def read_ahead(self, block: int = 256) -> None:
        """From now on the pixel noise comes from normals drawn a block ahead (the same values, ``normal(0, s)``
        being ``0.0 + s * z``; one numpy call a block, not a frame). Only when the pixel noise is the stream's one
        reader: no drops, no detector noise."""
        if self.drop_prob > 0.0 or self.detector_noise is not None:
            raise RuntimeError("GeometricCamera.read_ahead: drops or the detector noise draw from the same stream")
        self._ahead = NormalReadAhead(self.rng, block)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Pixel coordinates (n, 2) of camera-frame points with z > 0."""
        if self._distorted:
            img, _ = cv2.projectPoints(points_cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                       self.model.K, self.model.dist)
            return img.reshape(-1, 2)
        xy = points_cam[:, :2] / points_cam[:, 2:3]
        return xy.dot(self._K2T) + self._k2

    def to_camera(self, points_world: np.ndarray, p_enu: np.ndarray, R_enu_flu: np.ndarray) -> np.ndarray:
        """World ENU points (n, 3) -> camera OpenCV frame (n, 3)."""
        R_cam_world = (R_enu_flu @ self._R_flu_cam).T
        return (points_world - p_enu) @ R_cam_world.T

    def box_exact(
        self, p_enu: np.ndarray, R_enu_flu: np.ndarray, centre: np.ndarray, normal: np.ndarray, radius: float,
        t: float = 0.0,
    ) -> BoundingBox | None:
        """Noise-free box of the gate, or None when it is not (usefully) in view."""
        m = self.model
        # ndarray.dot, not @, every frame: matmul's dispatch costs ~2x the method on 3x3 operands; the same BLAS
        # result, bit for bit (tests/test_speed_identity.py).
        R_cam_world = R_enu_flu.dot(self._R_flu_cam).T
        c = R_cam_world.dot(centre - p_enu)
        # Python floats of the numpy results (tolist: the same values as float() of each element, in one call).
        c0, c1, cz = c.tolist()
        if cz <= 1e-3:
            return None
        key = _normal_key(normal)
        if self.rect is not None:
            return self._rect_box(c, _rim_basis(key).dot(R_cam_world.T), t)
        ab = _scaled_basis(key, float(radius)).dot(R_cam_world.T)  # rim = c + a cos + b sin
        (a0, a1, az), (b0, b1, bz) = ab.tolist()
        if self._pinhole is not None and cz - math.hypot(az, bz) > 1e-3:
            # Whole ring in front of an undistorted camera: exact extent of the projected circle.
            fx, cx, fy, cy = self._pinhole
            cu = fx * c0 / cz + cx
            cv = fy * c1 / cz + cy
            if not self.clip and not (0.0 <= cu <= m.width and 0.0 <= cv <= m.height):
                return None  # the FOV check: the gate centre must be in the image
            u0, u1 = _ratio_extremes(fx * c0 + cx * cz, fx * a0 + cx * az, fx * b0 + cx * bz, cz, az, bz)
            v0, v1 = _ratio_extremes(fy * c1 + cy * cz, fy * a1 + cy * az, fy * b1 + cy * bz, cz, az, bz)
        else:
            rim = c + _COS_SIN.dot(ab)  # sampled rim, camera frame
            front = rim[rim[:, 2] > 1e-3]  # rim points behind the camera: the ring is being passed
            if front.shape[0] < 3:
                return None
            px = self.project(np.vstack((c[None, :], front)))
            cu, cv = float(px[0, 0]), float(px[0, 1])
            if not self.clip and not (0.0 <= cu <= m.width and 0.0 <= cv <= m.height):
                return None
            lo, hi = px[1:].min(axis=0), px[1:].max(axis=0)
            u0, v0, u1, v1 = float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])
        if not self.clip:
            # The paper's measurement: the projected gate centre; the size is the rim's extent.
            if u1 - u0 < self.min_box or v1 - v0 < self.min_box:
                return None
            return BoundingBox(cu, cv, u1 - u0, v1 - v0, 1.0, t)
        if not (u0 >= 0.0 and u1 <= m.width and v0 >= 0.0 and v1 <= m.height):
            # Cut by the image border: the extent of the part of the ring that is in the image (a box
            # clipped to the image would also keep the height of the arcs that are outside it).
            vis = self._visible_extent(c, ab)
            if vis is None:
                return None
            u0, v0, u1, v1 = vis
        if u1 - u0 < self.min_box or v1 - v0 < self.min_box:
            return None
        return BoundingBox.from_xyxy(u0, v0, u1, v1, 1.0, t)

    def _rect_box(self, c: np.ndarray, uv: np.ndarray, t: float) -> BoundingBox | None:
        """Box of the rectangle c +- hw u +- hh v (camera frame; u horizontal, v vertical in the plane)."""
        m = self.model
        hw, hh = self.rect  # type: ignore[misc]
        outline = c + _RECT_UNIT * np.array([hw, hh]) @ uv  # cyclic samples along the four edges
        front = outline[:, 2] > 1e-3
        if not self.clip:
            cu, cv = self.project(c[None, :])[0]
            if not (0.0 <= cu <= m.width and 0.0 <= cv <= m.height) or front.sum() < 3:
                return None
            px = self.project(outline[front])
            lo, hi = px.min(axis=0), px.max(axis=0)
            if hi[0] - lo[0] < self.min_box or hi[1] - lo[1] < self.min_box:
                return None
            return BoundingBox(float(cu), float(cv), float(hi[0] - lo[0]), float(hi[1] - lo[1]), 1.0, t)
        vis = self._outline_extent(outline)
        if vis is None:
            return None
        u0, v0, u1, v1 = vis
        if u1 - u0 < self.min_box or v1 - v0 < self.min_box:
            return None
        return BoundingBox.from_xyxy(u0, v0, u1, v1, 1.0, t)

    def _visible_extent(self, c: np.ndarray, ab: np.ndarray) -> tuple[float, float, float, float] | None:
        """Pixel extent of the rim inside the image: each chord between rim samples (both in front of the
        camera) clipped to the image rectangle (Liang-Barsky), then the extent of what is left."""
        return self._outline_extent(c + _COS_SIN_FINE.dot(ab))

    def _outline_extent(self, rim: np.ndarray) -> tuple[float, float, float, float] | None:
        """Pixel extent inside the image of a closed outline (camera-frame samples, in order)."""
        n = rim.shape[0]
        nxt = _next_index(n)
        front = rim[:, 2] > 1e-3
        n_front = int(np.count_nonzero(front))
        if n_front == n:
            p0 = self.project(rim)
            d = p0[nxt] - p0
        else:
            if n_front < 2:
                return None
            px = np.zeros((n, 2))
            px[front] = self.project(rim[front])
            both = front & front[nxt]  # chords with both ends in front of the camera
            p0, p1 = px[both], px[nxt][both]
            if p0.shape[0] == 0:
                return None
            d = p1 - p0
        if np.count_nonzero(d) < d.size:  # (count_nonzero: no Python wrapper, unlike d.all())
            return self._clipped_extent_general(p0, d)  # a chord along an image axis (rare)
        # Liang-Barsky with no chord parallel to an image axis: per axis, one border bounds the entry (t0) and
        # the other the exit (t1), chosen by the sign of d: entry (-x0) / dx or (w - x0) / dx, exit the other.
        # The same quotients as the general form's (x0 / -dx == -x0 / dx exactly) in fewer numpy calls: this
        # runs in a third of the frames (a ring cut by the border) and was ~10 % of a simulator frame.
        neg, room = -p0, self._wh - p0  # (-x0, -y0), (w - x0, h - y0)
        ahead = d > 0.0
        q0, q1 = np.where(ahead, neg, room) / d, np.where(ahead, room, neg) / d
        t0 = np.maximum(q0[:, 0], q0[:, 1])  # column-wise: a reduce over rows of two is slower
        np.maximum(t0, 0.0, out=t0)
        t1 = np.minimum(q1[:, 0], q1[:, 1])
        np.minimum(t1, 1.0, out=t1)
        ends = np.concatenate((p0 + t0[:, None] * d, p0 + t1[:, None] * d), axis=1)[t0 <= t1]
        if ends.shape[0] == 0:
            return None
        u0, v0, u0b, v0b = np.minimum.reduce(ends, axis=0).tolist()
        u1, v1, u1b, v1b = np.maximum.reduce(ends, axis=0).tolist()
        return min(u0, u0b), min(v0, v0b), max(u1, u1b), max(v1, v1b)

    def _clipped_extent_general(self, p0: np.ndarray, d: np.ndarray) -> tuple[float, float, float, float] | None:
        """Liang-Barsky of the chords p0 -> p0 + d against the image rectangle, any chord; the extent of what
        is left."""
        w, h = float(self.model.width), float(self.model.height)
        pp = np.concatenate((-d, d), axis=1)  # (-dx, -dy, dx, dy)
        qq = np.concatenate((p0, (w, h) - p0), axis=1)  # (x0, y0, w - x0, h - y0)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = qq / pp
        t0 = np.where(pp < 0, r, 0.0).max(axis=1)
        t1 = np.where(pp > 0, r, 1.0).min(axis=1)
        keep = (t0 <= t1) & ~((pp == 0) & (qq < 0)).any(axis=1)
        if not keep.any():
            return None
        p0, d, t0, t1 = p0[keep], d[keep], t0[keep, None], t1[keep, None]
        ends = np.concatenate((p0 + t0 * d, p0 + t1 * d))
        lo, hi = ends.min(axis=0), ends.max(axis=0)
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])

    def capture(
        self, t: float, p_enu: np.ndarray, R_enu_flu: np.ndarray, centre: np.ndarray, normal: np.ndarray,
        radius: float,
    ) -> BoundingBox | None:
        """One frame: exact box + drop + pixel noise (noise keeps the box inside the image)."""
        if self.drop_prob > 0.0 and self.rng.random() < self.drop_prob:
            return None
        box = self.box_exact(p_enu, R_enu_flu, centre, normal, radius, t)
        if self.detector_noise is not None:
            return self.detector_noise.apply(box)
        if box is None or self.pixel_noise <= 0.0:
            return box
        if self._ahead is not None:
            s = self.pixel_noise
            z0, z1, z2, z3 = self._ahead.take(4)
            n0, n1, n2, n3 = 0.0 + s * z0, 0.0 + s * z1, 0.0 + s * z2, 0.0 + s * z3
        else:
            n0, n1, n2, n3 = self.rng.normal(0.0, self.pixel_noise, 4).tolist()  # Python floats: cheaper downstream
        m = self.model
        cx = min(max(box.cx + n0, 0.0), float(m.width))
        cy = min(max(box.cy + n1, 0.0), float(m.height))
        w = max(box.w + n2, 1.0)
        h = max(box.h + n3, 1.0)
        return BoundingBox(cx, cy, w, h, 1.0, t)


@cache
def _next_index(n: int) -> np.ndarray:
    """``np.roll(np.arange(n), -1)``: each outline sample's successor (cached: the same few sizes every frame)."""
    idx = np.roll(np.arange(n), -1)
    idx.flags.writeable = False
    return idx


def true_camera_config(cfg: Any) -> Any:
    """The ``camera`` section the simulated camera really has: ``camera.mount`` plus ``sim.camera.mount_error``.

    The app (controller, tracker, calibration) keeps the configured ``cfg.camera``; only the cameras that render
    what the vehicle sees (in-process geometric and rendered, the synthetic camera for PX4) use this one.
    """
    err, m = cfg.sim.camera.mount_error, cfg.camera.mount
    if err.roll == 0.0 and err.pitch == 0.0 and err.yaw == 0.0:
        return cfg.camera
    try:  # validated: a true pitch beyond +-90 deg is a config error, named
        true_mount = type(m).model_validate({"roll": m.roll + err.roll, "pitch": m.pitch + err.pitch,
                                             "yaw": m.yaw + err.yaw})
    except ValueError as e:
        raise ValueError(f"sim.camera.mount_error: camera.mount + error is not a mount: {e}") from None
    return cfg.camera.model_copy(update={"mount": true_mount})


def detector_noise(cfg: Any, rng: np.random.Generator) -> DetectorNoise:
    """The detector error model of ``cfg.sim.camera.detector_profile`` for the configured image size."""
    return DetectorNoise(PROFILES[cfg.sim.camera.detector_profile], rng, int(cfg.camera.width), int(cfg.camera.height))
