"""Hover thrust from the vehicle: the normalised thrust that carries the weight, estimated in flight.

The controller turns its mass-normalised thrust f (m/s^2) into PX4's normalised thrust with
``u = hover_thrust * f / g``. A vehicle heavier than configured (battery, payload) then flies with
too little thrust. The accelerometer measures the specific force along the thrust axis, which is
``a_up = theta * u_lag`` with ``theta = g / hover_thrust`` (thrust minus the small drag component along
the thrust axis, divided by the mass) and ``u_lag`` the commanded thrust through the motors' first-order
lag. One-parameter recursive least squares (a scalar Kalman filter on theta with a random walk, so
slow changes such as battery sag are followed) gives theta and so the hover thrust, from every frame
at which we command the thrust ourselves.

Pure: numbers in, numbers out; the app, the in-process runner and the tests feed it.

Drag along the thrust axis: in fast forward flight the airframe is tilted into the airspeed, so part of the
drag acts along the thrust axis and the accelerometer's -z reads less than thrust / mass (the estimate read
high: more thrust than needed). The controller has no velocity, but the accelerometer's body x and y see the
drag alone (the thrust has none there), and in the engagement's near-level flight the airspeed, and so the
drag, is horizontal. So (``hover.drag_correction``) the thrust's specific force is taken as the vertical
specific force over the cosine of the tilt, ``-f_ned_z / R_zz``, which removes exactly a horizontal drag
(``thrust_specific_force``). A climb or sink at w m/s leaves the drag of w in it (small beside cruise speed).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from functools import cache
from typing import Any

import numpy as np
from pydantic import Field

from companion.configbase import Deg, MetersPerSecond2, Number, Seconds, Section

G = 9.81


class HoverConfig(Section):
    """In-flight hover-thrust estimate (companion/hover.py)."""

    estimate: bool = Field(True, description="estimate the hover thrust from the IMU while we command the "
                                              "thrust, and use it (False: configured / MPC_THR_HOVER value)")
    tau_thrust: Seconds = Field(0.03, ge=0.0, le=1.0, description="first-order lag command -> thrust, s")
    prior_std: Number = Field(0.3, gt=0.0, le=2.0, description="relative std of the starting value")
    noise: MetersPerSecond2 = Field(0.5, gt=0.0, le=20.0, description="std of one specific-force sample vs "
                                                                       "the model (IMU noise, vibration, drag)")
    drift: Number = Field(0.01, ge=0.0, le=1.0, description="relative random walk of theta per second")
    min_samples: int = Field(5, ge=1, le=1000, description="samples before the estimate is used")
    max_change: Number = Field(0.5, gt=0.0, le=1.0, description="estimate kept within +- this fraction of the "
                                                                "starting hover thrust")
    drag_correction: bool = Field(True, description="remove the drag along the thrust axis: thrust specific force "
                                  "= vertical specific force / cos(tilt) (exact for horizontal airspeed); False: the "
                                  "accelerometer's -z (drag biases the estimate high at speed)")
    max_tilt: Deg = Field(60.0, gt=0.0, le=80.0, description="drag_correction: samples tilted more than this are "
                          "not used (1 / cos(tilt) amplifies the attitude's error)")
    start_from_px4: bool = Field(True, description="after take-off, when the thrust PX4 commands in its hover "
                                 "differs from the hover thrust in use by more than 10 %, fly PX4's measured value "
                                 "(the in-flight estimate starts from it); a matching vehicle flies as before "
                                 "(companion/vehiclematch.py)")


@dataclass
class HoverEstimate:
    hover_thrust: float
    std: float  # of hover_thrust
    samples: int


class HoverThrustEstimator:
    """``update(t, u, a_up)``: u = normalised thrust commanded since the previous call, a_up = specific force
    along the thrust axis (m/s^2; FRD accelerometer: ``-acc_d``) at t. Returns the estimate once usable."""

    def __init__(self, hover0: float, cfg: HoverConfig | None = None) -> None:
        if not 0.05 < hover0 < 0.95:
            raise ValueError(f"hover thrust {hover0} outside (0.05, 0.95)")
        self.cfg = cfg or HoverConfig()
        self.hover0 = hover0
        self.theta = G / hover0
        self.P = (self.cfg.prior_std * self.theta) ** 2
        self._u_lag: float | None = None
        self._t: float | None = None
        self.samples = 0
        lo, hi = hover0 * (1 - self.cfg.max_change), hover0 * (1 + self.cfg.max_change)
        self._bounds = (max(0.05, lo), min(0.95, hi))

    @property
    def hover_thrust(self) -> float:
        return min(max(G / self.theta, self._bounds[0]), self._bounds[1])

    @property
    def ready(self) -> bool:
        return self.samples >= self.cfg.min_samples

    def estimate(self) -> HoverEstimate:
        # d(g/theta)/dtheta = -g/theta^2
        return HoverEstimate(self.hover_thrust, G / self.theta**2 * math.sqrt(self.P), self.samples)

    def reset_lag(self) -> None:
        """We stop commanding (PX4 flies its own modes): the lag state no longer knows the thrust."""
        self._u_lag = None
        self._t = None

    def update(self, t: float, u: float, a_up: float) -> HoverEstimate | None:
        if not (math.isfinite(t) and math.isfinite(u) and math.isfinite(a_up)):
            return self.estimate() if self.ready else None
        c = self.cfg
        if self._t is None or self._u_lag is None or t <= self._t:
            # First sample of a stretch: assume the thrust has settled on the command.
            self._u_lag, self._t = u, t
            return self.estimate() if self.ready else None
        dt = t - self._t
        a = 1.0 if c.tau_thrust <= 0 else 1.0 - math.exp(-dt / c.tau_thrust)
        self._u_lag += (u - self._u_lag) * a
        self._t = t
        self.P += (c.drift * self.theta) ** 2 * dt
        x = self._u_lag
        # Saturated or idle thrust, or a specific force that is no flight (free fall, ground): no information.
        if 0.05 < x < 0.98 and a_up > 0.2 * G:
            k = self.P * x / (x * x * self.P + c.noise**2)
            self.theta += k * (a_up - self.theta * x)
            self.P *= 1.0 - k * x
            self.samples += 1
        return self.estimate() if self.ready else None


def thrust_specific_force(accel_frd: Any, R_ned_frd: Any | None, cfg: HoverConfig | None = None) -> float:
    """The thrust's specific force (m/s^2, along -body z) from an accelerometer sample (FRD, m/s^2).

    ``drag_correction`` (and an attitude): the vertical specific force over the cosine of the tilt, which
    removes a horizontal drag exactly; NaN (no sample) beyond ``max_tilt``. Else the accelerometer's -z.
    """
    c = cfg or HoverConfig()
    # An array of floats is used as it is (asarray's call costs more than the rest of this; every frame).
    f = accel_frd if type(accel_frd) is np.ndarray and accel_frd.dtype is _F64 else np.asarray(accel_frd, float)
    if not c.drag_correction or R_ned_frd is None:
        return -float(f[2])
    r = (R_ned_frd if type(R_ned_frd) is np.ndarray and R_ned_frd.dtype is _F64 else np.asarray(R_ned_frd, float))[2]
    cos_tilt = r.item(2)  # float(r[2]) without the scalar object
    if not cos_tilt >= _cos_deg(c.max_tilt):
        return math.nan
    return -float(r.dot(f)) / cos_tilt  # .dot: the same BLAS ddot as @, without matmul's dispatch (every frame)


_F64 = np.dtype(np.float64)  # the native float64 dtype is a singleton: an identity test


@cache
def _cos_deg(deg: float) -> float:
    """cos of an angle in degrees (cached: the same configured limit every frame)."""
    return math.cos(math.radians(deg))


HOVER_MISMATCH = 0.10  # relative difference between two hover thrusts that is worth a warning line


def hover_mismatch(configured: float, autopilot: float | None, in_use: float, estimate_on: bool,
                   limit: float = HOVER_MISMATCH) -> str | None:
    """One line when the configured airframe's hover thrust and the autopilot's differ by more than ``limit``
    (relative), saying which one flies; None when they agree or the autopilot's is unknown.

    A hover thrust 25 % off flies every crossing high or low (in process: the 0.5 m gate 0.93 -> 0.53 without
    the in-flight estimate); the estimate corrects it once we command the thrust, from the value in use.
    """
    if autopilot is None or not math.isfinite(autopilot) or autopilot <= 0.0:
        return None
    rel = autopilot / configured - 1.0
    if abs(rel) <= limit:
        return None
    what = "lighter" if rel < 0 else "heavier"
    then = ("the in-flight estimate (hover.estimate) starts from it" if estimate_on
            else "hover.estimate is OFF: nothing corrects it in flight")
    return (f"hover thrust mismatch: config airframe.hover_thrust {configured:.3f}, PX4 MPC_THR_HOVER "
            f"{autopilot:.3f} ({rel:+.0%}: the vehicle flies {what} than configured, or PX4's value is stale); "
            f"using {in_use:.3f}; {then}")


def use_hover_thrust(ctrl: Any, hover_thrust: float, thrust_to_weight: float, engagement: Any = None) -> None:
    """Give a running PNController (and the engagement around it) a new hover thrust without restarting
    the LOS filter.

    The same numbers as ``PNController.with_hover_thrust`` (thrust limits follow the hover thrust), but in
    place: the estimate changes every frame during an engagement, the filter state must survive. The
    engagement's straight pass and recovery use the hover thrust too (level flight, climb-out).
    """
    p = ctrl.p
    f_max = G * min(thrust_to_weight, 1.0 / hover_thrust)
    f_min = G * p.thrust_min / hover_thrust
    # _replacer's functions called positionally (every frame: _replaced's keyword dict and key tuple cost a tenth
    # of these three copies); the same objects as _replaced(p, hover_thrust=..., guidance=...) etc.
    gp = p.guidance
    ctrl.p = _replacer(type(p), _P_FIELDS)(p, hover_thrust, _replacer(type(gp), _G_FIELDS)(gp, f_max, f_min))
    if engagement is not None:
        ep = engagement.params
        engagement.params = _replacer(type(ep), _E_FIELDS)(ep, hover_thrust, f_min, f_max)


_P_FIELDS = ("hover_thrust", "guidance")  # what use_hover_thrust changes, in the order it passes them
_G_FIELDS = ("f_max", "f_min")
_E_FIELDS = ("hover_thrust", "f_min", "f_max")


def _replaced(obj: Any, **changes: Any) -> Any:
    """``dataclasses.replace`` without its generic field walk: the estimate changes every frame and ``replace``
    on the ~25-field controller parameters was ~6 % of a simulator frame. The class's own ``__init__`` (with its
    ``__post_init__`` validation, if any) builds the copy, positionally."""
    return _replacer(type(obj), tuple(changes))(obj, **changes)


@cache
def _replacer(cls: type, changed: tuple[str, ...]) -> Callable[..., Any]:
    """``f(obj, **changes)`` -> ``cls(obj.a, <changed b>, obj.c, ...)``: the call written out once per class and
    set of changed fields (cached: the same three every frame). Plain attribute reads in compiled code cost a
    fraction of a ``getattr`` per name in a loop (the generic version was ~5 % of a simulator frame)."""
    fs = fields(cls)
    if any(not f.init or f.kw_only for f in fs):
        raise TypeError(f"{cls.__name__}: _replaced needs every field to be a positional init field")
    names = [f.name for f in fs]
    unknown = set(changed) - set(names)
    if unknown:
        raise TypeError(f"{cls.__name__}: _replaced got unknown fields {sorted(unknown)}")
    args = ", ".join(name if name in changed else f"obj.{name}" for name in names)
    src = f"def replaced(obj, {', '.join(changed)}):\n    return cls({args})\n"
    scope: dict[str, Any] = {}
    exec(src, {"cls": cls}, scope)  # the field names of a dataclass, no user input
    return scope["replaced"]
