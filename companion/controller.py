"""The controller: ``(time, bounding box or None, attitude) -> setpoint``, and nothing else.

It accepts no position and no velocity: its only inputs are the box (pixels), the
attitude estimate (PX4's, from the IMU), optionally the accelerometer's specific force, and the
frame time. That is the point of the paper (control without full state estimation), and
``step``'s signature is the proof.

Data path of one frame, top to bottom:
  box centre (px) -> unit ray (intrinsics, distortion) -> body FRD (camera mount)
  -> world NED (attitude at capture) -> paper frame ENU -> LOS jump check -> LOS low-pass
  -> inertial LOS rate (lambda_dot, n) -> PN demand a_n -> closed-form thrust/attitude
  -> MAVSDK setpoint (NED/FRD degrees, normalised thrust).
The closing speed in the PN law is ``guidance.v_rel_bar`` (``closing_speed: fixed``, the paper) or, by
default, lowered from it on evidence by companion/closing.py: range from the box size and the
configured gate radius, filtered with the accelerometer when it is given.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Literal

import numpy as np

from companion import guidance
from companion.closing import ClosingParams, ClosingSpeedEstimator
from companion.frames import R_from_quat_wxyz_shared, euler_ned_deg_from_R, swap_ned_enu, swap_ned_enu_xyz
from companion.guidance import GuidanceParams, Setpoint
from companion.ownmotion import OwnMotion
from perception.fastinit import fast_init
from perception.los import CameraModel, LosFilter, LosKalman, LosKalmanParams
from perception.types import BoundingBox

# A 3-vector: an array, or three floats on the per-frame path.
Vec3 = np.ndarray | tuple[float, float, float]
# Max and min on the per-frame path: max(a, b) is written ``b if b > a else a`` and min(a, b) ``b if b < a else a``:
# the same value in every case (ties, signed zeros, NaN: the builtins keep the first argument unless a later one is
# strictly greater / smaller), at a tenth of the builtins' cost (~0.1 us a call, ~25 calls a frame).

if TYPE_CHECKING:
    from companion.config import Config

Mode = Literal["pn", "coast", "hover"]


@fast_init
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
    v_rel: float = math.nan  # closing speed the PN law used, m/s (v_rel_bar, or the estimate)


@fast_init
@dataclass(frozen=True, slots=True)
class ControllerParams:
    guidance: GuidanceParams
    hover_thrust: float
    thrust_min: float
    los_cutoff_hz: float
    max_los_rate: float  # rad/s; faster apparent LOS motion is a jump (tracker switched targets)
    max_dt: float  # s; a longer gap restarts the LOS filter
    rate_cutoff_hz: float = 0.0  # low-pass on the LOS rate vector; 0 = off
    rate_cutoff_min: float = 0.0  # Hz; > 0: the cut-off scheduled on the time to go down to this (_rate_cutoff)
    rate_cutoff_tgo: float = 2.0  # the scheduled cut-off is at least this / t_go (Hz)
    jump_reacquire_frames: int = 3  # consecutive "jumps" that agree are a real re-acquisition
    closing: ClosingParams | None = None  # None: the paper's fixed v_rel_bar
    drag_compensation: float = 0.0  # fraction of the measured drag normal to the LOS added to the PN demand
    drag_cutoff_hz: float = 2.0  # low-pass on the drag the accelerometer measures
    # Ring in view (guidance.ring_view_gamma): the FOV bound shrinks as the ring grows so that its rim stays in the
    # image (rad). view_margin None = off (the paper's fixed gamma_bar).
    view_margin: float | None = None
    gamma_min: float = math.radians(3.0)
    gate_radius: float = 0.0  # m, for the ring's angular size from the range estimate (0: from the box only)
    # Delay compensation (a Smith predictor on our own motion): the LOS rate of a late frame is brought forward by
    # the velocity our own commanded acceleration added since the frame was captured (the image shows it only
    # later). own_lag: time constant of the first-order model of how the commanded acceleration is reached.
    delay_compensation: bool = False
    own_lag: float = 0.2
    own_delay: float = 0.0  # s, pure delay before a command acts (airframe.response_time)
    own_drag_rate: float = 0.0  # 1/s, drag taking back the velocity we add (airframe.drag_rate)
    # Delay prediction: the relative state (range, range rate, LOS, LOS rate) propagated through the frame's age
    # (constant relative velocity, plus our own velocity change when delay_compensation is on).
    delay_prediction: bool = False
    # LOS estimation by a constant-velocity Kalman filter (los_filter.kind: kalman) instead of the low-pass +
    # differencing: None = the low-pass. Its measurement noise is kalman_px + kalman_px_rel * box size (px).
    los_kalman: LosKalmanParams | None = None
    kalman_px: float = 1.5
    kalman_px_rel: float = 0.03
    kalman_accel_width: float = 0.0  # px; > 0: process noise kalman_accel * (1 + box size / this)


def los_kalman_params(cfg: Config) -> LosKalmanParams | None:
    """The LOS Kalman filter's parameters (``los_filter.kind: kalman``), or None for the low-pass."""
    lf = cfg.los_filter
    if lf.kind != "kalman":
        return None
    return LosKalmanParams(accel_std=lf.kalman_accel, gate=lf.kalman_gate, reacquire=3, max_dt=lf.max_dt)


def closing_params(cfg: Config) -> ClosingParams | None:
    """The closing-speed estimator's parameters, or None for the paper's fixed v_rel_bar."""
    g = cfg.guidance
    if g.closing_speed == "fixed" or g.gate_radius <= 0.0:
        return None
    # The PN loop's lag: the vehicle's attitude response plus our two first-order filters (1 / (2 pi f_c) each).
    lag = cfg.airframe.response_time + 1.0 / (2.0 * math.pi * cfg.los_filter.cutoff)
    if cfg.los_filter.rate_cutoff > 0.0:
        lag += 1.0 / (2.0 * math.pi * cfg.los_filter.rate_cutoff)
    return ClosingParams(gate_radius=g.gate_radius, v_rel_bar=g.v_rel_bar, margin=g.closing_margin,
                         loop_lag=lag if g.lag_margin > 0.0 else 0.0, lag_margin=max(g.lag_margin, 1e-9),
                         max_box=g.closing_max_box)


class PNController:
    """PN-informed controller with its LOS filter state. One instance per engagement."""

    def __init__(self, params: ControllerParams, camera: CameraModel) -> None:
        self.p = params
        self.camera = camera
        self._filter = LosFilter(params.los_cutoff_hz, params.max_dt)
        self._kf = LosKalman(params.los_kalman) if params.los_kalman is not None else None
        self._closing = ClosingSpeedEstimator(params.closing, camera) if params.closing is not None else None
        self._half_fov = half_fov(camera)
        self.reset()

    @classmethod
    def from_config(cls, cfg: Config) -> PNController:
        # runtime import: config is a type-only import here
        from companion.config import camera_model, camera_uptilt

        camera = camera_model(cfg.camera)  # built once per camera section (a simulated run builds a controller)
        # A camera pitched up (about body y only) is part of the exact FOV bound (GuidanceParams.uptilt). Any
        # other mount: the solver bounds the angle between the LOS and body x, and a camera tilted off body x by
        # delta keeps the LOS within gamma_bar of the optical axis only if we ask for gamma_bar - delta.
        uptilt = camera_uptilt(cfg)
        misalign = 0.0 if uptilt is not None else math.acos(max(-1.0, min(1.0, float(camera.optical_axis_body[0]))))
        gp = GuidanceParams(
            k_pn=cfg.guidance.k_pn,
            v_rel_bar=cfg.guidance.v_rel_bar,
            gamma_bar=math.radians(cfg.guidance.gamma_bar) - misalign,
            uptilt=math.radians(uptilt or 0.0),
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
            rate_cutoff_hz=cfg.los_filter.rate_cutoff, rate_cutoff_min=cfg.los_filter.rate_cutoff_min,
            rate_cutoff_tgo=cfg.los_filter.rate_cutoff_tgo,
            closing=closing_params(cfg),
            drag_compensation=cfg.guidance.drag_compensation,
            view_margin=math.radians(cfg.guidance.view_margin) if cfg.guidance.keep_ring_in_view else None,
            gamma_min=math.radians(cfg.guidance.gamma_min),
            gate_radius=cfg.guidance.gate_radius,
            delay_compensation=cfg.guidance.delay_compensation,
            own_lag=cfg.guidance.delay_compensation_lag, own_delay=cfg.airframe.response_time,
            own_drag_rate=cfg.airframe.drag_rate,
            delay_prediction=cfg.guidance.delay_prediction,
            los_kalman=los_kalman_params(cfg), kalman_px=cfg.los_filter.kalman_px,
            kalman_px_rel=cfg.los_filter.kalman_px_rel, kalman_accel_width=cfg.los_filter.kalman_accel_width,
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
        if self._kf is not None:
            self._kf.reset()
        # Filtered LOS (ENU) of the last used frame, as floats: an array of it is made only where numpy's dot
        # product needs one (_l_prev_array).
        self._l_prev_xyz: tuple[float, float, float] | None = None
        self._t_prev: float | None = None
        self._t_last: float | None = None  # time of the last step, used or not
        self._jumps = 0
        self._w: tuple[float, float, float] | None = None  # filtered LOS rate vector lambda_dot * n (ENU), floats
        self._lam = 0.0  # last LOS rate, rad/s
        self._latency = 0.0  # age of the last frame when it reached us, s
        self._t_now: float | None = None  # the caller's time now (frame arrival), when given
        self._own = OwnMotion(self.p.own_lag, self.p.own_drag_rate)  # our commands since a frame (delay prediction)
        # Filtered aerodynamic acceleration (ENU) from the accelerometer, as floats (element-wise filter math).
        self._drag: tuple[float, float, float] | None = None
        self._t_drag: float | None = None
        if self._closing is not None:
            self._closing.reset()

    @property
    def has_los(self) -> bool:
        return self._l_prev_xyz is not None

    def _l_prev_array(self) -> np.ndarray:
        assert self._l_prev_xyz is not None
        return np.array(self._l_prev_xyz)

    @property
    def closing_rate(self) -> tuple[float, float] | None:
        """The closing-speed filter's range rate (m/s, negative when closing) and its standard deviation as of
        the last frame, None without the filter or before its first range (the target lock's speed bound)."""
        est = self._closing
        state = est.state if est is not None else None  # (a property: read once, every frame)
        if state is None:
            return None
        return state[1], math.sqrt(max(est.P_vv, 0.0))  # type: ignore[union-attr]

    @property
    def closing_estimate(self) -> tuple[float, float, float | None] | None:
        """The closing-speed filter's range (m) and range rate (m/s) as of the last frame, and when it last measured
        a range from a box (None: never); None without the filter or before its first range."""
        est = self._closing
        state = est.state if est is not None else None
        if state is None:
            return None
        return state[0], state[1], est.t_range  # type: ignore[union-attr]

    @property
    def drag_enu(self) -> np.ndarray | None:
        """The filtered aerodynamic acceleration (world ENU, m/s^2) the accelerometer measured, or None (no
        accelerometer given, or drag_compensation off). The straight pass cancels it."""
        return None if self._drag is None else np.array(self._drag)

    def step(self, t: float, box: BoundingBox | None, q_wxyz_ned_frd: np.ndarray,
             accel_frd: np.ndarray | None = None, t_now: float | None = None) -> ControlOutput:
        """One control step for the frame captured at ``t`` (s), with the attitude at that time and, if the
        caller has them, the accelerometer's specific force then (body FRD, m/s^2: closing speed and drag) and
        the current time on the same clock (``t_now - t`` is the frame's age: the gain allows for it)."""
        R_ned_frd = R_from_quat_wxyz_shared(q_wxyz_ned_frd)  # read only here: no copy of the cached matrix
        if t_now is not None and math.isfinite(t_now) and math.isfinite(t):
            age = t_now - t
            self._latency = age if age > 0.0 else 0.0  # max(0.0, age)
            self._t_now = t_now
        rejected = self._check(t, box)
        t_ok = math.isfinite(t) and (self._t_last is None or t > self._t_last)
        self._t_last = t if math.isfinite(t) else self._t_last
        if rejected is None:
            assert box is not None
            l_ned = R_ned_frd.dot(self.camera.ray_body(box.cx, box.cy))
            l_enu = swap_ned_enu_xyz(*l_ned.tolist())  # floats: the LOS checks and filter run on floats
            rejected = self._jump(t, l_enu, box)
            if rejected is None:
                self._closing_speed(t, box, R_ned_frd, accel_frd)
                self._update_drag(t, R_ned_frd, accel_frd)
                return self._pn(t, l_enu, R_ned_frd, box)
        if t_ok:
            self._closing_speed(t, None, R_ned_frd, accel_frd)
            self._update_drag(t, R_ned_frd, accel_frd)
        return self._no_box(t, R_ned_frd, rejected)

    def _update_drag(self, t: float, R_ned_frd: np.ndarray, accel_frd: np.ndarray | None) -> None:
        """Aerodynamic acceleration from the accelerometer: thrust acts along body z only, so the body x/y
        specific force is drag (the paper's f_aero / m), rotated to the world and low-passed."""
        if accel_frd is None or self.p.drag_compensation <= 0.0:
            return
        ax, ay = float(accel_frd[0]), float(accel_frd[1])
        if not (math.isfinite(ax) and math.isfinite(ay)):
            return
        # R[:, 0] ax + R[:, 1] ay and the low-pass in floats: numpy's element-wise products and sums, the same
        # bits, without ~8 array operations a frame.
        (r00, r01, _), (r10, r11, _), (r20, r21, _) = R_ned_frd.tolist()
        dx, dy, dz = swap_ned_enu_xyz(r00 * ax + r01 * ay, r10 * ax + r11 * ay, r20 * ax + r21 * ay)
        if self._drag is None or self._t_drag is None or not (0.0 < t - self._t_drag <= self.p.max_dt):
            self._drag = (dx, dy, dz)
        else:
            beta = 1.0 - math.exp(-2.0 * math.pi * self.p.drag_cutoff_hz * (t - self._t_drag))
            ox, oy, oz = self._drag
            self._drag = (ox + beta * (dx - ox), oy + beta * (dy - oy), oz + beta * (dz - oz))
        self._t_drag = t

    def _closing_speed(self, t: float, box: BoundingBox | None, R_ned_frd: np.ndarray,
                       accel_frd: np.ndarray | None) -> None:
        est = self._closing
        if est is None:
            return
        u = None
        d = est.range
        if accel_frd is not None and self._l_prev_xyz is not None and d is not None:
            # Range acceleration explained by our own motion: -a . l + d lambda_dot^2 (gate assumed unaccelerated).
            x, y, z = R_ned_frd.dot(np.asarray(accel_frd, dtype=float)).tolist()
            a_enu = np.array(swap_ned_enu_xyz(x + 0.0, y + 0.0, z + guidance.G))  # + [0, 0, g], element-wise
            u = -float(a_enu.dot(self._l_prev_array())) + d * self._lam * self._lam
        est.update(t, box, u)

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

    def _jump(self, t: float, l_enu: tuple[float, float, float], box: BoundingBox) -> str | None:
        """A LOS that moved faster than max_los_rate since the last used frame is a jump, unless it persists."""
        if self._l_prev_xyz is None or self._t_prev is None:
            return None
        dt = t - self._t_prev
        if dt > self.p.max_dt:
            return None  # long gap: the filter restarts anyway
        angle = guidance.angle_between(l_enu, self._l_prev_xyz)
        if angle / dt <= self.p.max_los_rate:
            self._jumps = 0
            return None
        self._jumps += 1
        if self._jumps >= self.p.jump_reacquire_frames:
            # The "jump" persisted: treat it as a new target and restart the filter there.
            self._jumps = 0
            self._filter.reset()
            if self._kf is not None:
                self._kf.reset()
            self._l_prev_xyz = None
            self._w = None
            est = self._closing
            if est is not None and not est.filled:
                # (Once the ring filled the view a LOS jump is the ring leaving it, not a new target: the range
                # stays dead-reckoned.) A jump *to* a box that fills the view is the ring filling it: the LOS of
                # a ring at arm's length jumps as its box saturates, and the jump's frames were rejected before
                # the filter saw their size. Forgetting the range there left nothing to dead-reckon (real PX4,
                # x500: steered at background boxes for 1.4 s after flying through).
                if est.fills(box):
                    est.filled = True
                else:
                    est.reset()
            return None
        return f"LOS jump ({math.degrees(angle):.1f} deg in {dt * 1e3:.0f} ms)"

    def _note_command(self, a: tuple[float, float, float]) -> None:
        """Remember the acceleration commanded now (world ENU, normal to the LOS) for the delay compensation."""
        t = self._t_now if self._t_now is not None else self._t_last
        if t is not None:
            self._own.note(t, a)

    def _predict_rate(self, t: float, lf: tuple[float, float, float], lam: float,
                      n: Vec3) -> tuple[float, Vec3]:
        """The LOS rate now, not at capture: ``dl/dt = v_rel_normal / d``, so our own velocity change since the
        capture, ``dv``, moves it by ``-dv_normal / d`` (d from the closing-speed range). The gate's own
        acceleration stays unknown."""
        d = self._closing.range if self._closing is not None else None
        t_now = self._t_now
        if d is None or d <= 0.5 or t_now is None or not self._own:
            return lam, n
        dv = self._own.dv(t - self.p.own_delay, t_now - self.p.own_delay)  # a command acts own_delay later
        l_f = np.array(lf)
        dv = dv - float(dv.dot(l_f)) * l_f
        w = lam * np.asarray(n, dtype=float) - dv / d
        lp = math.sqrt(w.dot(w))
        return lp, (w / lp if lp > 0.0 else np.zeros(3))

    def _predict_state(self, t: float, l_f: tuple[float, float, float], lam: float,
                       n: Vec3) -> tuple[Vec3, float, Vec3]:
        """The LOS and LOS rate now, not at capture: the relative position ``r = d l`` and velocity
        ``v = d_dot l + d lambda_dot n`` (range and range rate from the closing-speed filter) propagated through
        the frame's age at constant relative velocity, less our own velocity change (delay_compensation). For an
        unaccelerated gate the LOS rate grows as the range shrinks (``|r x v| / d^2`` is constant): a late frame
        shows the rate of a farther gate. The predicted range is floored at the ring's radius (closer, the
        frame no longer says where the ring's centre is)."""
        est = self._closing
        t_now = self._t_now
        if est is None or est.state is None or t_now is None or not (t_now > t):
            return l_f, lam, n
        d, d_dot = est.state
        if d <= 0.5:
            return l_f, lam, n
        tau = t_now - t
        # Element-wise parts in floats (the same operations as the array expressions, bit for bit); arrays only
        # where numpy's dot products must give their own rounding.
        (lx, ly, lz), (nx, ny, nz) = l_f, (n.tolist() if isinstance(n, np.ndarray) else n)
        dl = d * lam
        vx, vy, vz = d_dot * lx + dl * nx, d_dot * ly + dl * ny, d_dot * lz + dl * nz  # v = d_dot l + d lam n
        rx, ry, rz = d * lx + vx * tau, d * ly + vy * tau, d * lz + vz * tau  # r = d l + v tau
        if self.p.delay_compensation and self._own:
            t0, t1 = t - self.p.own_delay, t_now - self.p.own_delay  # a command acts own_delay after it is given
            (dvx, dvy, dvz), (dpx, dpy, dpz) = self._own.motion_xyz(t0, t1)
            rx, ry, rz = rx - dpx, ry - dpy, rz - dpz
            vx, vy, vz = vx - dvx, vy - dvy, vz - dvz
        r = np.array([rx, ry, rz])
        d2 = math.sqrt(r.dot(r))
        if not (d2 > 1e-6) or float(r.dot(np.array(l_f))) <= 0.0:
            return l_f, lam, n  # predicted past the gate: the frame says nothing about now
        l2x, l2y, l2z = rx / d2, ry / d2, rz / d2
        l2 = np.array([l2x, l2y, l2z])
        r_min = self.p.gate_radius
        d2 = r_min if r_min > d2 else d2  # max(d2, gate_radius, 0.5)
        d2 = 0.5 if d2 < 0.5 else d2
        c = float(np.array([vx, vy, vz]).dot(l2))
        wx, wy, wz = (vx - c * l2x) / d2, (vy - c * l2y) / d2, (vz - c * l2z) / d2  # w = (v - (v . l2) l2) / d2
        w = np.array([wx, wy, wz])
        lp = math.sqrt(w.dot(w))
        return l2, lp, ((wx / lp, wy / lp, wz / lp) if lp > 0.0 else (0.0, 0.0, 0.0))

    def _ring_angle(self, box: BoundingBox | None) -> float:
        """The ring's angular radius (rad): the larger of the range estimate's (``atan(r / d)``; it carries on
        through boxes cut by the border) and this box's (half its larger side; an under-estimate when cut)."""
        a = 0.0
        d = self._closing.range if self._closing is not None else None
        if d is not None and self.p.gate_radius > 0.0:
            a = math.atan2(self.p.gate_radius, 1e-3 if d < 1e-3 else d)  # max(d, 1e-3)
        if box is not None:
            f = float(self.camera.K[0, 0]) if box.w >= box.h else float(self.camera.K[1, 1])
            b = math.atan(0.5 * (box.h if box.h > box.w else box.w) / f)  # max(box.w, box.h)
            a = b if b > a else a  # max(a, b)
        return a

    def _gamma(self, box: BoundingBox | None) -> GuidanceParams:
        """The solver's parameters with the FOV bound that keeps the ring in view (when on)."""
        gp = self.p.guidance
        if self.p.view_margin is None:
            return gp
        g = guidance.ring_view_gamma(gp.gamma_bar, self._half_fov, self._ring_angle(box), self.p.view_margin,
                                     min(self.p.gamma_min, gp.gamma_bar))
        return gp if g >= gp.gamma_bar else guidance.with_gamma_bar(gp, g)

    def _pn(self, t: float, l_enu: tuple[float, float, float], R_ned_frd: np.ndarray,
            box: BoundingBox | None = None) -> ControlOutput:
        dt = t - self._t_prev if self._t_prev is not None else 0.0
        rejected = None
        # The filtered LOS as floats (lf); arrays of it only where numpy's dot products need them, and the output.
        if self._kf is not None:
            # The Kalman filter gives the LOS and its rate; a gated box leaves its prediction (PN goes on).
            size = (box.h if box.h > box.w else box.w) if box is not None else 0.0  # max(box.w, box.h)
            sigma = (self.p.kalman_px + self.p.kalman_px_rel * size) / float(self.camera.K[0, 0])
            # The LOS accelerates more as the gate nears (~1/range^2): optionally more process noise for a bigger box.
            w0 = self.p.kalman_accel_width
            acc = self._kf.p.accel_std * (1.0 + size / w0) if w0 > 0.0 else None
            if not self._kf.update(t, np.array(l_enu), sigma, acc):
                rejected = f"innovation gate ({self._kf.last_nis:.1f} sigma)"
            assert self._kf.l is not None
            lf = tuple(self._kf.l.tolist())
            lambda_dot, n = self._smooth_rate(lf, self._kf.rate, dt)
        else:
            lf = self._filter.update_xyz(t, *l_enu)
            w_xyz = guidance.los_rate_vector(lf, self._l_prev_xyz if dt <= self.p.max_dt else None, dt)
            lambda_dot, n = self._smooth_rate(lf, w_xyz, dt)
        self._lam = lambda_dot
        l_sol: Vec3 = lf
        if self.p.delay_prediction:
            l_sol, lambda_dot, n = self._predict_state(t, lf, lambda_dot, n)
        elif self.p.delay_compensation:
            lambda_dot, n = self._predict_rate(t, lf, lambda_dot, n)
        gp = self.p.guidance
        v_rel = self._closing.speed(lambda_dot, self._latency) if self._closing is not None else gp.v_rel_bar
        ax, ay, az = guidance.pn_demand_xyz(lambda_dot, n, gp.k_pn, v_rel)
        # The PN frame's y axis of the filtered LOS and the measured drag along it: only the drag terms below use
        # them (computed once, when there is a drag estimate). Element-wise math in floats from here (the same
        # operations as the array expressions, bit for bit); the drag's dot product stays numpy's.
        y_xyz = _y_pn_xyz(lf) if self._drag is not None else None
        drag_y = (float(np.array(self._drag).dot(np.array(y_xyz))) if self._drag is not None and y_xyz is not None
                  else 0.0)
        if y_xyz is not None and self.p.drag_compensation > 0.0:
            # The paper assumes drag along the LOS. Chasing a gate that moves sideways, drag has a horizontal part
            # normal to the LOS that PN would have to beat with a persistent LOS rate: cancel that part. (The
            # accelerometer misses drag along the thrust axis, so the vertical normal part is not trusted.)
            c = self.p.drag_compensation * drag_y
            yx, yy, yz = y_xyz
            ax, ay, az = ax - c * yx, ay - c * yy, az - c * yz  # a_n - c y_pn
        f_th, _, _, R_W_B, scale, _ = guidance.solve_fields(l_sol, (ax, ay, az), self._gamma(box),
                                                            self._y_ref(l_sol, R_ned_frd))
        self._l_prev_xyz, self._t_prev = lf, t
        if self.p.delay_compensation:
            # Our net acceleration normal to the LOS: thrust and gravity give the honoured demand; the drag the
            # accelerometer measures acts on top (the compensation above only cancels it in the command).
            nx, ny, nz = scale * ax, scale * ay, scale * az
            if y_xyz is not None:
                yx, yy, yz = y_xyz
                nx, ny, nz = nx + drag_y * yx, ny + drag_y * yy, nz + drag_y * yz
            self._note_command((nx, ny, nz))
        sp = guidance.to_setpoint(R_W_B, f_th, self.p.hover_thrust, self.p.thrust_min)
        return ControlOutput(t, sp, "pn", np.array(swap_ned_enu_xyz(*lf)), lambda_dot, np.array((ax, ay, az)),
                             scale, f_th, rejected, v_rel)

    def _smooth_rate(self, l_f: tuple[float, float, float], w: np.ndarray | tuple[float, float, float],
                     dt: float) -> tuple[float, tuple[float, float, float]]:
        """Optional first-order low-pass on the LOS rate vector: differencing a 30 Hz LOS amplifies
        pixel noise, and k_PN v_rel_bar (~30 m/s) turns it into thrust jitter. Kept normal to the LOS."""
        wx, wy, wz = w.tolist() if isinstance(w, np.ndarray) else w  # scalar math: this runs every frame
        if self.p.rate_cutoff_hz > 0.0:
            if self._w is None or not (0.0 < dt <= self.p.max_dt):
                self._w = (wx, wy, wz)
            else:
                beta = 1.0 - math.exp(-2.0 * math.pi * self._rate_cutoff() * dt)
                ox, oy, oz = self._w
                wx, wy, wz = ox + beta * (wx - ox), oy + beta * (wy - oy), oz + beta * (wz - oz)
                lx, ly, lz = l_f
                d = wx * lx + wy * ly + wz * lz
                wx, wy, wz = wx - d * lx, wy - d * ly, wz - d * lz
                self._w = (wx, wy, wz)
        lam = math.sqrt(wx * wx + wy * wy + wz * wz)
        return lam, ((wx / lam, wy / lam, wz / lam) if lam > 0.0 else (0.0, 0.0, 0.0))

    def _rate_cutoff(self) -> float:
        """The LOS-rate low-pass's cut-off now (Hz). Scheduled on the time to go (when rate_cutoff_min > 0): PN's
        loop must act within ~t_go, so a filter lag of ``1 / (2 pi f_c)`` costs nothing while it is a small part
        of it, ``f_c >= rate_cutoff_tgo / t_go``; far from the gate the cut-off drops to rate_cutoff_min and the
        box noise the gain ``k_PN v_rel`` turns into attitude jitter with it. t_go is the range over the closing
        speed less the frame's age (the frame is that much nearer now)."""
        fc = self.p.rate_cutoff_hz
        est = self._closing
        if self.p.rate_cutoff_min <= 0.0 or est is None or est.state is None:
            return fc
        d, d_dot = est.state
        if d_dot >= -0.5:  # not closing: no time to go
            return fc
        t_go = d / -d_dot - self._latency
        if t_go <= 0.0:
            return fc
        f = self.p.rate_cutoff_tgo / t_go
        f = f if f < fc else fc  # max(rate_cutoff_min, min(fc, f))
        return f if f > self.p.rate_cutoff_min else self.p.rate_cutoff_min

    def _no_box(self, t: float, R_ned_frd: np.ndarray, rejected: str) -> ControlOutput:
        zero = np.zeros(3)
        if self._l_prev_xyz is None:
            _, _, yaw = euler_ned_deg_from_R(R_ned_frd)
            sp = guidance.hover_setpoint(yaw, self.p.hover_thrust)
            return ControlOutput(t, sp, "hover", None, 0.0, zero, 0.0, guidance.G, rejected)
        # Coast: keep flying along the last inertial LOS with no PN demand until the box returns
        # (the app's safety layer decides when "lost" becomes an abort).
        l_prev = self._l_prev_xyz
        sol = guidance.solve(l_prev, zero, self._gamma(None), y_ref=self._y_ref(l_prev, R_ned_frd))
        sp = guidance.to_setpoint(sol.R_W_B, sol.f_th, self.p.hover_thrust, self.p.thrust_min)
        return ControlOutput(t, sp, "coast", np.array(swap_ned_enu_xyz(*l_prev)), 0.0, zero, sol.demand_scale, sol.f_th,
                             rejected)

    @staticmethod
    def _y_ref(l_enu: Vec3, R_ned_frd: np.ndarray) -> np.ndarray | None:
        """The solver's y_ref: pn_frame reads it only at a vertical LOS (its own test, ``hypot(l_x, l_y) <= 1e-9``),
        so elsewhere it is not built (a slice, a matmul and a negation every frame)."""
        lx, ly, _ = l_enu.tolist() if isinstance(l_enu, np.ndarray) else l_enu
        return None if math.hypot(lx, ly) > 1e-9 else PNController._body_y_enu(R_ned_frd)

    @staticmethod
    def _body_y_enu(R_ned_frd: np.ndarray) -> np.ndarray:
        # FLU y = -FRD y; re-expressed in ENU. Only used to orient the PN frame at a vertical LOS.
        return -swap_ned_enu(R_ned_frd[:, 1])




def _y_pn_xyz(l_enu: tuple[float, float, float]) -> tuple[float, float, float] | None:
    """The PN frame's y axis (``e_z x l`` normalised: horizontal, normal to the LOS), None at a vertical LOS."""
    lx, ly, _ = l_enu
    h = math.hypot(lx, ly)
    return (-ly / h, lx / h, 0.0) if h > 1e-6 else None


def half_fov(camera: CameraModel) -> float:
    """The smallest angle from the optical axis to an image border (rad; pinhole, distortion ignored): a ring
    within it of the optical axis is in the image whichever way the gate sits."""
    K = camera.K
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    return min(math.atan2(cx, fx), math.atan2(camera.width - cx, fx), math.atan2(cy, fy),
               math.atan2(camera.height - cy, fy))
