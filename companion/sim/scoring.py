"""Scoring a run from ground truth: gate-plane crossing, d_center, t_gate, success per gate radius.

Ground truth (positions) is used here and only here: the controller never sees it.
The gate plane passes through the moving gate centre with the gate's fixed normal. The run is
decided by the first crossing of that plane from the vehicle's side (normal side) to the other:
``d_center`` is the distance from the crossing point to the gate centre at that instant. Between
two samples, vehicle and gate move linearly (at 30 Hz the error is ~a dt^2 / 8, about 1 mm): that geometry
is companion/scoring.py's, shared with the app's judge and the flight log.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

# The pull-up's scorer is the core's (the app's judge on PX4 uses the same one): re-exported for the simulator.
from companion.scoring import (  # noqa: F401
    GatePlane,
    PullUpScorer,
    distance_to_rect,
    predicted_miss,
    rect_basis,
    signed_distance,
)

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
