"""Does the vehicle match the configured airframe? The decisions, pure (issue 20).

After take-off, while PX4 holds the vehicle in its own mode, the thrust PX4 commands is a direct measurement of
the hover thrust the vehicle really needs: PX4's position controller flies with its hover-thrust estimator's
value (mc_hover_thrust_estimator, not on MAVLink as such) plus a small velocity loop, and streams the result
as ATTITUDE_TARGET (10 Hz on PX4 v1.15's onboard link). ``measured_hover`` turns those samples into one number
(the vertical part of the commanded thrust, median); ``hover_after_takeoff`` compares it with the configured
airframe, PX4's MPC_THR_HOVER and the app's own estimate, decides which value flies, and writes the one line
the operator reads. ``param_mismatches``: PX4 parameters read before arming that disagree with the airframe.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass

HOVER_LIMIT = 0.10  # relative mismatch worth a WARNING (and, with hover.start_from_px4, a change of value)
WINDOW = 10  # the newest PX4 thrust samples used (1 s at 10 Hz): the hover after the take-off's end
MIN_SAMPLES = 5  # fewer usable samples: not measured
MIN_ALT = 1.0  # m above the take-off point: below, the ground may still carry the vehicle
SETTLE_S = 0.5  # s after PX4's hover began (landed state IN_AIR) before its thrust counts: the climb's end swings


@dataclass(frozen=True)
class ThrustSample:
    """One ATTITUDE_TARGET: received at ``t`` (monotonic s), PX4's collective thrust (0..1), its attitude
    setpoint (w, x, y, z; NED/FRD), and at reception: the mode, the landed state and PX4's barometric
    altitude (raw: the ground is the app's own reference, taken at arm or given by safety.altitude_reference)."""

    t: float
    thrust: float
    q_wxyz: tuple[float, float, float, float]
    mode: str | None = None
    landed: str | None = None
    alt: float | None = None


def vertical_thrust(thrust: float, q_wxyz: tuple[float, float, float, float]) -> float:
    """The vertical part of a collective thrust along the setpoint's body z: thrust * R_zz(q) (1 - 2(x^2+y^2))."""
    w, x, y, z = q_wxyz
    n = w * w + x * x + y * y + z * z
    if not (math.isfinite(n) and n > 0.5):
        return math.nan
    return thrust * (1.0 - 2.0 * (x * x + y * y) / n)


def hovering(s: ThrustSample, ground: float | None = None) -> bool:
    """PX4 flies the vehicle itself in the air, off the ground: landed state IN_AIR (PX4 reports it once the
    take-off climb is over), not our OFFBOARD setpoints, not a landing, and more than MIN_ALT above ``ground``
    (the app's raw barometric ground reference; unknown: PX4's IN_AIR decides)."""
    return (s.landed == "IN_AIR" and s.mode not in (None, "OFFBOARD", "LAND", "RTL")
            and (ground is None or (s.alt is not None and s.alt - ground > MIN_ALT)))


def measured_hover(samples: Iterable[ThrustSample], until: float = math.inf,
                   need: int = MIN_SAMPLES, ground: float | None = None) -> tuple[float | None, int]:
    """(median vertical thrust PX4 commanded in its newest WINDOW hover samples received up to ``until``,
    number used); (None, n) with fewer than ``need``.

    The raw command, not corrected by the IMU: on PX4 SITL one HIGHRES_IMU sample scatters +-15 % about g, the
    command 1-2 % about the hover. The first SETTLE_S of the hover are left out and the median of the newest
    second rides out the rest of the take-off's end (PX4 1.15 SIH, 1.5 kg, true hover 0.400: the command dips
    to 0.35 in the first 0.5 s of IN_AIR, then swings 0.38-0.44 for ~1 s; medians of 5-10 samples from 0.5 s on
    were 0.39-0.41).
    """
    hover = [s for s in samples if hovering(s, ground)]
    if not hover:
        return None, 0
    start = hover[0].t + SETTLE_S
    vals = [v for s in hover if start <= s.t <= until
            for v in (vertical_thrust(s.thrust, s.q_wxyz),) if math.isfinite(v) and 0.05 < v < 0.95][-WINDOW:]
    n = len(vals)
    if n < need:
        return None, n
    vals.sort()
    mid = n // 2
    return (vals[mid] if n % 2 else 0.5 * (vals[mid - 1] + vals[mid])), n


@dataclass
class HoverCheck:
    """What the flight knew about the hover thrust after take-off (summary.json ``hover.after_takeoff``)."""

    px4_commanded: float | None  # median vertical thrust PX4 commanded in its hover (None: not measured)
    samples: int
    app_estimate: float  # the app's in-flight estimate at that time (the value in use before it commands)
    configured: float  # airframe.hover_thrust
    mpc_thr_hover: float | None  # PX4's MPC_THR_HOVER when read
    in_use: float  # what the app flew with until now
    vs_configured: float | None  # px4_commanded / configured - 1
    vs_in_use: float | None  # px4_commanded / in_use - 1
    warning: bool
    flies: float  # what the app flies from now on (its estimate starts here)
    flies_source: str  # "PX4 measured" or the previous value's source
    line: str

    def as_dict(self) -> dict[str, object]:
        return asdict(self)


def hover_after_takeoff(px4_commanded: float | None, samples: int, app_estimate: float, configured: float,
                        mpc_thr_hover: float | None, in_use: float, in_use_source: str, *, start_from_px4: bool,
                        estimate_on: bool, too_late: bool = False, limit: float = HOVER_LIMIT) -> HoverCheck:
    """Compare PX4's measured hover thrust with the configuration and the value in use; decide what flies.

    The app switches to PX4's value only when it is off the value in use by more than ``limit`` (and
    ``start_from_px4``, and not ``too_late``: the engagement had begun before PX4's hover was measured): a vehicle
    that matches its configuration flies exactly as before.
    """
    mpc = f" (PX4 MPC_THR_HOVER {mpc_thr_hover:.2f})" if mpc_thr_hover is not None else ""
    head = "hover thrust after take-off: "
    if px4_commanded is None:
        line = (f"{head}PX4's commanded thrust not measured ({samples} samples in its hover, {MIN_SAMPLES} needed); "
                f"the app's estimate {app_estimate:.2f}, configured {configured:.2f}{mpc}; flying with "
                f"{in_use:.2f} ({in_use_source})")
        return HoverCheck(None, samples, app_estimate, configured, mpc_thr_hover, in_use, None, None, False,
                          in_use, in_use_source, line)
    rel_cfg = px4_commanded / configured - 1.0
    rel_use = px4_commanded / in_use - 1.0
    warning = max(abs(rel_cfg), abs(rel_use)) > limit
    adopt = start_from_px4 and not too_late and abs(rel_use) > limit
    flies, source = (px4_commanded, "PX4 measured") if adopt else (in_use, in_use_source)
    if abs(rel_cfg) <= limit:
        what = "the vehicle matches the configuration"
    else:
        what = f"the vehicle is {abs(rel_cfg):.0%} {'lighter' if rel_cfg < 0 else 'heavier'} than configured"
    if adopt:
        then = f"flying with PX4's measured value ({flies:.2f})" + (
            "; the in-flight estimate starts from it" if estimate_on else "")
    elif warning and abs(rel_use) > limit:
        why = "the engagement had begun" if too_late else "hover.start_from_px4 is off"
        then = (f"still flying with {in_use:.2f} ({in_use_source}; {why})"
                + ("; the in-flight estimate corrects it once the app commands the thrust" if estimate_on
                   else "; hover.estimate is OFF: nothing corrects it"))
    else:
        then = f"flying with {in_use:.2f} ({in_use_source})" + (
            ", the in-flight estimate from there" if estimate_on else "")
    line = (f"{'WARNING ' if warning else ''}{head}PX4 commands {px4_commanded:.2f} (median of {samples}), the "
            f"app's estimate {app_estimate:.2f}, configured {configured:.2f}{mpc}: {what}; {then}")
    return HoverCheck(px4_commanded, samples, app_estimate, configured, mpc_thr_hover, in_use, rel_cfg, rel_use,
                      warning, flies, source, line)


# PX4 parameter -> (airframe key, tolerance, unit, what the app does with its own value).
PARAM_PAIRS: dict[str, tuple[str, float, str, str]] = {
    "MPC_TILTMAX_AIR": ("max_tilt", 0.5, " deg", "the app clamps its attitude setpoints to airframe.max_tilt "
                        "(PX4's limit is for its own modes)"),
    "MPC_THR_MIN": ("thrust_min", 0.005, "", "the app never sends less than airframe.thrust_min (PX4's minimum "
                    "is for its own modes)"),
}


def param_mismatches(px4: Mapping[str, float | None], airframe: object) -> list[str]:
    """One line per PX4 parameter that disagrees with the airframe's value, saying which one the app uses;
    a parameter PX4 did not give is not compared."""
    out = []
    for name, (key, tol, unit, uses) in PARAM_PAIRS.items():
        v = px4.get(name)
        mine = float(getattr(airframe, key))
        if v is None or not math.isfinite(v) or abs(v - mine) <= tol:
            continue
        out.append(f"PX4 {name} {v:g}{unit}, config airframe.{key} {mine:g}{unit}: {uses}")
    return out
