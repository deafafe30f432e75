"""Gate-plane crossing geometry: the one scorer of "where did the vehicle cross the gate's plane" (pure).

Used by the in-process simulator (companion/sim/scoring.py, sample by sample), the app's live ground-truth
judge (companion/app/outcome.py) and the flight-log re-score (companion/flightlog.py, over arrays): all three
call ``segment_crossing``, so one pair of samples gives one number whichever path scores it.

The gate plane passes through the moving gate centre with the gate's fixed normal (unit, pointing to the
side the vehicle starts on). A crossing is a change of the signed distance from the normal side (> 0) to the
other (<= 0) between two samples. Between two samples, vehicle and gate move linearly (at 30 Hz the error is
~a dt^2 / 8, about 1 mm): the crossing is where that interpolated signed distance is 0, and ``d_center`` is
the distance from the vehicle to the interpolated gate centre there (in the plane, since the signed distance
is 0 at that point).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PlaneCrossing:
    """One front-to-back crossing of a gate plane."""

    t: float  # s, time of the crossing (on the samples' clock)
    d_center: float  # m, from the gate centre at the crossing, in the plane
    point: np.ndarray  # vehicle position at the crossing
    angle_deg: float  # between the vehicle's path relative to the gate and the plane's normal (0: square on)


def unit(normal: Sequence[float] | np.ndarray) -> np.ndarray:
    n = np.asarray(normal, dtype=float)
    return n / np.linalg.norm(n)


def signed_distance(normal: np.ndarray, p: np.ndarray, gate: np.ndarray) -> float:
    """Distance of ``p`` from the plane through ``gate`` along the unit ``normal`` (> 0 on the normal side)."""
    return float(normal @ (p - gate))


def segment_crossing(normal: np.ndarray, t0: float, p0: np.ndarray, g0: np.ndarray, s0: float,
                     t1: float, p1: np.ndarray, g1: np.ndarray, s1: float) -> PlaneCrossing | None:
    """The crossing between two samples (time, vehicle, gate centre, signed distance), None if not crossed."""
    if not s0 > 0.0 >= s1:
        return None
    tau = s0 / (s0 - s1)
    pc = p0 + tau * (p1 - p0)
    gc = g0 + tau * (g1 - g0)
    d = float(np.linalg.norm(pc - gc))
    rel = (p1 - g1) - (p0 - g0)  # the vehicle's path relative to the gate; rel @ normal = s1 - s0 < 0
    cos = float(-(normal @ rel) / np.linalg.norm(rel))
    return PlaneCrossing(t0 + tau * (t1 - t0), d, pc, math.degrees(math.acos(min(1.0, max(-1.0, cos)))))


class GatePlane:
    """Streaming: feed (t, vehicle position, gate centre) samples; each front-to-back crossing is returned once."""

    def __init__(self, normal: Sequence[float] | np.ndarray) -> None:
        self.normal = unit(normal)
        self._prev: tuple[float, np.ndarray, np.ndarray, float] | None = None

    def update(self, t: float, p: np.ndarray, gate: np.ndarray) -> PlaneCrossing | None:
        p = np.asarray(p, dtype=float)
        gate = np.asarray(gate, dtype=float)
        s = signed_distance(self.normal, p, gate)
        c = None if self._prev is None else segment_crossing(self.normal, *self._prev, t, p, gate, s)
        self._prev = (t, p.copy(), gate.copy(), s)
        return c


def plane_crossings(normal: Sequence[float] | np.ndarray, t: np.ndarray, p: np.ndarray,
                    gate: np.ndarray) -> list[PlaneCrossing]:
    """Every front-to-back crossing over sample arrays (t: (N,), p and gate: (N, 3)).

    The same signed distance and the same ``segment_crossing`` as ``GatePlane`` fed the rows one by one, so
    the numbers are the streaming scorer's (tests/test_scoring_core.py checks it).
    """
    n = unit(normal)
    p = np.asarray(p, dtype=float)
    gate = np.asarray(gate, dtype=float)
    ts = [float(x) for x in t]
    s = [signed_distance(n, p[i], gate[i]) for i in range(len(ts))]
    out: list[PlaneCrossing] = []
    for i in range(len(ts) - 1):
        c = segment_crossing(n, ts[i], p[i], gate[i], s[i], ts[i + 1], p[i + 1], gate[i + 1], s[i + 1])
        if c is not None:
            out.append(c)
    return out
