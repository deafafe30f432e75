"""Gate-plane crossing geometry: the one scorer of "where did the vehicle cross the gate's plane" (pure).

Also the one scorer of an intercept with a pull-up (``PullUpScorer``: predicted miss at the pull-up, clearance of
the target's box after it), for the simulator and the app's judge alike.

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
from dataclasses import dataclass, field

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
    return float(normal.dot(p - gate))  # .dot: the same BLAS ddot as @, without matmul's dispatch (every frame)


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


# ------------------------------------------------------------------------------ intercept with a pull-up

SEGMENT_STEPS = tuple((k + 1) / 8 for k in range(8))  # the clearance between two samples: 8 points along it


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


def predicted_offset(p: np.ndarray, v: np.ndarray, g: np.ndarray, gv: np.ndarray,
                     normal: np.ndarray) -> np.ndarray | None:
    """Where the vehicle would cross the target's plane, from the target's centre (a vector in the plane), both
    extrapolated at their velocities; None when the vehicle was not closing on the plane."""
    n = np.asarray(normal, float) / float(np.linalg.norm(normal))
    r = np.asarray(p, float) - np.asarray(g, float)
    u = np.asarray(v, float) - np.asarray(gv, float)
    un = float(u @ n)
    if un >= -1e-9:
        return None
    s = -float(r @ n) / un
    return r + u * s


def predicted_miss(p: np.ndarray, v: np.ndarray, g: np.ndarray, gv: np.ndarray, normal: np.ndarray) -> float | None:
    """Distance from the target's centre where the vehicle would cross the target's plane, both extrapolated
    at their velocities (the paper's "predicted miss", from the last velocity before the pull-up); None when the
    vehicle was not closing on the plane."""
    off = predicted_offset(p, v, g, gv, normal)
    return None if off is None else float(np.linalg.norm(off))


@dataclass
class PullUpScorer:
    """Scores an intercept with a pull-up from ground truth: the predicted miss at the pull-up (extrapolated from
    the last state before it) and the clearance (least distance between the vehicle and the target's box after
    it). One scorer for the in-process simulator (companion/sim/runner.py, per frame) and the app's judge on a
    simulated or SITL PX4 (companion/app/outcome.py, per truth sample)."""

    normal: np.ndarray
    half_w: float
    half_h: float
    t_pullup: float | None = None
    miss: float | None = None  # m, predicted miss
    on_target: bool = False  # the predicted crossing lies inside the target's box (it would have been hit)
    clearance: float = math.inf  # m, after the pull-up
    speed_at_pullup: float | None = None
    min_altitude: float = math.inf  # m, the vehicle's lowest true altitude over the whole run
    _last: tuple | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self._basis = rect_basis(self.normal)

    def update(self, t: float, p: np.ndarray, v: np.ndarray, g: np.ndarray, gv: np.ndarray, pulled: bool) -> None:
        """One sample: ``pulled`` once the engagement has pulled up (this sample is the first after it)."""
        p = np.asarray(p, float)
        g = np.asarray(g, float)
        self.min_altitude = min(self.min_altitude, float(p[2]))
        if not pulled:
            self._last = (p.copy(), np.asarray(v, float).copy(), g.copy(), np.asarray(gv, float).copy())
            return
        if self.t_pullup is None:
            self.t_pullup = t
            if self._last is not None:
                lp, lv, lg, lgv = self._last
                off = predicted_offset(lp, lv, lg, lgv, self.normal)
                if off is not None:
                    u, w, _ = self._basis
                    self.miss = float(np.linalg.norm(off))
                    # Inside the target's box: the track before the pull-up would have hit it.
                    self.on_target = abs(float(off @ u)) <= self.half_w and abs(float(off @ w)) <= self.half_h
                self.speed_at_pullup = float(np.linalg.norm(lv))
            self._last = None
        # Between two samples both move linearly: the least distance along that segment, not only at its ends
        # (20 Hz truth at 24 m/s is 1.2 m apart; the closest approach over the target's top falls between them).
        prev = self._last
        steps: tuple[float, ...] = (1.0,)
        if prev is not None:
            steps = SEGMENT_STEPS
            n = self._basis[2]
            s0, s1 = float(n @ (prev[0] - prev[2])), float(n @ (p - g))
            if s0 * s1 < 0.0:  # through the target's plane: where (in its box, 0: an impact) counts exactly
                steps = (*steps, s0 / (s0 - s1))
        for w in steps:
            q = p if prev is None else prev[0] + w * (p - prev[0])
            c = g if prev is None else prev[2] + w * (g - prev[2])
            self.clearance = min(self.clearance, distance_to_rect(q, c, self._basis, self.half_w, self.half_h))
        self._last = (p.copy(), None, g.copy(), None)

    def as_dict(self) -> dict:
        return {"pulled_up": self.t_pullup is not None, "t_pullup_s": self.t_pullup, "predicted_miss_m": self.miss,
                "on_target": self.on_target,
                "clearance_m": self.clearance if math.isfinite(self.clearance) else None,
                "speed_at_pullup_mps": self.speed_at_pullup,
                "min_altitude_m": self.min_altitude if math.isfinite(self.min_altitude) else None}
