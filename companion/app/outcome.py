"""The flight's honest outcome: was each gate flown through? (pure; ground truth scores, never steers)

Where ground truth exists (our simulated PX4, PX4 SITL: the flight's truth source and the
synthetic camera's gate log) the ``GateJudge`` scores each gate like the in-process studies do
(companion/scoring.py, the geometry the simulator and the flight log use too: the first crossing of the
gate plane from the vehicle's side, distance to the centre there against the gate radius). Its results
are the flight's one record of the gates: the verdict, summary.json's "truth" and the gate lines printed
after a flight (companion/flightlog.py ``flight_crossings``) all read them. ``verdict`` turns that, and
what the engagement claimed, into the flight's reason (its exit code):

* with truth: a gate plane crossed outside the radius, or fewer gates flown through than passes
  claimed, is ``GATE_MISSED``;
* without truth (the field): a pass that ended on its timeout (no evidence the gate went behind) is
  ``PASS_NOT_CONFIRMED``.

The judge's samples arrive from the telemetry monitor (vehicle position) and the camera (gate
positions) on the same monotonic clock; a moving gate is extrapolated linearly from its last two
samples to each vehicle sample.

Why a PX4 flight's printed gate line once said 0.05 m while summary.json's truth said 0.121 m: the line was
re-scored from the flight log, the truth judged live here, on other samples. The log stamps a truth row
when the telemetry loop writes it (every 50 ms, the latest sample again if none came since) while the judge
takes each sample at its arrival time, and the log interpolates the gate between its rows where the judge
extrapolates it: a moving gate is compared at other instants. The printed line now reads this judge's
record (``GateResult.as_dict`` keeps the crossing time for it; tests/app/test_outcome.py reproduces the case).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from companion.app.states import Reason
from companion.engagement import GatePass
from companion.scoring import GatePlane, PlaneCrossing


@dataclass
class _Gate:
    k: int
    radius: float
    plane: GatePlane
    first: PlaneCrossing | None = None  # the first crossing: the gate's score
    samples: list[tuple[float, np.ndarray]] = field(default_factory=list)  # (t, centre NED), the last two

    def centre_at(self, t: float) -> np.ndarray:
        (t1, c1) = self.samples[-1]
        if len(self.samples) < 2:
            return c1
        t0, c0 = self.samples[-2]
        return c1 if t1 <= t0 else c1 + (c1 - c0) * ((t - t1) / (t1 - t0))


@dataclass(frozen=True)
class GateResult:
    gate: int
    radius: float
    crossed: bool
    t: float | None = None  # monotonic time of the crossing
    d_center: float | None = None

    @property
    def through(self) -> bool:
        return self.crossed and self.d_center is not None and self.d_center < self.radius

    def as_dict(self) -> dict:
        # t_monotonic_s: the flight log's meta.json "t0_monotonic" is its 0 (flightlog.flight_crossings)
        return {"gate": self.gate, "radius_m": self.radius, "crossed": self.crossed,
                "d_center_m": self.d_center, "through": self.through, "t_monotonic_s": self.t}


class GateJudge:
    """Feed it gate samples and vehicle positions (NED, metres, one monotonic clock); ask ``results``."""

    def __init__(self) -> None:
        self._gates: dict[int, _Gate] = {}
        self.vehicle_samples = 0

    def gate(self, t: float, k: int, centre_ned: np.ndarray, normal_ned: np.ndarray, radius: float) -> None:
        g = self._gates.get(k)
        if g is None:
            g = self._gates[k] = _Gate(k, float(radius), GatePlane(np.asarray(normal_ned, dtype=float)))
        if g.samples and t <= g.samples[-1][0]:
            return
        g.samples = [*g.samples[-1:], (float(t), np.asarray(centre_ned, dtype=float).copy())]

    def vehicle(self, t: float, p_ned: np.ndarray) -> None:
        p = np.asarray(p_ned, dtype=float)
        if not np.isfinite(p).all():
            return
        self.vehicle_samples += 1
        for g in list(self._gates.values()):  # a copy: the image camera adds gates from its worker thread
            if g.first is None:
                g.first = g.plane.update(t, p, g.centre_at(t))

    @property
    def has_truth(self) -> bool:
        return bool(self._gates) and self.vehicle_samples >= 2

    def results(self) -> list[GateResult]:
        out = []
        for k in sorted(self._gates):
            g = self._gates[k]
            r = g.first
            out.append(GateResult(k, g.radius, False) if r is None else GateResult(k, g.radius, True, r.t, r.d_center))
        return out


def verdict(passes: list[GatePass], truth: list[GateResult] | None) -> tuple[Reason, str]:
    """(reason, one line) for a flight that ended normally, from what was claimed and, if any, the truth."""
    claimed = [p for p in passes if p.status in ("confirmed", "not_confirmed")]
    if truth is not None:
        missed = [g for g in truth if g.crossed and not g.through]
        through = [g for g in truth if g.through]
        if missed:
            g = missed[0]
            return Reason.GATE_MISSED, (f"gate {g.gate} missed: crossed its plane {g.d_center:.2f} m from the centre "
                                        f"(radius {g.radius:.2f} m)")
        if len(through) < len(claimed):
            return Reason.GATE_MISSED, (f"{len(claimed)} pass(es) claimed but ground truth saw {len(through)} gate(s) "
                                        "flown through")
        return Reason.OK, f"ground truth: {len(through)} gate(s) flown through"
    unconf = [p for p in passes if p.status == "not_confirmed"]
    if unconf:
        return Reason.PASS_NOT_CONFIRMED, (f"gate {unconf[0].gate}: pass not confirmed ({unconf[0].evidence}); "
                                           "no ground truth")
    return Reason.OK, "no ground truth; every pass confirmed by the camera"
