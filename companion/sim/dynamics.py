"""Quadrotor rigid-body dynamics of the paper's eq:meth_quadrotor_dynamics, x500-like.

World ENU, body FLU (z = thrust axis), quaternions xyzw (body -> world), as in companion/frames.py.
Input: commanded attitude + normalised collective thrust (what PX4's offboard attitude setpoint
gives). Inside: Brescianini's attitude law ``omega_c = 2/tau sgn(q_e0) q_e(1:3)``, a first-order
body-rate response ``tau_omega`` (stands in for PX4's rate PID), a first-order thrust lag, thrust
limits, linear + quadratic drag on the airspeed, wind, and a flat ground at z = 0. An optional pure
delay ``cmd_delay`` between a setpoint and the loops that follow it stands for the transport and
scheduling latency of a real autopilot (PX4 SIH's roll answers its setpoint ~220 ms late, more than a
first-order loop can produce at the ~2 Hz where a limit cycle lives). The vehicle profiles in
config/vehicles/ set these per airframe.

The integrator is on the simulator's hot path (>= 200 Hz, >= 200x real time), so it works on plain
Python floats; numpy/scipy only appear at the API boundary.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from companion.frames import R_enu_flu_from_ned_frd, R_from_quat_wxyz

G = 9.81  # m/s^2, the paper's |g|


@dataclass(frozen=True)
class QuadParams:
    """Physical parameters of the simulated vehicle.

    Drag (paper's f_aero, acting against the airspeed v_air = v - wind) in newtons:
    ``f_aero = (drag_lin + drag_quad * |v_air|) * v_air``. The defaults (0.05 N s/m,
    0.011 N s^2/m^2, 2 kg) are calibrated to the paper's PX4/Gazebo x500: level flight at the
    21 deg tilt the tuned controller uses (gamma_bar = 21.05 deg) tops out at ~24 m/s, so runs
    from 30 m and 150 m reach the paper's ~15 and ~25 m/s. At 45 deg it would be ~40 m/s.
    """

    mass: float = 2.0  # kg
    hover_thrust: float = 0.5  # normalised thrust that hovers (the vehicle's true MPC_THR_HOVER)
    thrust_to_weight: float = 2.0  # max collective thrust / weight
    tau_omega: float = 0.04  # s, body-rate first-order response
    tau_att: float = 0.15  # s, attitude loop: omega_c = 2/tau * sgn(q_e0) * q_e(1:3)
    tau_thrust: float = 0.03  # s, collective thrust first-order lag
    drag_lin: float = 0.05  # N / (m/s)
    drag_quad: float = 0.011  # N / (m/s)^2
    max_rate: float = math.radians(220.0)  # rad/s, per-axis body-rate limit (PX4 MC_*RATE_MAX-like)
    max_touchdown_speed: float = 1.0  # m/s; descending faster at z = 0 is a ground contact
    max_step: float = 1.0 / 200.0  # s; step() subdivides longer dt so integration stays >= 200 Hz
    cmd_delay: float = 0.0  # s; pure delay of every setpoint (attitude and thrust) before the loops act on it

    @property
    def f_max(self) -> float:
        """Largest mass-normalised thrust, m/s^2."""
        return self.thrust_to_weight * G

    @classmethod
    def from_config(cls, cfg: Any) -> QuadParams:
        """From a Config: true mass/hover/T-W from ``sim.quad`` when set there, else ``airframe`` scaled by
        ``sim.quad.mass_scale`` (a heavier vehicle, same motors: more hover thrust, less thrust-to-weight)."""
        af, q = cfg.airframe, cfg.sim.quad
        s = float(q.mass_scale)
        hover = q.hover_thrust if q.hover_thrust is not None else af.hover_thrust * s
        tw = q.thrust_to_weight if q.thrust_to_weight is not None else af.thrust_to_weight / s
        if not (0.05 < hover < 0.95 and tw > 1.0):
            raise ValueError(f"sim.quad.mass_scale {s:g}: the vehicle would need hover thrust {hover:.2f} and have "
                             f"thrust-to-weight {tw:.2f}; it could not fly (hover thrust must be in (0.05, 0.95), "
                             f"thrust-to-weight > 1)")
        return cls(
            mass=q.mass if q.mass is not None else af.mass * s,
            hover_thrust=hover,
            thrust_to_weight=tw,
            tau_omega=q.tau_omega,
            tau_att=q.tau_att,
            tau_thrust=q.tau_thrust,
            drag_lin=q.drag_lin,
            drag_quad=q.drag_quad,
            max_rate=math.radians(q.max_rate),
            max_touchdown_speed=q.max_touchdown_speed,
            max_step=1.0 / cfg.sim.rate,
            cmd_delay=q.cmd_delay,
        )


def _zeros() -> np.ndarray:
    return np.zeros(3)


def _level() -> np.ndarray:
    return np.array([0.0, 0.0, 0.0, 1.0])


@dataclass
class QuadState:
    t: float = 0.0  # s
    p: np.ndarray = field(default_factory=_zeros)  # ENU, m
    v: np.ndarray = field(default_factory=_zeros)  # ENU, m/s
    q: np.ndarray = field(default_factory=_level)  # xyzw, body FLU -> world ENU
    omega: np.ndarray = field(default_factory=_zeros)  # body FLU, rad/s
    f_th: float = 0.0  # current mass-normalised thrust, m/s^2
    on_ground: bool = True
    ground_contact: bool = False  # latched: touched the ground faster than max_touchdown_speed


def qmul(a: tuple, b: tuple) -> tuple:
    """Hamilton product of xyzw quaternions (tuples of floats)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


def _rot(q: tuple, v: tuple) -> tuple:
    """Rotate v by unit quaternion q (xyzw): R(q) v."""
    x, y, z, w = q
    vx, vy, vz = v
    # v + 2 w (u x v) + 2 u x (u x v), u = (x, y, z)
    tx = 2.0 * (y * vz - z * vy)
    ty = 2.0 * (z * vx - x * vz)
    tz = 2.0 * (x * vy - y * vx)
    return (
        vx + w * tx + (y * tz - z * ty),
        vy + w * ty + (z * tx - x * tz),
        vz + w * tz + (x * ty - y * tx),
    )


def _rot_inv(q: tuple, v: tuple) -> tuple:
    x, y, z, w = q
    return _rot((-x, -y, -z, w), v)


class Quadrotor:
    """Integrates eq:meth_quadrotor_dynamics. ``state`` is refreshed after every ``step``."""

    def __init__(self, params: QuadParams, state: QuadState | None = None):
        self.params = params
        self._coeffs: dict[float, tuple[int, float, float, float]] = {}  # per dt: substeps and gains
        self._k_lin = params.drag_lin / params.mass  # mass-normalised drag coefficients
        self._k_quad = params.drag_quad / params.mass
        self._queue: deque[tuple[float, tuple, float]] = deque()  # (time it takes effect, q_cmd, f_cmd)
        self._active: tuple[tuple, float] | None = None  # the delayed command in effect
        self.state = state if state is not None else QuadState()

    @property
    def state(self) -> QuadState:
        if self._stale:  # advanced since the last QuadState was built
            self._publish()
        return self._state

    @state.setter
    def state(self, s: QuadState) -> None:
        """Assigning a state (e.g. a scenario's initial condition) re-initialises the integrator."""
        self._state = replace(s, p=np.array(s.p, dtype=float), v=np.array(s.v, dtype=float),
                              q=np.array(s.q, dtype=float), omega=np.array(s.omega, dtype=float))
        self._load(self._state)
        self._stale = False
        # q_xyzw is state.q: the assigned state's own (maybe not quite unit) quaternion until the first step, then
        # the integrator's (a QuadState built after a step holds that one).
        self._q_state = tuple(float(c) for c in self._state.q)

    # The state as floats, without building a QuadState (the runner's per-frame reads; advance() does not build one).
    @property
    def p_xyz(self) -> tuple[float, float, float]:
        """Position, ENU m."""
        return self._p

    @property
    def v_xyz(self) -> tuple[float, float, float]:
        """Velocity, ENU m/s."""
        return self._v

    @property
    def q_xyzw(self) -> tuple[float, float, float, float]:
        """Attitude, body FLU -> world ENU, xyzw (``state.q``'s floats)."""
        return self._q_state

    @property
    def on_ground(self) -> bool:
        return self._on_ground

    @property
    def ground_contact(self) -> bool:
        """Latched: touched the ground faster than max_touchdown_speed."""
        return self._contact

    # -- float-level copy of the state (hot path) ---------------------------------------------------
    def _load(self, s: QuadState) -> None:
        self._t = float(s.t)
        self._p = tuple(float(c) for c in s.p)
        self._v = tuple(float(c) for c in s.v)
        q = np.asarray(s.q, dtype=float)
        if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-9:
            raise ValueError(f"QuadState.q: expected a 4-element xyzw quaternion (got {s.q})")
        q = q / np.linalg.norm(q)
        self._q = tuple(float(c) for c in q)
        self._w = tuple(float(c) for c in s.omega)
        self._f = float(s.f_th)
        self._on_ground = bool(s.on_ground)
        self._contact = bool(s.ground_contact)
        self._a = (0.0, 0.0, 0.0)  # last true acceleration (world), for the accelerometer
        self._queue.clear()  # a new state starts with no setpoints in flight
        self._active = None

    def _publish(self) -> QuadState:
        self._state = QuadState(
            t=self._t,
            p=np.array(self._p),
            v=np.array(self._v),
            q=np.array(self._q),
            omega=np.array(self._w),
            f_th=self._f,
            on_ground=self._on_ground,
            ground_contact=self._contact,
        )
        self._stale = False
        return self._state

    def step(
        self, dt: float, q_cmd: np.ndarray | tuple[float, float, float, float], thrust_norm: float,
        wind_enu: np.ndarray | tuple[float, float, float] | None = None,
    ) -> QuadState:
        """Advance by dt seconds holding the command (zero-order hold, as PX4 holds a setpoint).

        ``q_cmd`` (xyzw) and ``wind_enu`` may be tuples of Python floats (the runner's per-frame values), taken as
        they are; other sequences are converted element by element."""
        self.advance(dt, q_cmd, thrust_norm, wind_enu)
        return self._publish()

    def advance(
        self, dt: float, q_cmd: np.ndarray | tuple[float, float, float, float], thrust_norm: float,
        wind_enu: np.ndarray | tuple[float, float, float] | None = None,
    ) -> None:
        """:meth:`step` without building its QuadState (``state`` builds one when read; the runner reads the floats
        instead: four arrays and a dataclass a frame)."""
        if not dt > 0.0:
            raise ValueError(f"Quadrotor.step: dt must be > 0 (got {dt})")
        p = self.params
        # tolist: the same floats as float() of each element, in one call (every frame)
        if type(q_cmd) is tuple and len(q_cmd) == 4:  # quat_enu_flu_from_R_ned_frd's floats (every frame)
            c0, c1, c2, c3 = q_cmd
        else:
            c0, c1, c2, c3 = q_cmd.tolist() if type(q_cmd) is np.ndarray else (float(c) for c in q_cmd[:4])
        nrm = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2 + c3 * c3)
        if not (nrm > 1e-9 and math.isfinite(nrm)):
            raise ValueError(f"Quadrotor.step: q_cmd is not a quaternion (got {q_cmd})")
        qc = (c0 / nrm, c1 / nrm, c2 / nrm, c3 / nrm)
        thr = min(max(float(thrust_norm), 0.0), 1.0)
        f_cmd = min(thr * G / p.hover_thrust, p.f_max)
        if type(wind_enu) is tuple and len(wind_enu) == 3:  # Wind.step's floats (every frame)
            wind = wind_enu
        else:
            wind = (0.0, 0.0, 0.0) if wind_enu is None else (
                tuple(wind_enu.tolist()) if type(wind_enu) is np.ndarray else tuple(float(c) for c in wind_enu[:3]))
        coeffs = self._coeffs.get(dt)
        if coeffs is None:
            n = max(1, math.ceil(dt / p.max_step - 1e-9))
            h = dt / n
            coeffs = (n, h, 1.0 - math.exp(-h / p.tau_omega), 1.0 - math.exp(-h / p.tau_thrust))
            self._coeffs[dt] = coeffs
        n, h, a_w, a_f = coeffs
        if p.cmd_delay > 0.0:
            # Delayed: the command reaches the loops cmd_delay after it was given; until the first one arrives the
            # vehicle holds the first command it got (as an autopilot holds its last setpoint).
            self._queue.append((self._t + p.cmd_delay - 1e-9, qc, f_cmd))
            if self._active is None:
                self._active = (qc, f_cmd)
        self._integrate(n, h, qc, f_cmd, wind, a_w, a_f, 2.0 / p.tau_att, p.max_rate)
        self._q_state = self._q
        self._stale = True

    def _integrate(self, n: int, h: float, qc: tuple, f_cmd: float, wind: tuple, a_w: float, a_f: float,
                   k_att: float, wmax: float) -> None:
        """n substeps of h holding (qc, f_cmd), or with cmd_delay the queued commands as they fall due.

        The simulator's innermost loop: hand-inlined quaternion algebra on local floats (the state is loaded
        once and stored back after the n substeps; the arithmetic is the same expression by expression)."""
        p = self.params
        queue = self._queue if p.cmd_delay > 0.0 else None
        k_lin, k_quad, touchdown = self._k_lin, self._k_quad, p.max_touchdown_speed
        wdx, wdy, wdz = wind
        t, f, on_ground, contact, acc = self._t, self._f, self._on_ground, self._contact, self._a
        qx, qy, qz, qw = self._q
        w0, w1, w2 = self._w
        v0, v1, v2 = self._v
        p0, p1, p2 = self._p
        ax, ay, az = acc
        # Local names for the loop (every substep): math's functions bound once, -wmax once; the same arithmetic.
        sqrt, sin, cos = math.sqrt, math.sin, math.cos
        nwmax = -wmax
        cx, cy, cz, cw = qc
        for _ in range(n):
            if queue is not None:
                while queue and queue[0][0] <= t:
                    _, q_a, f_a = queue.popleft()
                    self._active = (q_a, f_a)
                qc, f_cmd = self._active  # type: ignore[misc]
                cx, cy, cz, cw = qc
            # Attitude controller (Brescianini): q_e = q^-1 * q_c, omega_c = 2/tau sgn(q_e0) q_e(1:3).
            ew = qw * cw + qx * cx + qy * cy + qz * cz
            ex = qw * cx - qx * cw - qy * cz + qz * cy
            ey = qw * cy + qx * cz - qy * cw - qz * cx
            ez = qw * cz - qx * cy + qy * cx - qz * cw
            k = k_att if ew >= 0.0 else -k_att
            # Exact discretisation of the first-order rate response, command clipped to the rate limit.
            cx_, cy_, cz_ = k * ex, k * ey, k * ez
            cx_ = wmax if cx_ > wmax else (nwmax if cx_ < nwmax else cx_)
            cy_ = wmax if cy_ > wmax else (nwmax if cy_ < nwmax else cy_)
            cz_ = wmax if cz_ > wmax else (nwmax if cz_ < nwmax else cz_)
            w0 += (cx_ - w0) * a_w
            w1 += (cy_ - w1) * a_w
            w2 += (cz_ - w2) * a_w
            f += (f_cmd - f) * a_f  # thrust lag
            # Translational dynamics: a = R (f e_z) - f_aero / m + g; R e_z is the third column of R(q).
            vax, vay, vaz = v0 - wdx, v1 - wdy, v2 - wdz
            k_d = k_lin + k_quad * sqrt(vax * vax + vay * vay + vaz * vaz)
            f2 = 2.0 * f  # (2.0 * f * x is (2.0 * f) * x)
            ax = f2 * (qx * qz + qy * qw) - k_d * vax
            ay = f2 * (qy * qz - qx * qw) - k_d * vay
            az = f * (1.0 - 2.0 * (qx * qx + qy * qy)) - k_d * vaz - G
            if on_ground and az <= 0.0:
                # Resting on the ground: the normal force cancels everything (legs don't slide).
                v0 = v1 = v2 = 0.0
                ax = ay = az = 0.0
            else:
                on_ground = False
                # Semi-implicit Euler: velocity first, then position with the new velocity.
                v0 += ax * h
                v1 += ay * h
                v2 += az * h
                p0 += v0 * h
                p1 += v1 * h
                p2 += v2 * h
                if p2 <= 0.0:
                    if -v2 > touchdown:
                        contact = True
                    p2 = 0.0
                    v0 = v1 = v2 = 0.0
                    on_ground = True
                    ax = ay = az = 0.0
            # Attitude kinematics: q <- q * exp(omega h / 2), exact for constant omega over the step.
            wn = sqrt(w0 * w0 + w1 * w1 + w2 * w2)
            if wn > 1e-12:
                half = 0.5 * wn * h
                sh = sin(half) / wn
                dx, dy, dz, dw = w0 * sh, w1 * sh, w2 * sh, cos(half)
                nx = qw * dx + qx * dw + qy * dz - qz * dy
                ny = qw * dy - qx * dz + qy * dw + qz * dx
                nz = qw * dz + qx * dy - qy * dx + qz * dw
                nw = qw * dw - qx * dx - qy * dy - qz * dz
                qn = 1.0 / sqrt(nx * nx + ny * ny + nz * nz + nw * nw)
                qx, qy, qz, qw = nx * qn, ny * qn, nz * qn, nw * qn
            t += h
        # The last substep's true acceleration (zero on the ground), for the accelerometer.
        self._t, self._f, self._on_ground, self._contact, self._a = t, f, on_ground, contact, (ax, ay, az)
        self._q = (qx, qy, qz, qw)
        self._w = (w0, w1, w2)
        self._v = (v0, v1, v2)
        self._p = (p0, p1, p2)

    def specific_force_body(self) -> np.ndarray:
        """Accelerometer reading without noise (FLU, m/s^2): R^T (a - g) = (thrust - drag) / m, body."""
        return np.array(self.specific_force_body_xyz())

    def specific_force_body_xyz(self) -> tuple[float, float, float]:
        """:meth:`specific_force_body` as three floats (the simulator's per-frame path: no array)."""
        a = self._a
        return _rot_inv(self._q, (a[0], a[1], a[2] + G))  # type: ignore[return-value]

    def acceleration_world(self) -> np.ndarray:
        """True acceleration of the last substep, ENU m/s^2 (for scoring and tests)."""
        return np.array(self._a)


# -- rotation helpers for the simulator's 30 Hz loop (scipy's Rotation costs ~30 us per construction) --


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of an xyzw quaternion (scipy order); the closed form lives in companion/frames.py."""
    x, y, z, w = q.tolist() if isinstance(q, np.ndarray) else q  # Python floats: the closed form's cheap path
    return R_from_quat_wxyz((w, x, y, z))


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """xyzw quaternion (w >= 0) of a rotation matrix, Shepperd's method (numerically safe branch)."""
    # tolist: the same floats as float() of each element, in one call (every frame).
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = np.asarray(R, dtype=float).tolist()
    return np.array(_quat_of(m00, m01, m02, m10, m11, m12, m20, m21, m22))


def quat_enu_flu_from_R_ned_frd(R_ned_frd: np.ndarray) -> tuple[float, float, float, float]:
    """``matrix_to_quat(R_enu_flu_from_ned_frd(R_ned_frd))`` bit for bit, as four floats (``Quadrotor.step`` takes
    them as they are), without the two matrix products (a setpoint every frame). ``P R F`` only moves and negates
    elements: its products are by 0 and +-1 (exact) and BLAS adds them to a +0, so each element is ``0.0 +`` or
    ``0.0 -`` one element of R (a zero always comes out +0; tested against the products over 300k matrices with
    zeros of both signs). A non-finite R (0 * inf in the products) takes the products."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = np.asarray(R_ned_frd, dtype=float).tolist()
    if not math.isfinite(r00 + r01 + r02 + r10 + r11 + r12 + r20 + r21 + r22):
        return tuple(matrix_to_quat(R_enu_flu_from_ned_frd(R_ned_frd)).tolist())  # type: ignore[return-value]
    return _quat_of(0.0 + r10, 0.0 - r11, 0.0 - r12, 0.0 + r00, 0.0 - r01, 0.0 - r02, 0.0 - r20, 0.0 + r21,
                    0.0 + r22)


def _quat_of(m00: float, m01: float, m02: float, m10: float, m11: float, m12: float, m20: float, m21: float,
             m22: float) -> tuple[float, float, float, float]:
    """:func:`matrix_to_quat` of the matrix's elements, as floats."""
    tr = m00 + m11 + m22
    if tr >= max(m00, m11, m22):
        r = math.sqrt(1.0 + tr)
        q = (0.5 * (m21 - m12) / r, 0.5 * (m02 - m20) / r, 0.5 * (m10 - m01) / r, 0.5 * r)
    elif m00 >= m11 and m00 >= m22:
        r = math.sqrt(1.0 + m00 - m11 - m22)
        q = (0.5 * r, 0.5 * (m01 + m10) / r, 0.5 * (m02 + m20) / r, 0.5 * (m21 - m12) / r)
    elif m11 >= m22:
        r = math.sqrt(1.0 - m00 + m11 - m22)
        q = (0.5 * (m01 + m10) / r, 0.5 * r, 0.5 * (m12 + m21) / r, 0.5 * (m02 - m20) / r)
    else:
        r = math.sqrt(1.0 - m00 - m11 + m22)
        q = (0.5 * (m02 + m20) / r, 0.5 * (m12 + m21) / r, 0.5 * r, 0.5 * (m10 - m01) / r)
    a = np.array(q)
    n = math.sqrt(a.dot(a))  # np.linalg.norm of a vector is sqrt(x.dot(x)): the same bits, without its overhead
    # The division and the sign in floats: an array divided by a float is IEEE division element by element, and a
    # negation is exact (the same bits as out /= n; -out if out[3] < 0, tested over 300k quaternions).
    x, y, z, w = q[0] / n, q[1] / n, q[2] / n, q[3] / n
    return (-x, -y, -z, -w) if w < 0 else (x, y, z, w)


def rotvec_to_matrix(rv: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation matrix of a rotation vector (rad)."""
    x, y, z = (float(c) for c in rv)
    a = math.sqrt(x * x + y * y + z * z)
    if a < 1e-12:
        return np.eye(3)
    kx, ky, kz = x / a, y / a, z / a
    K = np.array([[0.0, -kz, ky], [kz, 0.0, -kx], [-ky, kx, 0.0]])
    return np.eye(3) + math.sin(a) * K + (1.0 - math.cos(a)) * (K @ K)
