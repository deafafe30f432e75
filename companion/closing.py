"""Closing speed without position: range from the gate's apparent size, range rate from a small Kalman filter.

Why: the PN law ``a_n = k_PN v_rel_bar lambda_dot n`` has the effective navigation gain
``k_PN v_rel_bar / v_closing``. With the paper's fixed ``v_rel_bar`` (15 m/s, tuned on a fast x500) a slow
vehicle gets a gain of ~7 (PX4's SIH quad at 4.4 m/s), which with its ~220 ms roll lag limit-cycles.
This estimator lowers ``v_rel_bar`` to what the image shows, and only on evidence.

Measurement: the gate is a ring of known radius ``r`` (``guidance.gate_radius``); the angle ``alpha`` its box
subtends (the larger of width and height: a tilted ring keeps its full diameter along one axis) gives the
range ``d = r / tan(alpha / 2)``. Boxes touching the image border are cut and are not measurements.

Filter: state (d, d_dot), constant range acceleration over a frame, driven (when the IMU is given) by the
range acceleration the vehicle's own acceleration explains, ``d_ddot = -a . l + d lambda_dot^2`` (a from the
accelerometer and the attitude; the gate's own acceleration is process noise). The prior on ``d_dot`` is
``-v_rel_bar`` with a standard deviation of ``v_rel_bar / 2``: until the image says otherwise the closing
speed is the paper's bound (runs may start at cruise speed; an IMU integral from zero would be wrong).

Output (:meth:`ClosingSpeedEstimator.speed`): ``margin |v_rel| + sigma_v``, an upper confidence value of the
relative speed (PN needs ``k_PN v >= 2 v_rel`` to converge, so it errs high), never above ``v_rel_bar``,
and near the gate at most ``d / (lag_margin * loop_lag)``: lag-aware, PN's loop gain ``N / t_go`` must stay
below the bandwidth the vehicle's lag allows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from perception.los import CameraModel
from perception.types import BoundingBox


@dataclass(frozen=True, slots=True)
class ClosingParams:
    gate_radius: float  # m, radius of the ring the camera sees
    v_rel_bar: float  # m/s, the prior and the upper bound
    margin: float = 5.0  # v = margin * |v_rel| + sigma (then capped): effective navigation gain <= margin * k_PN
    v_min: float = 1.0  # m/s, floor (a hovering start still gets some PN)
    pixel_noise: float = 1.5  # px, std of a box edge
    size_noise: float = 0.03  # relative std of the box size beyond pixel noise (detector, ring tilt)
    accel_noise: float = 3.0  # m/s^2, std of the range acceleration the model does not explain (no IMU)
    accel_noise_imu: float = 1.0  # m/s^2, the same when the IMU explains our own acceleration
    border: float = 1.0  # px; a box this close to the image border is cut: no range from it
    loop_lag: float = 0.0  # s, vehicle attitude response + filter lags; 0 = no range-based gain limit
    lag_margin: float = 1.0  # the PN loop's crossover kept below 1 / (lag_margin * loop_lag)
    # A box whose larger side reaches this fraction of the image's smaller side gives no range (0 = off): a ring
    # that near fills the view, its box saturates at the image and then gives way to background boxes of the same
    # size, and the range they say stays at ~2 m while the vehicle flies through (docs/verification-px4.md). From
    # there the range is dead-reckoned with the IMU.
    max_box: float = 0.0


class ClosingSpeedEstimator:
    """Per-engagement state; ``update`` once per frame, ``reset`` when the target changes."""

    def __init__(self, params: ClosingParams, camera: CameraModel) -> None:
        self.p = params
        self.camera = camera
        self.reset()

    def reset(self) -> None:
        # The state in floats: (d, d_dot) and the covariance's (p00, p01, p11). Arrays per frame cost more than
        # this filter's arithmetic; ``x`` and ``P`` give them as arrays to whoever reads them.
        self._x: tuple[float, float] | None = None
        self._P: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self.t: float | None = None
        self.t_range: float | None = None  # time of the last range measured from a box
        self.filled = False  # a box reached max_box: the ring fills the view; no range from any box after it

    @property
    def x(self) -> np.ndarray | None:
        """The state (d, d_dot) as an array (a copy), None before the first range."""
        return None if self._x is None else np.array(self._x)

    @x.setter
    def x(self, value: np.ndarray | None) -> None:
        self._x = None if value is None else (float(value[0]), float(value[1]))

    @property
    def state(self) -> tuple[float, float] | None:
        """(d, d_dot) as floats, None before the first range."""
        return self._x

    @property
    def P_vv(self) -> float:
        """The range rate's variance, (m/s)^2."""
        return self._P[2]

    @property
    def P(self) -> np.ndarray:
        """The state covariance, 2x2 (a copy)."""
        p00, p01, p11 = self._P
        return np.array([[p00, p01], [p01, p11]])

    def speed(self, lambda_dot: float = 0.0, latency: float = 0.0) -> float:
        """The relative speed to use in the PN law, m/s, given the current LOS rate (rad/s).

        ``margin * |v_rel| + sigma`` with ``|v_rel|^2 = d_dot^2 + (d lambda_dot)^2`` (closing and crossing parts:
        the paper's v_rel is the relative speed, and a gate crossing the view needs the gain too), at most
        ``v_rel_bar``, and at most ``d / (lag_margin * (loop_lag + latency))``: PN's loop gain grows as
        ``N / t_go`` while the vehicle's lag (and the frame's age ``latency``, s) stays, so near the gate the gain
        is capped where the loop would ring."""
        if self._x is None:
            return self.p.v_rel_bar
        # max(a, b) written ``b if b > a else a`` and min(a, b) ``b if b < a else a``: the same value in every case
        # (ties, NaN), without the builtins' cost (~0.1 us a call; this runs every frame).
        p = self.p
        x0, x1 = self._x
        d = 0.0 if x0 < 0.0 else x0  # max(x0, 0.0)
        v_rel = math.hypot(x1, d * lambda_dot)
        pvv = self._P[2]
        v = p.margin * v_rel + math.sqrt(0.0 if pvv < 0.0 else pvv)
        if p.loop_lag > 0.0:
            cap = d / (p.lag_margin * (p.loop_lag + (0.0 if latency < 0.0 else latency)))
            v = cap if cap < v else v  # min(v, cap)
        v = v if v > p.v_min else p.v_min  # min(v_rel_bar, max(v_min, v))
        return v if v < p.v_rel_bar else p.v_rel_bar

    @property
    def range(self) -> float | None:
        return None if self._x is None else self._x[0]

    def range_from_box(self, box: BoundingBox) -> float | None:
        """Range to a ring of the configured radius from its box, or None (cut by the border, degenerate).

        Each image axis whose box edges are both inside the image gives the angle the ring subtends along it;
        the larger one is the ring's diameter (a tilted ring is foreshortened along the other axis only, which
        makes the range too long and the closing speed too high: the safe side for PN)."""
        if self.filled or self.fills(box):
            return None
        return self._range_of(box)

    def _range_of(self, box: BoundingBox) -> float | None:
        """:meth:`range_from_box` once the fill test has passed (``update`` has just made it: not twice a frame)."""
        cam, b = self.camera, self.p.border
        x0, y0, x1, y1 = box.xyxy
        alpha = 0.0
        # The angle between the rays through opposite edges (CameraModel.ray_angle: floats, no arrays).
        if x0 > b and x1 < cam.width - b:
            alpha = cam.ray_angle(x0, box.cy, x1, box.cy)
        if y0 > b and y1 < cam.height - b:
            a = cam.ray_angle(box.cx, y0, box.cx, y1)
            alpha = a if a > alpha else alpha  # max(alpha, a)
        if not (1e-6 < alpha < math.pi * 0.9):
            return None
        return self.p.gate_radius / math.tan(0.5 * alpha)

    def fills(self, box: BoundingBox) -> bool:
        """The box reaches ``max_box`` of the image's smaller side: the ring fills the view."""
        cam = self.camera
        w, h = box.w, box.h
        # max(w, h) >= max_box * min(width, height), without the builtins' cost (every frame)
        return self.p.max_box > 0.0 and (h if h > w else w) >= self.p.max_box * (
            cam.height if cam.height < cam.width else cam.width)

    def update(self, t: float, box: BoundingBox | None, range_accel: float | None = None) -> None:
        """Advance to frame time ``t`` with this frame's box (or None); ``range_accel`` is the range
        acceleration the vehicle's measured acceleration explains (m/s^2), None without an IMU."""
        p = self.p
        # Scalar 2-state Kalman filter: numpy's per-call overhead on 2x2 arrays dominated this 30 Hz path.
        predicted = False
        if self._x is not None and self.t is not None and t > self.t:
            dt = t - self.t
            imu = range_accel is not None and math.isfinite(range_accel)
            u = range_accel if imu else 0.0
            x0, x1 = self._x
            p00, p01, p11 = self._P
            x0, x1 = x0 + dt * x1 + 0.5 * dt * dt * u, x1 + dt * u  # x = F x + B u, F = [[1, dt], [0, 1]]
            q = (p.accel_noise_imu if imu else p.accel_noise) ** 2
            # P = F P F^T + Q (white-acceleration Q)
            p00, p01, p11 = (p00 + 2.0 * dt * p01 + dt * dt * p11 + q * dt**3 / 3.0,
                             p01 + dt * p11 + q * dt * dt / 2.0, p11 + q * dt)
            predicted = True
        if self.t is None or t > self.t:
            self.t = t
        if box is not None and not self.filled and self.fills(box):
            self.filled = True  # no range from any box until reset
        # range_from_box(box), its fill test just made above (filled now says it)
        d = self._range_of(box) if box is not None and not self.filled else None
        if d is None:
            if predicted:
                self._x, self._P = (x0, x1), (p00, p01, p11)
            return
        self.t_range = t
        size = box.h if box.h > box.w else box.w  # max(box.w, box.h)
        sigma = d * (p.pixel_noise * math.sqrt(2.0) / size + p.size_noise)
        if self._x is None:
            self._x = (d, -p.v_rel_bar)
            self._P = (sigma * sigma, 0.0, (0.5 * p.v_rel_bar) ** 2)
            return
        if not predicted:
            x0, x1 = self._x
            p00, p01, p11 = self._P
        s_ = p00 + sigma * sigma
        k0, k1 = p00 / s_, p01 / s_
        r = d - x0
        # x += K r;  P -= K P[0, :] (symmetric by construction)
        self._x = (x0 + k0 * r, x1 + k1 * r)
        self._P = (p00 - k0 * p00, p01 - k0 * p01, p11 - k1 * p01)

