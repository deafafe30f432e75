"""Scoring a run from ground truth: gate-plane crossing, d_center, t_gate, success per gate radius.

Ground truth (positions) is used here and only here: the controller never sees it.
The gate plane passes through the moving gate centre with the gate's fixed normal. The run is
decided by the first crossing of that plane from the vehicle's side (normal side) to the other:
``d_center`` is the distance from the crossing point to the gate centre at that instant. Between
two samples, vehicle and gate move linearly (at 30 Hz the error is ~a dt^2 / 8, about 1 mm): that geometry
is companion/scoring.py's, shared with the app's judge and the flight log.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from companion.scoring import GatePlane, signed_distance

FailReason = Literal["fov_lost", "timeout", "ground", "missed"]


def rkey(radius: float) -> str:
    """JSON key of a gate radius: "0.5", "1.0", "2.0"."""
    return str(float(radius))


@dataclass
class RunOutcome:
    """How a run ended (independent of the gate radius, except through ``d_center``)."""

    crossed: bool
    t_gate: float | None  # s, time of the plane crossing
    d_center: float | None  # m
    reason: FailReason | None  # why the run ended without a crossing (None if it crossed)
    crossing_point: np.ndarray | None = None
    top_speed: float = 0.0  # m/s, largest true speed before the end

    def success(self, radius: float) -> bool:
        return self.crossed and self.d_center is not None and self.d_center < radius

    def failure(self, radius: float) -> FailReason | None:
        """None for a success; 'missed' when the plane was crossed outside this radius."""
        if self.crossed:
            return None if self.success(radius) else "missed"
        return self.reason

    def as_dict(self, radii: list[float]) -> dict:
        return {
            "crossed": self.crossed,
            "t_gate_s": self.t_gate,
            "d_center_m": self.d_center,
            "end_reason": self.reason,
            "top_speed_mps": self.top_speed,
            "success": {rkey(r): self.success(r) for r in radii},
            "failure": {rkey(r): self.failure(r) for r in radii},
        }


@dataclass
class PlaneCrossingScorer:
    """Feed it (t, vehicle position, gate centre) samples; it reports the first front-to-back crossing.

    The crossing geometry is companion/scoring.py's (the app's judge and the flight log use the same)."""

    normal: np.ndarray  # unit, points to the side the vehicle starts on
    _plane: GatePlane = field(init=False, repr=False)
    result: RunOutcome | None = field(default=None, init=False)

    def __post_init__(self) -> None:
        self._plane = GatePlane(self.normal)
        self.normal = self._plane.normal

    def signed_distance(self, p: np.ndarray, gate: np.ndarray) -> float:
        return signed_distance(self.normal, np.asarray(p, float), np.asarray(gate, float))

    def update(self, t: float, p: np.ndarray, gate: np.ndarray) -> RunOutcome | None:
        """Returns the outcome at the first crossing, else None."""
        if self.result is not None:
            return self.result
        c = self._plane.update(t, p, gate)
        if c is not None:
            self.result = RunOutcome(True, c.t, c.d_center, None, c.point)
        return self.result


def aggregate(outcomes: list[dict], radii: list[float]) -> dict:
    """Success rate per radius, mean/std t_gate and d_center over crossings, top speed, reasons."""
    n = len(outcomes)
    out: dict = {"runs": n}
    if n == 0:
        return out
    out["success"] = {rkey(r): sum(o["success"][rkey(r)] for o in outcomes) / n for r in radii}
    crossed = [o for o in outcomes if o["crossed"]]
    tg = [o["t_gate_s"] for o in crossed]
    dc = [o["d_center_m"] for o in crossed]
    out["crossed"] = len(crossed) / n
    out["t_gate_mean_s"] = float(np.mean(tg)) if tg else None
    out["d_center_mean_m"] = float(np.mean(dc)) if dc else None
    out["d_center_std_m"] = float(np.std(dc)) if dc else None
    out["top_speed_mps"] = float(max(o["top_speed_mps"] for o in outcomes))
    out["top_speed_mean_mps"] = float(np.mean([o["top_speed_mps"] for o in outcomes]))
    reasons: dict[str, dict[str, int]] = {}
    for r in radii:
        counts: dict[str, int] = {}
        for o in outcomes:
            f = o["failure"][rkey(r)]
            if f is not None:
                counts[f] = counts.get(f, 0) + 1
        reasons[rkey(r)] = counts
    out["failures"] = reasons
    out.update(setpoint_metrics(outcomes))
    return out


SETPOINT_METRICS = ("roll_osc_rms_rate_dps", "roll_osc_amp_deg", "roll_osc_freq_hz")


def setpoint_metrics(runs: list[dict]) -> dict:
    """Over runs: the largest commanded tilt, and the mean of each roll-oscillation figure (runs that have one)."""
    tilts = [r["max_tilt_deg"] for r in runs if r.get("max_tilt_deg") is not None]
    out: dict = {"max_tilt_deg": float(max(tilts)) if tilts else None}
    for k in SETPOINT_METRICS:
        vals = [r[k] for r in runs if r.get(k) is not None]
        out[f"{k}_mean"] = float(np.mean(vals)) if vals else None
    return out


def rect_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(horizontal in-plane axis, vertical in-plane axis, normal) of a target with a horizontal normal."""
    n = np.asarray(normal, float) / float(np.linalg.norm(normal))
    a = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(n, a)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u), n


def distance_to_rect(p: np.ndarray, centre: np.ndarray, basis: tuple[np.ndarray, np.ndarray, np.ndarray],
                     half_w: float, half_h: float) -> float:
    """Distance (m) from point p to the flat width x height rectangle (the target's box) at ``centre``."""
    u, w, n = basis
    q = np.asarray(p, float) - np.asarray(centre, float)
    da = max(abs(float(q @ u)) - half_w, 0.0)
    db = max(abs(float(q @ w)) - half_h, 0.0)
    return math.sqrt(da * da + db * db + float(q @ n) ** 2)


def predicted_miss(p: np.ndarray, v: np.ndarray, g: np.ndarray, gv: np.ndarray, normal: np.ndarray) -> float | None:
    """Distance from the target's centre where the vehicle would cross the target's plane, both extrapolated
    at their velocities (the paper's "predicted miss", from the last velocity before the pull-up); None when the
    vehicle was not closing on the plane."""
    n = np.asarray(normal, float) / float(np.linalg.norm(normal))
    r = np.asarray(p, float) - np.asarray(g, float)
    u = np.asarray(v, float) - np.asarray(gv, float)
    un = float(u @ n)
    if un >= -1e-9:
        return None
    s = -float(r @ n) / un
    return float(np.linalg.norm(r + u * s))


@dataclass
class PullUpScorer:
    """Scores an intercept with a pull-up from ground truth: the predicted miss at the pull-up (extrapolated from
    the last state before it) and the clearance (least distance between the vehicle and the target's box after
    it)."""

    normal: np.ndarray
    half_w: float
    half_h: float
    t_pullup: float | None = None
    miss: float | None = None  # m, predicted miss
    clearance: float = math.inf  # m, after the pull-up
    speed_at_pullup: float | None = None
    min_altitude: float = math.inf  # m, the vehicle's lowest true altitude over the whole run
    _last: tuple | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self._basis = rect_basis(self.normal)

    def update(self, t: float, p: np.ndarray, v: np.ndarray, g: np.ndarray, gv: np.ndarray, pulled: bool) -> None:
        """One frame: ``pulled`` once the engagement has pulled up (this frame's state is the first after it)."""
        self.min_altitude = min(self.min_altitude, float(p[2]))
        if not pulled:
            self._last = (p.copy(), v.copy(), g.copy(), np.asarray(gv, float).copy())
            return
        if self.t_pullup is None:
            self.t_pullup = t
            if self._last is not None:
                lp, lv, lg, lgv = self._last
                self.miss = predicted_miss(lp, lv, lg, lgv, self.normal)
                self.speed_at_pullup = float(np.linalg.norm(lv))
        self.clearance = min(self.clearance, distance_to_rect(p, g, self._basis, self.half_w, self.half_h))

    def as_dict(self) -> dict:
        return {"pulled_up": self.t_pullup is not None, "t_pullup_s": self.t_pullup, "predicted_miss_m": self.miss,
                "clearance_m": self.clearance if math.isfinite(self.clearance) else None,
                "speed_at_pullup_mps": self.speed_at_pullup,
                "min_altitude_m": self.min_altitude if math.isfinite(self.min_altitude) else None}
