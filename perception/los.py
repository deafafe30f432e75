"""Bounding box -> line of sight: pixel -> unit ray (intrinsics, distortion) -> body -> world, and the LOS filter.

Pure functions and small state; no I/O. Frames: camera = OpenCV (x right, y down,
z forward), body = FRD, world = NED (the attitude PX4 reports). The controller turns the
world LOS into the paper's frame at its own boundary (companion/frames.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

_I3 = np.eye(3)
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


@dataclass(frozen=True)
class CameraModel:
    """Pinhole camera with OpenCV distortion, mounted on the body with ``R_body_cam``."""

    K: np.ndarray  # 3x3 intrinsics
    dist: np.ndarray  # OpenCV distortion coefficients (may be empty)
    R_body_cam: np.ndarray  # camera -> body FRD
    width: int
    height: int

    def __post_init__(self) -> None:
        # Cached for the hot path: the inverse intrinsics and the flag that lets us skip cv2.
        object.__setattr__(self, "_K_inv", np.linalg.inv(self.K))
        Ki = self._K_inv  # type: ignore[attr-defined]
        object.__setattr__(self, "_K_inv_scalars", (float(Ki[0, 0]), float(Ki[0, 1]), float(Ki[0, 2]),
                                                    float(Ki[1, 1]), float(Ki[1, 2])))
        object.__setattr__(self, "_distorted", bool(self.dist.size and np.any(self.dist != 0.0)))
        # A mount that only permutes and negates axes (a camera along a body axis, the common case): its
        # rows as floats, for ray_body without a matrix product (every frame).
        R = np.asarray(self.R_body_cam, dtype=float)
        perm = R.shape == (3, 3) and bool(np.isin(R, (0.0, 1.0, -1.0)).all()) and bool(
            (np.count_nonzero(R, axis=0) == 1).all() and (np.count_nonzero(R, axis=1) == 1).all())
        object.__setattr__(self, "_perm_rows", tuple(tuple(r) for r in R.tolist()) if perm else None)

    @classmethod
    def from_config(cls, camera: Any) -> CameraModel:
        """From a ``companion.config.CameraConfig`` (duck-typed so perception does not import companion)."""
        return cls(np.asarray(camera.K, float), np.asarray(camera.dist, float),
                   np.asarray(camera.R_body_cam, float), int(camera.width), int(camera.height))

    @property
    def optical_axis_body(self) -> np.ndarray:
        return self.R_body_cam[:, 2].copy()

    def ray_cam(self, u: float, v: float) -> np.ndarray:
        """Unit ray in the camera frame through pixel (u, v), distortion removed."""
        return np.array(self.ray_cam_xyz(u, v))

    def ray_cam_xyz(self, u: float, v: float) -> tuple[float, float, float]:
        """:meth:`ray_cam` as three floats (the same values, bit for bit): the closing-speed range needs four
        rays a frame, and a numpy array per ray cost more than the arithmetic."""
        if self._distorted:
            # OpenCV's default 5 iterations leave ~0.2 px error in the corners of a wide lens.
            pts = cv2.undistortPoints(np.array([[[u, v]]], dtype=np.float64), self.K, self.dist,
                                      R=_I3, P=_I3, criteria=_UNDISTORT_CRITERIA)
            x, y = float(pts[0, 0, 0]), float(pts[0, 0, 1])
        else:
            k00, k01, k02, k11, k12 = self._K_inv_scalars
            x = k00 * u + k01 * v + k02
            y = k11 * v + k12
        n = math.sqrt(x * x + y * y + 1.0)
        return x / n, y / n, 1.0 / n

    def ray_angle(self, u0: float, v0: float, u1: float, v1: float) -> float:
        """The angle (rad) between the rays through pixels (u0, v0) and (u1, v1): ``atan2(|a x b|, a . b)`` of
        their :meth:`ray_cam_xyz`, in floats (the closing speed's range takes two a frame)."""
        if self._distorted:
            ax, ay, az = self.ray_cam_xyz(u0, v0)
            bx, by, bz = self.ray_cam_xyz(u1, v1)
        else:  # ray_cam_xyz's pinhole branch written out for both rays: the same floats, two calls fewer a ray pair
            k00, k01, k02, k11, k12 = self._K_inv_scalars
            x, y = k00 * u0 + k01 * v0 + k02, k11 * v0 + k12
            n = math.sqrt(x * x + y * y + 1.0)
            ax, ay, az = x / n, y / n, 1.0 / n
            x, y = k00 * u1 + k01 * v1 + k02, k11 * v1 + k12
            n = math.sqrt(x * x + y * y + 1.0)
            bx, by, bz = x / n, y / n, 1.0 / n
        cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        return math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz), ax * bx + ay * by + az * bz)

    def ray_body(self, u: float, v: float) -> np.ndarray:
        """Unit ray in body FRD through pixel (u, v)."""
        rows = self._perm_rows  # type: ignore[attr-defined]
        if rows is None:
            return self.R_body_cam.dot(self.ray_cam(u, v))
        # Every product is by 0 or +-1 and exact, one non-zero per row: the sum is exact in any order, the float
        # the matrix product gives; BLAS adds to a +0 accumulator, which the leading 0.0 repeats (signed zeros).
        x, y, z = self.ray_cam_xyz(u, v)
        (a0, a1, a2), (b0, b1, b2), (c0, c1, c2) = rows
        return np.array([0.0 + a0 * x + a1 * y + a2 * z, 0.0 + b0 * x + b1 * y + b2 * z,
                         0.0 + c0 * x + c1 * y + c2 * z])

    def project_body(self, v_body: np.ndarray) -> tuple[float, float] | None:
        """Pixel of a body-frame direction or point (distortion applied); None if behind the camera."""
        p = self.R_body_cam.T @ np.asarray(v_body, dtype=float)
        if p[2] <= 1e-9:
            return None
        if self._distorted:
            img, _ = cv2.projectPoints(p.reshape(1, 1, 3), np.zeros(3), np.zeros(3), self.K, self.dist)
            return float(img[0, 0, 0]), float(img[0, 0, 1])
        x, y = p[0] / p[2], p[1] / p[2]
        return float(self.K[0, 0] * x + self.K[0, 1] * y + self.K[0, 2]), float(self.K[1, 1] * y + self.K[1, 2])


def los_world(model: CameraModel, u: float, v: float, R_ned_frd: np.ndarray) -> np.ndarray:
    """Unit LOS in world NED through pixel (u, v), given the attitude at the frame's capture time."""
    return R_ned_frd.dot(model.ray_body(u, v))


class LosFilter:
    """First-order low-pass on a unit vector (world frame), with time-step-aware gain.

    ``l_f <- normalise(l_f + alpha (l - l_f))``, ``alpha = 1 - exp(-2 pi f_c dt)``. Filtering in
    the world frame (after rotating with the attitude) keeps the vehicle's own rotation out of
    the filter lag: only the inertial LOS motion is smoothed. A gap longer than ``max_dt``
    restarts the filter at the new measurement.
    """

    def __init__(self, cutoff_hz: float, max_dt: float = 0.5) -> None:
        if not cutoff_hz > 0:
            raise ValueError(f"LOS filter cutoff must be > 0 Hz, got {cutoff_hz}")
        self.cutoff_hz = float(cutoff_hz)
        self.max_dt = float(max_dt)
        # The state as three floats (the controller's per-frame path reads and writes floats: update_xyz);
        # ``value`` gives it as an array.
        self._xyz: tuple[float, float, float] | None = None
        self.t: float | None = None

    @property
    def value(self) -> np.ndarray | None:
        """The filtered unit vector (a new array), None before the first update."""
        return None if self._xyz is None else np.array(self._xyz)

    @value.setter
    def value(self, v: np.ndarray | None) -> None:
        self._xyz = None if v is None else tuple(np.asarray(v, dtype=float).tolist())

    def reset(self) -> None:
        self._xyz = None
        self.t = None

    def update(self, t: float, l: np.ndarray) -> np.ndarray:  # noqa: E741
        return np.array(self.update_xyz(t, *np.asarray(l, dtype=float).tolist()))

    def update_xyz(self, t: float, lx: float, ly: float, lz: float) -> tuple[float, float, float]:
        """:meth:`update` on three floats, returning three floats (the same values, bit for bit)."""
        v = self._xyz
        if v is None or self.t is None or not (0.0 < t - self.t <= self.max_dt):
            v = (lx, ly, lz)
        else:
            alpha = 1.0 - math.exp(-2.0 * math.pi * self.cutoff_hz * (t - self.t))
            # Scalar math (the same operations as the array form, bit for bit): this runs every frame.
            ox, oy, oz = v
            vx, vy, vz = ox + alpha * (lx - ox), oy + alpha * (ly - oy), oz + alpha * (lz - oz)
            nv = math.sqrt(vx * vx + vy * vy + vz * vz)
            # Opposite vectors can cancel; then the new measurement is all we have.
            v = (vx / nv, vy / nv, vz / nv) if nv > 1e-9 else (lx, ly, lz)
        self._xyz = v
        self.t = t
        return v


@dataclass(frozen=True)
class LosKalmanParams:
    """Tuning of ``LosKalman``."""

    accel_std: float  # rad/s^2 per sqrt(Hz): white LOS-acceleration density of the constant-velocity model
    gate: float  # innovations beyond this many sigmas are rejected (wrong target, glitch)
    reacquire: int = 3  # this many rejections in a row: a real jump, restart at the measurement
    max_dt: float = 0.5  # s; a longer gap restarts the filter
    rate0: float = 0.5  # rad/s, prior std of the LOS rate at a (re)start


class LosKalman:
    """Constant-velocity Kalman filter on the unit LOS (world frame): the LOS and its rate from noisy rays.

    State per world axis: the LOS component and its rate, with white LOS acceleration (density ``accel_std^2``).
    The measurement noise (rad) comes with each ray, so the caller scales it with the box (a detector's centre
    error grows with the box). All three axes share the model and the noise, hence one 2x2 covariance. After
    each step the LOS is renormalised and its rate made normal to it; the rate is ``lambda_dot n`` of the PN law
    (``guidance.los_rate``'s n is the direction of dl/dt). An innovation beyond ``gate`` sigmas is rejected and
    the prediction kept; ``reacquire`` rejections in a row restart the filter at the new LOS.
    """

    def __init__(self, params: LosKalmanParams) -> None:
        p = params
        if not (p.accel_std > 0.0 and p.gate > 0.0 and p.max_dt > 0.0 and p.rate0 > 0.0 and p.reacquire >= 1):
            raise ValueError(f"LOS Kalman filter: accel_std, gate, max_dt and rate0 must be > 0, got {p}")
        self.p = params
        self.reset()

    def reset(self) -> None:
        self.l: np.ndarray | None = None  # unit LOS
        self.rate = np.zeros(3)  # dl/dt, normal to l
        self.P = np.zeros((2, 2))  # covariance of (component, rate), the same for each axis
        self.t: float | None = None
        self.rejections = 0
        self.last_nis = 0.0  # normalised innovation (sigmas) of the last measurement

    def _start(self, t: float, z: np.ndarray, sigma: float) -> None:
        self.l = z.copy()
        self.rate = np.zeros(3)
        self.P = np.diag([sigma * sigma, self.p.rate0 ** 2])
        self.t = t
        self.rejections = 0
        self.last_nis = 0.0

    def update(self, t: float, l: np.ndarray, sigma: float, accel_std: float | None = None) -> bool:  # noqa: E741
        """Fuse the unit LOS ``l`` measured at ``t`` with noise std ``sigma`` (rad). False: rejected by the gate
        (``self.l``/``self.rate`` then hold the prediction to ``t``). ``accel_std`` overrides the parameter's
        process noise for this step."""
        z = np.asarray(l, dtype=float)
        sigma = max(float(sigma), 1e-6)
        if self.l is None or self.t is None or not (0.0 < t - self.t <= self.p.max_dt):
            self._start(t, z, sigma)
            return True
        dt = t - self.t
        # Predict: x <- F x, P <- F P F' + Q (white acceleration).
        lp = self.l + dt * self.rate
        P = self.P
        p00 = P[0, 0] + dt * (2.0 * P[0, 1] + dt * P[1, 1])
        p01 = P[0, 1] + dt * P[1, 1]
        p11 = P[1, 1]
        q = (self.p.accel_std if accel_std is None else accel_std) ** 2
        p00 += q * dt ** 3 / 3.0
        p01 += q * dt ** 2 / 2.0
        p11 += q * dt
        s = p00 + sigma * sigma
        nu = z - lp
        nis = math.sqrt(float(nu.dot(nu)) / s)
        self.last_nis = nis
        self.t = t
        if nis > self.p.gate:
            self.rejections += 1
            if self.rejections >= self.p.reacquire:
                self._start(t, z, sigma)
                return True
            self._set(lp, self.rate, np.array([[p00, p01], [p01, p11]]))
            return False
        self.rejections = 0
        k0, k1 = p00 / s, p01 / s
        self._set(lp + k0 * nu, self.rate + k1 * nu,
                  np.array([[(1.0 - k0) * p00, (1.0 - k0) * p01], [(1.0 - k0) * p01, p11 - k1 * p01]]))
        return True

    def _set(self, l: np.ndarray, rate: np.ndarray, P: np.ndarray) -> None:  # noqa: E741
        n = math.sqrt(float(l.dot(l)))
        self.l = l / n if n > 1e-9 else self.l
        assert self.l is not None
        self.rate = rate - float(rate.dot(self.l)) * self.l
        self.P = P
