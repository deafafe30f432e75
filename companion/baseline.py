"""Baseline of the paper's Table III: the PN acceleration controller of Bhattacharya et al. (2021).

As the paper describes it: the PN law commands an acceleration ``a = N V_c lambda_dot n`` with the
closing speed ``V_c`` *known* (they had GPS velocity; here the simulator's ground truth is passed
in explicitly), the speed along the LOS is held at a low constant value (5 m/s), and the
acceleration goes to PX4's acceleration controller, which turns it into a thrust vector
(``a - g``) with a tilt limit and points the camera (yaw) at the LOS. There is no field-of-view
constraint: that, and the slow speed, is what the PN-informed controller improves on.

The LOS comes from the same box -> ray -> world path as ours (perception/los.py), and the LOS
rate from the same filter and differencing (companion/guidance.py), so only the control law differs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from companion import guidance
from companion.frames import P_NED_ENU, R_from_quat_wxyz, euler_ned_deg_from_R
from perception.los import CameraModel, LosFilter
from perception.types import BoundingBox

if TYPE_CHECKING:
    from companion.config import Config


@dataclass(frozen=True, slots=True)
class BaselineOutput:
    t: float
    setpoint: guidance.Setpoint
    mode: str  # "pn" box used, "coast" no box (last LOS, no PN term), "hover" no LOS yet
    a_cmd: np.ndarray  # commanded acceleration, world ENU, m/s^2 (before the tilt limit)
    los_enu: np.ndarray | None = None  # the filtered LOS the command was built on, world ENU (None: no LOS yet)


class BaselinePN:
    """PN acceleration control with known velocity and speed hold."""

    def __init__(self, camera: CameraModel, nav_constant: float, speed: float, speed_gain: float,
                 max_tilt_rad: float, hover_thrust: float, thrust_min: float, f_max: float,
                 los_cutoff_hz: float, max_dt: float) -> None:
        self.camera = camera
        self.N = nav_constant
        self.speed = speed
        self.k_s = speed_gain
        self.max_tilt = max_tilt_rad
        self.hover_thrust = hover_thrust
        self.thrust_min = thrust_min
        self.f_max = f_max
        self.max_dt = max_dt
        self._filter = LosFilter(los_cutoff_hz, max_dt)
        self._l_prev: np.ndarray | None = None
        self._t_prev: float | None = None

    @classmethod
    def from_config(cls, cfg: Config) -> BaselinePN:
        b = cfg.sim.baseline
        return cls(CameraModel.from_config(cfg.camera), b.nav_constant, b.speed, b.speed_gain,
                   math.radians(b.max_tilt), cfg.airframe.hover_thrust, cfg.airframe.thrust_min,
                   cfg.airframe.f_max, cfg.los_filter.cutoff, cfg.los_filter.max_dt)

    def step(self, t: float, box: BoundingBox | None, q_wxyz_ned_frd: np.ndarray, v_enu: np.ndarray,
             v_rel_enu: np.ndarray) -> BaselineOutput:
        """One step. ``v_enu``: own velocity; ``v_rel_enu``: gate velocity minus own (both known here)."""
        R_ned_frd = R_from_quat_wxyz(q_wxyz_ned_frd)
        a_pn = np.zeros(3)
        mode = "coast"
        if box is not None and box.is_valid(self.camera.width, self.camera.height):
            l_enu = P_NED_ENU @ (R_ned_frd @ self.camera.ray_body(box.cx, box.cy))
            l_f = self._filter.update(t, l_enu)
            dt = t - self._t_prev if self._t_prev is not None else 0.0
            rate = guidance.los_rate(l_f, self._l_prev if 0.0 < dt <= self.max_dt else None, dt)
            closing = max(0.0, -float(l_f @ v_rel_enu))  # V_c = -d|r|/dt
            a_pn = self.N * closing * rate.lambda_dot * rate.n
            self._l_prev, self._t_prev = l_f.copy(), t
            mode = "pn"
        if self._l_prev is None:
            _, _, yaw = euler_ned_deg_from_R(R_ned_frd)
            sp = guidance.hover_setpoint(yaw, self.hover_thrust)
            return BaselineOutput(t, sp, "hover", np.zeros(3))
        los = self._l_prev
        a_cmd = a_pn + self.k_s * (self.speed - float(v_enu @ los)) * los
        return BaselineOutput(t, self._attitude(a_cmd, los), mode, a_cmd, los.copy())

    def _attitude(self, a_cmd: np.ndarray, los: np.ndarray) -> guidance.Setpoint:
        """PX4-style acceleration -> thrust vector with tilt limit; body x yawed at the LOS."""
        f = a_cmd - guidance.g_W
        if f[2] < 1e-3:
            f = np.array([f[0], f[1], 1e-3])
        horiz = math.hypot(f[0], f[1])
        lim = f[2] * math.tan(self.max_tilt)
        if horiz > lim:  # keep the vertical part (altitude first), shorten the horizontal one
            f = np.array([f[0] * lim / horiz, f[1] * lim / horiz, f[2]])
        f_th = min(float(np.linalg.norm(f)), self.f_max)
        z = f / np.linalg.norm(f)
        heading = np.array([los[0], los[1], 0.0])
        if np.linalg.norm(heading) < 1e-6:
            heading = np.array([1.0, 0.0, 0.0])
        x = heading - (heading @ z) * z
        x /= np.linalg.norm(x)
        R_W_B = np.column_stack((x, np.cross(z, x), z))
        return guidance.to_setpoint(R_W_B, f_th, self.hover_thrust, self.thrust_min)
