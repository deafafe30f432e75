"""Gate motions of the paper (section V-A): stationary, linear slow/fast, planar, knot.

The motion formulas are written in a *motion frame* M attached to the scenario:
``x_M`` = horizontal, in the gate plane (lateral to the initial approach), ``y_M`` = horizontal
along the gate normal (depth), ``z_M`` = world up. So the planar motion
``p0 + d_plan [cos(wt), cos(2wt)/2, 0]`` sweeps 2 d_plan sideways and d_plan in depth, and the
knot adds +-d_knot vertically. Linear motions move along ``x_M`` (sideways, sign chosen per run).

``omega`` is solved so the top speed equals the configured one (paper: 3.1 m/s planar, 1.2 m/s
knot); :func:`motion_extremes` reports the resulting peak accelerations. Gates only translate:
the gate plane's normal is fixed (assumption 2 of the paper).

Beyond the paper's five (``MOTIONS``), two motions of a target a user would test (``ALL_MOTIONS``):
``recede`` drives away along the normal (away from the vehicle) at ``recede_speed`` (the paper's truck,
section end-to-end experiment), ``sinusoid`` swings sideways, ``x = A sin(2 pi f t + phase)`` (an evasive gate).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from typing import Literal

import numpy as np

from companion.frames import cross_xyz

MotionKind = Literal["stationary", "linear_slow", "linear_fast", "planar", "knot", "recede", "sinusoid"]
MOTIONS: tuple[MotionKind, ...] = ("stationary", "linear_slow", "linear_fast", "planar", "knot")  # the paper's
ALL_MOTIONS: tuple[MotionKind, ...] = (*MOTIONS, "recede", "sinusoid")


def planar_shape(u: np.ndarray | float) -> np.ndarray:
    """Unit-amplitude planar curve at phase u = omega t: [cos u, cos(2u)/2, 0] (columns = samples)."""
    u = np.asarray(u, dtype=float)
    return np.array([np.cos(u), 0.5 * np.cos(2 * u), np.zeros_like(u)])


def planar_shape_d1(u: np.ndarray | float) -> np.ndarray:
    """d/du of :func:`planar_shape`."""
    u = np.asarray(u, dtype=float)
    return np.array([-np.sin(u), -np.sin(2 * u), np.zeros_like(u)])


def planar_shape_d2(u: np.ndarray | float) -> np.ndarray:
    u = np.asarray(u, dtype=float)
    return np.array([-np.cos(u), -2.0 * np.cos(2 * u), np.zeros_like(u)])


def knot_shape(u: np.ndarray | float) -> np.ndarray:
    """Unit-amplitude knot: [sin 3u (1 + cos(2u)/2), sin 3u sin 2u, sin 4u]."""
    u = np.asarray(u, dtype=float)
    return np.array([np.sin(3 * u) * (1 + 0.5 * np.cos(2 * u)), np.sin(3 * u) * np.sin(2 * u), np.sin(4 * u)])


def knot_shape_d1(u: np.ndarray | float) -> np.ndarray:
    u = np.asarray(u, dtype=float)
    s3, c3, s2, c2 = np.sin(3 * u), np.cos(3 * u), np.sin(2 * u), np.cos(2 * u)
    return np.array([3 * c3 * (1 + 0.5 * c2) - s3 * s2, 3 * c3 * s2 + 2 * s3 * c2, 4 * np.cos(4 * u)])


def knot_shape_d2(u: np.ndarray | float) -> np.ndarray:
    u = np.asarray(u, dtype=float)
    s3, c3, s2, c2 = np.sin(3 * u), np.cos(3 * u), np.sin(2 * u), np.cos(2 * u)
    return np.array([
        -9 * s3 * (1 + 0.5 * c2) - 3 * c3 * s2 - 3 * c3 * s2 - 2 * s3 * c2,
        -9 * s3 * s2 + 6 * c3 * c2 + 6 * c3 * c2 - 4 * s3 * s2,
        -16 * np.sin(4 * u),
    ])


_SHAPES = {
    "planar": (planar_shape, planar_shape_d1, planar_shape_d2),
    "knot": (knot_shape, knot_shape_d1, knot_shape_d2),
}


@cache
def shape_extremes(kind: str) -> tuple[float, float]:
    """(max |d shape/du|, max |d^2 shape/du^2|) over one period, for a unit-amplitude curve."""
    _, d1, d2 = _SHAPES[kind]
    u = np.linspace(0.0, 2 * math.pi, 200_001)  # both curves have period 2 pi in u
    return float(np.max(np.linalg.norm(d1(u), axis=0))), float(np.max(np.linalg.norm(d2(u), axis=0)))


def omega_for_top_speed(kind: str, amplitude: float, top_speed: float) -> float:
    """omega [rad/s] making ``amplitude * shape(omega t)`` peak at ``top_speed``."""
    vmax, _ = shape_extremes(kind)
    return top_speed / (amplitude * vmax)


def motion_extremes(kind: str, amplitude: float, top_speed: float) -> dict[str, float]:
    """omega, top speed and peak acceleration of a periodic motion (for the report)."""
    w = omega_for_top_speed(kind, amplitude, top_speed)
    vmax, amax = shape_extremes(kind)
    return {"omega": w, "top_speed": amplitude * w * vmax, "top_accel": amplitude * w * w * amax}


@dataclass(frozen=True)
class GateMotion:
    """A gate centre trajectory in world ENU plus the gate's fixed plane.

    ``R_world_motion`` columns are the motion-frame axes (x lateral, y along the normal, z up)
    in ENU. ``normal`` points from the gate towards the side the vehicle starts on.
    """

    kind: MotionKind
    p0: np.ndarray  # ENU, m: trajectory origin (the formulas' p0)
    normal: np.ndarray  # unit, ENU
    R_world_motion: np.ndarray  # 3x3
    speed: float = 0.0  # linear motions, m/s (signed along x_M)
    amplitude: float = 0.0  # d_plan / d_knot, m
    omega: float = 0.0  # rad/s
    phase: float = 0.0  # rad, start phase of planar/knot

    def position(self, t: float) -> np.ndarray:
        if self.kind == "stationary":
            return self.p0.copy()
        if self.kind in ("linear_slow", "linear_fast"):
            return self.p0 + self.R_world_motion[:, 0] * (self.speed * t)
        if self.kind == "recede":  # away from the vehicle: against the normal (which points at the vehicle)
            return self.p0 - self.normal * (self.speed * t)
        if self.kind == "sinusoid":
            return self.p0 + self.R_world_motion[:, 0] * (self.amplitude * math.sin(self.omega * t + self.phase))
        u = self.omega * t + self.phase
        # Scalar math (this runs every frame); the same formulas as planar_shape / knot_shape.
        if self.kind == "planar":
            m = (math.cos(u), 0.5 * math.cos(2 * u), 0.0)
        else:
            s3 = math.sin(3 * u)
            m = (s3 * (1 + 0.5 * math.cos(2 * u)), s3 * math.sin(2 * u), math.sin(4 * u))
        a = self.amplitude
        return self.p0 + self.R_world_motion.dot(np.array((a * m[0], a * m[1], a * m[2])))  # .dot: cheaper than @

    def velocity(self, t: float) -> np.ndarray:
        if self.kind == "stationary":
            return np.zeros(3)
        if self.kind in ("linear_slow", "linear_fast"):
            return self.R_world_motion[:, 0] * self.speed
        if self.kind == "recede":
            return -self.normal * self.speed
        if self.kind == "sinusoid":
            return self.R_world_motion[:, 0] * (self.amplitude * self.omega * math.cos(self.omega * t + self.phase))
        _, d1, _ = _SHAPES[self.kind]
        return self.R_world_motion @ (self.amplitude * self.omega * d1(self.omega * t + self.phase))

    def acceleration(self, t: float) -> np.ndarray:
        if self.kind in ("stationary", "linear_slow", "linear_fast", "recede"):
            return np.zeros(3)
        if self.kind == "sinusoid":
            return self.R_world_motion[:, 0] * (-self.amplitude * self.omega**2
                                                * math.sin(self.omega * t + self.phase))
        _, _, d2 = _SHAPES[self.kind]
        return self.R_world_motion @ (self.amplitude * self.omega**2 * d2(self.omega * t + self.phase))


def motion_frame(normal_enu: np.ndarray) -> np.ndarray:
    """Motion frame for a horizontal gate normal: x lateral (z x normal... right-handed), y normal, z up."""
    n = np.array([normal_enu[0], normal_enu[1], 0.0])
    n /= np.linalg.norm(n)
    n0, n1, n2 = n.tolist()
    x = cross_xyz((n0, n1, n2), (0.0, 0.0, 1.0))  # n x z: horizontal, in the gate plane
    return np.array([[x[0], n0, 0.0], [x[1], n1, 0.0], [x[2], n2, 1.0]])


def make_gate(
    kind: MotionKind,
    start_position: np.ndarray,
    normal: np.ndarray,
    *,
    rng: np.random.Generator,
    gates_cfg: object,
) -> GateMotion:
    """A gate of the given motion whose centre is at ``start_position`` at t = 0.

    Random parts (from ``rng``): the direction sign of linear motions, the start phase of
    planar/knot (p0 is then placed so the trajectory passes through ``start_position`` at t = 0).
    ``gates_cfg`` is a ``GateMotionConfig``.
    """
    if kind not in ALL_MOTIONS:
        raise ValueError(f"unknown gate motion {kind!r} (use one of: {', '.join(ALL_MOTIONS)})")
    R = motion_frame(np.asarray(normal, dtype=float))
    n = R[:, 1].copy()
    start = np.asarray(start_position, dtype=float)
    if kind == "stationary":
        return GateMotion(kind, start, n, R)
    if kind in ("linear_slow", "linear_fast"):
        speed = gates_cfg.linear_slow_speed if kind == "linear_slow" else gates_cfg.linear_fast_speed
        sign = 1.0 if rng.random() < 0.5 else -1.0
        return GateMotion(kind, start, n, R, speed=sign * speed)
    if kind == "recede":
        return GateMotion(kind, start, n, R, speed=gates_cfg.recede_speed)
    if kind == "sinusoid":
        # Random start phase; p0 is the swing's centre, placed so the gate is at start_position at t = 0.
        a, w = gates_cfg.sinusoid_amplitude, 2 * math.pi * gates_cfg.sinusoid_frequency
        phase = float(rng.uniform(0.0, 2 * math.pi))
        return GateMotion(kind, start - R[:, 0] * (a * math.sin(phase)), n, R, amplitude=a, omega=w, phase=phase)
    amp = gates_cfg.d_plan if kind == "planar" else gates_cfg.d_knot
    top = gates_cfg.planar_top_speed if kind == "planar" else gates_cfg.knot_top_speed
    w = omega_for_top_speed(kind, amp, top)
    phase = float(rng.uniform(0.0, 2 * math.pi))
    f, _, _ = _SHAPES[kind]
    p0 = start - R @ (amp * f(phase))
    return GateMotion(kind, p0, n, R, amplitude=amp, omega=w, phase=phase)
