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
        object.__setattr__(self, "_distorted", bool(self.dist.size and np.any(self.dist != 0.0)))

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
        if self._distorted:
            # OpenCV's default 5 iterations leave ~0.2 px error in the corners of a wide lens.
            pts = cv2.undistortPoints(np.array([[[u, v]]], dtype=np.float64), self.K, self.dist,
                                      R=_I3, P=_I3, criteria=_UNDISTORT_CRITERIA)
            x, y = float(pts[0, 0, 0]), float(pts[0, 0, 1])
        else:
            Ki = self._K_inv
            x = Ki[0, 0] * u + Ki[0, 1] * v + Ki[0, 2]
            y = Ki[1, 1] * v + Ki[1, 2]
        r = np.array([x, y, 1.0])
        return r / math.sqrt(x * x + y * y + 1.0)

    def ray_body(self, u: float, v: float) -> np.ndarray:
        """Unit ray in body FRD through pixel (u, v)."""
        return self.R_body_cam @ self.ray_cam(u, v)

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
    return R_ned_frd @ model.ray_body(u, v)


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
        self.value: np.ndarray | None = None
        self.t: float | None = None

    def reset(self) -> None:
        self.value = None
        self.t = None

    def update(self, t: float, l: np.ndarray) -> np.ndarray:  # noqa: E741
        if self.value is None or self.t is None or not (0.0 < t - self.t <= self.max_dt):
            self.value = np.asarray(l, dtype=float).copy()
        else:
            alpha = 1.0 - math.exp(-2.0 * math.pi * self.cutoff_hz * (t - self.t))
            v = self.value + alpha * (l - self.value)
            nv = math.sqrt(float(v @ v))
            # Opposite vectors can cancel; then the new measurement is all we have.
            self.value = v / nv if nv > 1e-9 else np.asarray(l, dtype=float).copy()
        self.t = t
        return self.value
