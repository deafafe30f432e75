"""PN-informed guidance: the paper's section IV in pure numpy (no I/O, no state, no asyncio).

Frames: world W is ENU-like with z up and ``g = [0, 0, -G]``; body B is FLU (x = optical
axis, z = thrust axis). Thrust ``f_th`` is mass-normalised (m/s^2) throughout, as in the
paper's simplified problem. Names follow the paper's symbols:

=====================================  ==========================================
paper                                   here
=====================================  ==========================================
lambda_dot = f_est arccos(l . l_prev)   :func:`los_rate` -> ``lambda_dot``
k_l = l x l_prev,  n = l x k_l          :func:`los_rate` -> ``k_l``, ``n``
eq:meth_pn_guidance_law (a_n)           :func:`pn_demand`
eq:meth_rotation_pn_world (R_PN^W)      :func:`pn_frame`
eq:meth_optimization_problem_roll_pitch :func:`roll_pitch`
f_th*, phi*, theta* (closed form)       :func:`solve`
saturation of infeasible demands        :func:`demand_scale`
R_B^W = R_PN^W R_y(phi) R_x(theta)      :func:`solve` -> ``R_W_B``
MAVSDK setpoint (NED/FRD, deg, 0..1)    :func:`to_setpoint`
=====================================  ==========================================

Field-of-view bound. With ``R_B^PN = R_y(phi) R_x(theta)`` the optical axis is ``R_y(phi) e_x``:
the real angle between it and the LOS is ``phi`` alone (roll turns the vehicle about the LOS).
The paper bounds ``cos(phi) cos(theta) >= cos(gamma_bar)``, which is stricter than needed and
caps the acceleration normal to the LOS at ``g tan(gamma_bar)`` sideways. ``fov="exact"`` (the
default) bounds the real angle, ``phi <= gamma_bar``, i.e. ``f^2 - t_y^2 <= (t_z / cos gamma_bar)^2``,
so the optimum is ``f* = min(f_max, hypot(t_y, t_z / cos(gamma_bar)))``. ``fov="paper"`` keeps the
paper's ``f* = min(f_max, t_z / cos(gamma_bar))`` to reproduce its derivation.

Saturation rule (the paper leaves infeasible demands open). With ``t = s a_n^PN - g^PN``
restricted to the PN y-z plane (the thrust components normal to the LOS that the demand
fixes), a demand is feasible when the largest thrust the FOV bound allows reaches f_min, (a), when
``|t| <= f_max``, (b), and for ``fov="paper"`` when ``|t_y| <= t_z tan(gamma_bar)``, (c). For "paper",
(a) is ``t_z >= f_min cos(gamma_bar)``; all three are convex in ``t``, so the feasible scales ``s``
form an interval. For "exact", (a) is ``t_z > 0`` and ``t_y^2 + (t_z / cos gamma_bar)^2 >= f_min^2``,
the outside of an ellipse: along ``t(s)`` the feasible scales are ``[0, r1]`` or ``[r2, ...]``.
Either way we take the largest feasible ``s`` in [0, 1]: the normal demand keeps its direction and
is scaled down just enough.
If even ``s = 0`` is infeasible (LOS steeper than the FOV bound allows with f_min, or an
airframe too weak to hold the LOS), the vehicle points its optical axis along the LOS
(phi = theta = 0) with ``f = clip(t_z, f_min, f_max)``: the FOV bound holds exactly and
the thrust stays in its limits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.frames import euler_ned_deg_from_R, quat_wxyz_from_R

G = 9.81
g_W = np.array([0.0, 0.0, -G])

_EPS = 1e-12
_ENU_TO_NED_ROWS = [1, 0, 2]
_NED_FRD_SIGNS = np.outer([1.0, 1.0, -1.0], [1.0, -1.0, -1.0])  # row signs of P_NED_ENU x column signs of F_FRD_FLU


@dataclass(frozen=True, slots=True)
class GuidanceParams:
    """Everything the solver needs. Angles in radians, thrusts mass-normalised (m/s^2)."""

    k_pn: float
    v_rel_bar: float
    gamma_bar: float
    f_max: float
    f_min: float
    fov: str = "exact"  # "exact": bound the real LOS-to-optical-axis angle; "paper": cos(phi) cos(theta)

    def __post_init__(self) -> None:
        if self.fov not in ("exact", "paper"):
            raise ValueError(f"fov must be 'exact' or 'paper', got {self.fov!r}")
        if not (0.0 < self.gamma_bar < math.pi / 2):
            raise ValueError(f"gamma_bar must be in (0, pi/2) rad, got {self.gamma_bar}")
        if not (0.0 < self.f_min < self.f_max):
            raise ValueError(f"need 0 < f_min < f_max, got f_min={self.f_min}, f_max={self.f_max}")


@dataclass(frozen=True, slots=True)
class LosRate:
    lambda_dot: float  # rad/s, >= 0
    k_l: np.ndarray  # l x l_prev (not normalised, as in the paper)
    n: np.ndarray  # unit normal direction of the PN acceleration; zero when lambda_dot == 0


@dataclass(frozen=True, slots=True)
class ThrustAttitude:
    f_th: float  # mass-normalised thrust, m/s^2
    phi: float  # pitch about PN y, rad
    theta: float  # roll about PN x, rad
    R_W_B: np.ndarray  # commanded attitude, body FLU -> world
    demand_scale: float  # s in [0, 1]: 1 = PN demand met exactly
    fallback: bool  # True when even s = 0 was infeasible (optical axis on the LOS)


def angle_between(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two vectors, accurate for small and large angles alike."""
    ax, ay, az = a.tolist()
    bx, by, bz = b.tolist()
    cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    return math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz), ax * bx + ay * by + az * bz)


def los_rate(l: np.ndarray, l_prev: np.ndarray | None, dt: float) -> LosRate:  # noqa: E741
    """Inertial LOS rate from two consecutive world-frame unit LOS vectors, ``dt`` apart.

    ``lambda_dot = arccos(l . l_prev) / dt`` (the paper's ``f_est = 1/dt``), computed as
    ``atan2(|l x l_prev|, l . l_prev)`` which is exact for small angles where arccos is not.
    """
    if l_prev is None or not (dt > 0.0) or not math.isfinite(dt):
        return LosRate(0.0, np.zeros(3), np.zeros(3))
    # Scalar math: numpy's per-call overhead on 3-vectors dominates this 30 Hz path.
    lx, ly, lz = l.tolist()
    px, py, pz = l_prev.tolist()
    kx, ky, kz = ly * pz - lz * py, lz * px - lx * pz, lx * py - ly * px  # k_l = l x l_prev
    s = math.sqrt(kx * kx + ky * ky + kz * kz)
    if s < _EPS:
        return LosRate(0.0, np.array([kx, ky, kz]), np.zeros(3))
    angle = math.atan2(s, lx * px + ly * py + lz * pz)
    # n = l x k_l / |k_l|: |l x k_l| = |k_l| because k_l is normal to the unit vector l.
    n = np.array([ly * kz - lz * ky, lz * kx - lx * kz, lx * ky - ly * kx]) / s
    return LosRate(angle / dt, np.array([kx, ky, kz]), n)


def pn_demand(lambda_dot: float, n: np.ndarray, k_pn: float, v_rel_bar: float) -> np.ndarray:
    """eq:meth_pn_guidance_law: ``a_n = k_PN * v_rel_bar * lambda_dot * n``."""
    return (k_pn * v_rel_bar * lambda_dot) * n


def pn_frame(l: np.ndarray, y_ref: np.ndarray | None = None) -> np.ndarray:  # noqa: E741
    """eq:meth_rotation_pn_world: ``R_PN^W = [l, e_z x l, l x (e_z x l)]`` with unit columns.

    Singular when the LOS is vertical (``e_z x l = 0``): then the y axis is taken from
    ``y_ref`` (default world y) made normal to ``l``, so the frame stays orthonormal.
    """
    lx, ly, lz = l.tolist()
    ny = math.hypot(lx, ly)
    if ny > 1e-9:
        yx, yy, yz = -ly / ny, lx / ny, 0.0  # e_z x l, normalised
    else:
        rx, ry, rz = (0.0, 1.0, 0.0) if y_ref is None else np.asarray(y_ref, dtype=float).tolist()
        d = rx * lx + ry * ly + rz * lz
        yx, yy, yz = rx - d * lx, ry - d * ly, rz - d * lz
        n = math.sqrt(yx * yx + yy * yy + yz * yz)
        if n < 1e-9:  # y_ref parallel to l: any normal will do
            yx, yy, yz = 1.0 - lx * lx, -lx * ly, -lx * lz
            n = math.sqrt(yx * yx + yy * yy + yz * yz)
        yx, yy, yz = yx / n, yy / n, yz / n
    zx, zy, zz = ly * yz - lz * yy, lz * yx - lx * yz, lx * yy - ly * yx  # l x y
    return np.array([[lx, yx, zx], [ly, yy, zy], [lz, yz, zz]])


def roll_pitch(f_th: float, t_y: float, t_z: float) -> tuple[float, float]:
    """eq:meth_optimization_problem_roll_pitch for thrust components ``t = (t_y, t_z)`` normal to the LOS.

    ``t_y = n_y a_n - g_y^PN`` and ``t_z = n_z a_n - g_z^PN`` (the paper has ``g_y^PN = 0``).
    Returns (theta, phi). Arguments are clipped to [-1, 1] against rounding only: callers
    pass feasible inputs.
    """
    theta = math.asin(max(-1.0, min(1.0, -t_y / f_th)))
    c = math.sqrt(max(f_th * f_th - t_y * t_y, 0.0))
    phi = math.acos(max(-1.0, min(1.0, t_z / c))) if c > _EPS else 0.0
    return theta, phi


def _max_scale_linear(c0: float, c1: float) -> float:
    """Largest s >= 0 with c0 + c1 s >= 0 (given c0 >= 0)."""
    return math.inf if c1 >= 0.0 else c0 / -c1


def demand_scale(a_y: float, a_z: float, g_y: float, g_z: float, p: GuidanceParams) -> float | None:
    """Largest s in [0, 1] for which the demand ``s * (a_y, a_z)`` is feasible; None if s = 0 is not.

    See the module docstring for the constraints (a), (b), (c).
    """
    cg = math.cos(p.gamma_bar)
    # Linear constraints c0 + c1 s >= 0, with t_y = s a_y - g_y and t_z = s a_z - g_z.
    if p.fov == "paper":
        tg = math.tan(p.gamma_bar)
        lin: tuple[tuple[float, float], ...] = (
            (-g_z - p.f_min * cg, a_z),  # (a) t_z >= f_min cos(gamma_bar)
            (-g_z * tg + g_y, a_z * tg - a_y),  # (c) t_z tan - t_y >= 0
            (-g_z * tg - g_y, a_z * tg + a_y),  # (c) t_z tan + t_y >= 0
        )
    else:
        lin = ((-g_z - 1e-9 * G, a_z),)  # (a) t_z > 0: the optical axis can be within 90 deg of the LOS
    # (b) |s A - G|^2 <= f_max^2  <=>  qa s^2 + qb s + qc <= 0
    qa = a_y * a_y + a_z * a_z
    qb = -2.0 * (a_y * g_y + a_z * g_z)
    qc = g_y * g_y + g_z * g_z - p.f_max * p.f_max
    # (a), exact: h(s) = t_y^2 + (t_z / cos)^2 - f_min^2 >= 0, a convex quadratic in s
    ha = a_y * a_y + (a_z / cg) ** 2
    hb = -2.0 * (a_y * g_y + a_z * g_z / (cg * cg))
    hc = g_y * g_y + (g_z / cg) ** 2 - p.f_min * p.f_min
    tol = 1e-12 * (1.0 + p.f_max * p.f_max)
    if any(c0 < -1e-12 * (1.0 + abs(c0)) for c0, _ in lin) or qc > tol:
        return None
    if p.fov == "exact" and hc < -tol:
        return None
    s = 1.0
    for c0, c1 in lin:
        s = min(s, _max_scale_linear(max(c0, 0.0), c1))
    if qa > _EPS:
        s = min(s, (-qb + math.sqrt(max(qb * qb - 4.0 * qa * qc, 0.0))) / (2.0 * qa))
    s = max(s, 0.0)
    if p.fov == "exact" and ha > _EPS and (ha * s + hb) * s + hc < 0.0:
        # s fell between the roots of h: the largest feasible scale is the lower root.
        s = max(0.0, (-hb - math.sqrt(max(hb * hb - 4.0 * ha * hc, 0.0))) / (2.0 * ha))
    return s


def _R_y_R_x(phi: float, theta: float) -> np.ndarray:
    """eq:meth_body_pn_rotation ``R_B^PN = R_y(phi) R_x(theta)``, multiplied out."""
    cp, sp, ct, st = math.cos(phi), math.sin(phi), math.cos(theta), math.sin(theta)
    return np.array([[cp, sp * st, sp * ct], [0.0, ct, -st], [-sp, cp * st, cp * ct]])


def solve(l: np.ndarray, a_n: np.ndarray, p: GuidanceParams, y_ref: np.ndarray | None = None) -> ThrustAttitude:  # noqa: E741
    """Closed-form optimum of eq:meth_optimization_problem_simplified, with saturation.

    ``f_th* = min(f_max, hypot(n_y a_n - g_y^PN, (n_z a_n - g_z^PN) / cos(gamma_bar)))`` for the exact
    FOV bound, ``min(f_max, (n_z a_n - g_z^PN) / cos(gamma_bar))`` for the paper's;
    ``phi* = phi(f_th*)``, ``theta* = theta(f_th*)``, attitude ``R_B^W = R_PN^W R_y(phi*) R_x(theta*)``.
    ``l`` is the world-frame unit LOS, ``a_n`` the PN demand (world frame).
    """
    R_W_PN = pn_frame(l, y_ref)
    ax, ay, az = a_n.tolist()
    (_, yx, zx), (_, yy, zy), (_, yz, zz) = R_W_PN.tolist()
    a_y, a_z = yx * ax + yy * ay + yz * az, zx * ax + zy * ay + zz * az  # n_y a_n, n_z a_n
    g_y, g_z = -G * yz, -G * zz  # g^PN = R_W^PN g: its y part is 0 unless the LOS is vertical
    s = demand_scale(a_y, a_z, g_y, g_z, p)
    if s is None:
        f = min(p.f_max, max(p.f_min, -g_z))
        return ThrustAttitude(f, 0.0, 0.0, R_W_PN, 0.0, True)
    t_y, t_z = s * a_y - g_y, s * a_z - g_z
    f_fov = t_z / math.cos(p.gamma_bar)  # largest thrust the FOV bound allows
    if p.fov == "exact":
        f_fov = math.hypot(t_y, f_fov)
    f = max(min(p.f_max, f_fov), p.f_min)  # only rounding can put it below f_min (constraint (a))
    theta, phi = roll_pitch(f, t_y, t_z)
    return ThrustAttitude(f, phi, theta, R_W_PN @ _R_y_R_x(phi, theta), s, False)


@dataclass(frozen=True, slots=True)
class Setpoint:
    """What goes to MAVSDK ``Offboard.set_attitude``: NED/FRD Euler (deg, absolute yaw) + thrust 0..1."""

    roll_deg: float
    pitch_deg: float
    yaw_deg: float
    thrust: float
    R_ned_frd: np.ndarray  # the same attitude as a rotation matrix (body FRD -> world NED)

    def q_wxyz(self) -> np.ndarray:
        """The attitude as a scalar-first quaternion (MAVLink SET_ATTITUDE_TARGET order)."""
        return quat_wxyz_from_R(self.R_ned_frd)


def normalised_thrust(f_th: float, hover_thrust: float, thrust_min: float) -> float:
    """PX4's collective thrust 0..1 from mass-normalised thrust: ``hover_thrust * f_th / g``, clamped.

    Never 0: a quadrotor at zero thrust falls and cannot recover.
    """
    return min(1.0, max(thrust_min, hover_thrust * f_th / G))


def to_setpoint(R_W_B: np.ndarray, f_th: float, hover_thrust: float, thrust_min: float) -> Setpoint:
    """The one conversion from the paper's frames (ENU/FLU) to a MAVSDK setpoint (NED/FRD)."""
    R_ned_frd = R_W_B[_ENU_TO_NED_ROWS] * _NED_FRD_SIGNS  # = P_NED_ENU @ R_W_B @ F_FRD_FLU, without two matmuls
    roll, pitch, yaw = euler_ned_deg_from_R(R_ned_frd)
    return Setpoint(roll, pitch, yaw, normalised_thrust(f_th, hover_thrust, thrust_min), R_ned_frd)


def hover_setpoint(yaw_deg: float, hover_thrust: float) -> Setpoint:
    """Level attitude at the given yaw with hover thrust: the recover / no-target command."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return Setpoint(0.0, 0.0, yaw_deg, hover_thrust, R)


def straight_pass(l: np.ndarray, f_min: float, f_max: float, y_ref: np.ndarray | None = None) -> ThrustAttitude:  # noqa: E741
    """The gate pass: zero PN demand, optical axis (body x) on the LOS ``l`` (world, unit), no roll about it
    (body y horizontal: the PN frame with phi = theta = 0) and the thrust whose vertical part carries the
    weight, ``f = g / (e_z . z_B)`` within [f_min, f_max]. The net acceleration is then horizontal and along
    the LOS's heading (``-g tan(elevation)``): no climb, no sink, no bank held through the gate.
    """
    R_W_PN = pn_frame(l, y_ref)
    up = float(R_W_PN[2, 2])  # vertical part of the thrust axis: cos(LOS elevation)
    f = min(f_max, max(f_min, G / max(up, 1e-3)))
    return ThrustAttitude(f, 0.0, 0.0, R_W_PN, 0.0, False)
