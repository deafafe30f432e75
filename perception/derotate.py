"""The camera's own rotation between two frames, taken out of the tracker's image-space state.

The pipeline predicts the target's box in the image with a constant-velocity Kalman filter. When the vehicle
itself rotates, the whole image moves: a level gate 25 m ahead of a vehicle that pitches from hover to -36 deg in
0.3 s (PX4 SIH, the first setpoint of an engagement) crosses 240 px of a 640x480 image, 70 px between two frames.
Its detections then fell outside the prediction's reach, the track coasted on the old pixel while the gate left,
and the app rotated that stale pixel with the new attitude into a LOS 22 deg below the true one (SIH run060,
2026-12-07: the engagement dived at it and lost the gate). The attitude at each frame's capture (the one the
controller rotates the box with) tells how far every pixel moved by rotation alone; moving the held boxes by it
before predicting leaves the filter only the target's own motion and the vehicle's translation.

``M = R_world_body(now)^T R_world_body(before)`` maps a body-frame ray of the earlier frame into the current one (the
camera is fixed on the body); a box centre moves to the projection of its rotated ray. Sizes are kept (a rotation
changes them by the lens's off-centre stretch only). A centre whose ray turned behind the camera has no place in
the image: ``None``.
"""

from __future__ import annotations

import math

import numpy as np

from perception.los import CameraModel

_MIN_ANGLE = 1e-6  # rad: below, the rotation moves no pixel by more than ~1e-3 px (hover): nothing is moved
# Faster than any multirotor turns (PX4's MC_*RATE_MAX default to 220 deg/s; racers reach ~1000): an attitude that
# jumps further between two frames is the estimator's (a yaw reset), not the camera's; moving the track by it would
# throw the gate out of the prediction. Nothing is moved for such a step.
MAX_RATE = math.radians(1500.0)  # rad/s


class Derotation:
    """Follows the camera's attitude frame to frame; :meth:`step` gives the rotation since the previous frame."""

    def __init__(self, model: CameraModel) -> None:
        self.model = model
        self._R_prev: np.ndarray | None = None

    def reset(self) -> None:
        self._R_prev = None

    def step(self, R_world_body: np.ndarray | None, dt: float) -> np.ndarray | None:
        """``M`` (a body-frame direction at the previous frame -> the same direction in this frame's body frame) for a
        frame ``dt`` s after the previous one whose attitude is ``R_world_body`` (body FRD -> any fixed world frame);
        None without an attitude, for the first one, for a negligible rotation, or for one faster than ``MAX_RATE``
        (an estimator's jump). The camera is fixed on the body, so the body's rotation is the camera's."""
        if R_world_body is None:
            self._R_prev = None
            return None
        R = np.asarray(R_world_body, dtype=float)
        prev, self._R_prev = self._R_prev, R
        if prev is None:
            return None
        M = R.T @ prev
        # The rotation angle from the trace, clamped against rounding: cos = (tr - 1) / 2.
        c = max(-1.0, min(1.0, 0.5 * (float(M[0, 0] + M[1, 1] + M[2, 2]) - 1.0)))
        angle = math.acos(c)
        return None if angle < _MIN_ANGLE or angle > MAX_RATE * max(dt, 1e-3) else M

    def move(self, M: np.ndarray, u: float, v: float) -> tuple[float, float] | None:
        """Where pixel (u, v) of the earlier frame is in this one, by the rotation ``M`` alone."""
        return self.model.project_body(M @ self.model.ray_body(u, v))
