"""The controller: ``(time, bounding box or None, attitude) -> setpoint``, and nothing else.

It accepts no position and no velocity: its only inputs are the box (pixels), the
attitude estimate (PX4's, from the IMU) and the frame time. That is the point of the
paper (control without full state estimation), and ``step``'s signature is the proof.

Data path of one frame, top to bottom:
  box centre (px) -> unit ray (intrinsics, distortion) -> body FRD (camera mount)
  -> world NED (attitude at capture) -> paper frame ENU -> LOS jump check -> LOS low-pass
  -> inertial LOS rate (lambda_dot, n) -> PN demand a_n -> closed-form thrust/attitude
  -> MAVSDK setpoint (NED/FRD degrees, normalised thrust).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Literal

import numpy as np

from companion import guidance
from companion.frames import P_NED_ENU, R_from_quat_wxyz, euler_ned_deg_from_R
from companion.guidance import GuidanceParams, Setpoint
from perception.los import CameraModel, LosFilter
from perception.types import BoundingBox

if TYPE_CHECKING:
    from companion.config import Config

Mode = Literal["pn", "coast", "hover"]


@dataclass(frozen=True, slots=True)
class ControlOutput:
    t: float
    setpoint: Setpoint
    mode: Mode  # pn: box used; coast: no usable box, last LOS held with zero PN demand; hover: no LOS yet
    los_ned: np.ndarray | None  # filtered world LOS (unit, NED) the setpoint was computed from
    lambda_dot: float  # rad/s
    a_n: np.ndarray  # PN demand, world ENU, m/s^2 (before saturation)
    demand_scale: float  # fraction of a_n the solver could honour (1 = all)
    f_th: float  # commanded mass-normalised thrust, m/s^2
    rejected: str | None  # why this frame's box was not used, if it was not


@dataclass(frozen=True, slots=True)
class ControllerParams:
    guidance: GuidanceParams
    hover_thrust: float
    thrust_min: float
    los_cutoff_hz: float
    max_los_rate: float  # rad/s; faster apparent LOS motion is a jump (tracker switched targets)
    max_dt: float  # s; a longer gap restarts the LOS filter
    rate_cutoff_hz: float = 0.0  # low-pass on the LOS rate vector; 0 = off
    jump_reacquire_frames: int = 3  # consecutive "jumps" that agree are a real re-acquisition


class PNController:
    """PN-informed controller with its LOS filter state. One instance per engagement."""

    def __init__(self, params: ControllerParams, camera: CameraModel) -> None:
        self.p = params
        self.camera = camera
        self._filter = LosFilter(params.los_cutoff_hz, params.max_dt)
        self.reset()

    @classmethod
    def from_config(cls, cfg: Config) -> PNController:
        camera = CameraModel.from_config(cfg.camera)
        # The solver bounds the angle between the LOS and body x; a camera tilted off body x by
        # delta keeps the LOS within gamma_bar of the optical axis only if we ask for gamma_bar - delta.
        misalign = math.acos(max(-1.0, min(1.0, float(camera.optical_axis_body[0]))))
        gp = GuidanceParams(
            k_pn=cfg.guidance.k_pn,
            v_rel_bar=cfg.guidance.v_rel_bar,
            gamma_bar=math.radians(cfg.guidance.gamma_bar) - misalign,
            f_max=cfg.airframe.f_max,
            f_min=cfg.airframe.f_min,
            fov=cfg.guidance.fov,
            max_tilt=math.radians(cfg.airframe.max_tilt),
        )
        cp = ControllerParams(
            guidance=gp,
            hover_thrust=cfg.airframe.hover_thrust,
            thrust_min=cfg.airframe.thrust_min,
            los_cutoff_hz=cfg.los_filter.cutoff,
            max_los_rate=cfg.los_filter.max_rate,
            max_dt=cfg.los_filter.max_dt,
            rate_cutoff_hz=cfg.los_filter.rate_cutoff,
        )
        return cls(cp, camera)

    def with_hover_thrust(self, hover_thrust: float, thrust_to_weight: float) -> PNController:
        """A fresh controller for the hover thrust the autopilot reports (MPC_THR_HOVER)."""
        if not (0.05 < hover_thrust < 0.95):
            raise ValueError(f"hover thrust {hover_thrust} outside (0.05, 0.95)")
        f_max = guidance.G * min(thrust_to_weight, 1.0 / hover_thrust)
        f_min = guidance.G * self.p.thrust_min / hover_thrust
        gp = replace(self.p.guidance, f_max=f_max, f_min=f_min)
        return PNController(replace(self.p, guidance=gp, hover_thrust=hover_thrust), self.camera)

    def reset(self) -> None:
        self._filter.reset()
        self._l_prev: np.ndarray | None = None  # filtered LOS (ENU) of the last used frame
        self._t_prev: float | None = None
        self._t_last: float | None = None  # time of the last step, used or not
        self._jumps = 0
        self._w: np.ndarray | None = None  # filtered LOS rate vector lambda_dot * n (ENU)

    @property
    def has_los(self) -> bool:
        return self._l_prev is not None

    def step(self, t: float, box: BoundingBox | None, q_wxyz_ned_frd: np.ndarray) -> ControlOutput:
        """One control step for the frame captured at ``t`` (s), with the attitude at that time."""
        R_ned_frd = R_from_quat_wxyz(q_wxyz_ned_frd)
        rejected = self._check(t, box)
        self._t_last = t if math.isfinite(t) else self._t_last
        if rejected is None:
            assert box is not None
            l_ned = R_ned_frd @ self.camera.ray_body(box.cx, box.cy)
            l_enu = P_NED_ENU @ l_ned
            rejected = self._jump(t, l_enu)
            if rejected is None:
                return self._pn(t, l_enu, R_ned_frd)
        return self._no_box(t, R_ned_frd, rejected)

    # -- internals -------------------------------------------------------------------------

    def _check(self, t: float, box: BoundingBox | None) -> str | None:
        if not math.isfinite(t):
            return "non-finite frame time"
        if self._t_last is not None and t <= self._t_last:
            return "frame time not after the previous one"
        if box is None:
            return "no box"
        if not box.is_valid(self.camera.width, self.camera.height):
            return f"invalid box ({box.cx}, {box.cy}, {box.w}, {box.h})"
        return None

    def _jump(self, t: float, l_enu: np.ndarray) -> str | None:
        """A LOS that moved faster than max_los_rate since the last used frame is a jump, unless it persists."""
        if self._l_prev is None or self._t_prev is None:
            return None
        dt = t - self._t_prev
        if dt > self.p.max_dt:
            return None  # long gap: the filter restarts anyway
        angle = guidance.angle_between(l_enu, self._l_prev)
        if angle / dt <= self.p.max_los_rate:
            self._jumps = 0
            return None
        self._jumps += 1
        if self._jumps >= self.p.jump_reacquire_frames:
            # The "jump" persisted: treat it as a new target and restart the filter there.
            self._jumps = 0
            self._filter.reset()
            self._l_prev = None
            self._w = None
            return None
        return f"LOS jump ({math.degrees(angle):.1f} deg in {dt * 1e3:.0f} ms)"

    def _pn(self, t: float, l_enu: np.ndarray, R_ned_frd: np.ndarray) -> ControlOutput:
        l_f = self._filter.update(t, l_enu)
        dt = t - self._t_prev if self._t_prev is not None else 0.0
        rate = guidance.los_rate(l_f, self._l_prev if dt <= self.p.max_dt else None, dt)
        lambda_dot, n = self._smooth_rate(l_f, rate.lambda_dot * rate.n, dt)
        gp = self.p.guidance
        a_n = guidance.pn_demand(lambda_dot, n, gp.k_pn, gp.v_rel_bar)
        sol = guidance.solve(l_f, a_n, gp, y_ref=self._body_y_enu(R_ned_frd))
        self._l_prev, self._t_prev = l_f.copy(), t
        sp = guidance.to_setpoint(sol.R_W_B, sol.f_th, self.p.hover_thrust, self.p.thrust_min)
        return ControlOutput(t, sp, "pn", P_NED_ENU @ l_f, lambda_dot, a_n, sol.demand_scale, sol.f_th, None)

    def _smooth_rate(self, l_f: np.ndarray, w: np.ndarray, dt: float) -> tuple[float, np.ndarray]:
        """Optional first-order low-pass on the LOS rate vector: differencing a 30 Hz LOS amplifies
        pixel noise, and k_PN v_rel_bar (~30 m/s) turns it into thrust jitter. Kept normal to the LOS."""
        wx, wy, wz = w.tolist()  # scalar math: this runs every frame
        if self.p.rate_cutoff_hz > 0.0:
            if self._w is None or not (0.0 < dt <= self.p.max_dt):
                self._w = w.copy()
            else:
                beta = 1.0 - math.exp(-2.0 * math.pi * self.p.rate_cutoff_hz * dt)
                ox, oy, oz = self._w.tolist()
                wx, wy, wz = ox + beta * (wx - ox), oy + beta * (wy - oy), oz + beta * (wz - oz)
                lx, ly, lz = l_f.tolist()
                d = wx * lx + wy * ly + wz * lz
                wx, wy, wz = wx - d * lx, wy - d * ly, wz - d * lz
                self._w = np.array([wx, wy, wz])
        lam = math.sqrt(wx * wx + wy * wy + wz * wz)
        return lam, (np.array([wx / lam, wy / lam, wz / lam]) if lam > 0.0 else np.zeros(3))

    def _no_box(self, t: float, R_ned_frd: np.ndarray, rejected: str) -> ControlOutput:
        zero = np.zeros(3)
        if self._l_prev is None:
            _, _, yaw = euler_ned_deg_from_R(R_ned_frd)
            sp = guidance.hover_setpoint(yaw, self.p.hover_thrust)
            return ControlOutput(t, sp, "hover", None, 0.0, zero, 0.0, guidance.G, rejected)
        # Coast: keep flying along the last inertial LOS with no PN demand until the box returns
        # (the app's safety layer decides when "lost" becomes an abort).
        sol = guidance.solve(self._l_prev, zero, self.p.guidance, y_ref=self._body_y_enu(R_ned_frd))
        sp = guidance.to_setpoint(sol.R_W_B, sol.f_th, self.p.hover_thrust, self.p.thrust_min)
        return ControlOutput(t, sp, "coast", P_NED_ENU @ self._l_prev, 0.0, zero, sol.demand_scale, sol.f_th, rejected)

    @staticmethod
    def _body_y_enu(R_ned_frd: np.ndarray) -> np.ndarray:
        # FLU y = -FRD y; re-expressed in ENU. Only used to orient the PN frame at a vertical LOS.
        return -(P_NED_ENU @ R_ned_frd[:, 1])
