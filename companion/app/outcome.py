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

An intercept (``app.on_close: pull_up``) claims no pass: its target is scored as an intercept, not a gate (the
vehicle crosses the target's plane over its top, which the gate score would call a miss). ``intercepts`` scores
each pull-up with the one scorer the in-process studies use (companion/scoring.py ``PullUpScorer``): the
predicted miss at the pull-up (the last true state before it, extrapolated to the target's plane as the paper
does) and the clearance (the least true distance between the vehicle and the target's box after it). The verdict:

* the pull-up came within ``IMPACT_DISTANCE`` of the target's box: ``INTERCEPT_IMPACT`` (it hit);
* it cleared, but the track before the pull-up would have crossed the target's plane outside its box:
  ``TARGET_MISSED`` (nothing to pull up from);
* else ``OK``: "intercept: pulled up at 23.8 m/s, predicted miss 0.40 m, cleared by 1.70 m (ground truth)".

The judge's samples arrive from the telemetry monitor (vehicle position) and the camera (gate
positions) on the same monotonic clock. A vehicle sample waits (at most ``MAX_WAIT``) for the gate sample at or
after its time, so a moving gate is interpolated to it, as a re-score of the flight log does (the log's truth rows
carry the sample's own time, ``t_truth``); it used to be extrapolated from the last two gate samples, which
put a swinging gate centimetres off when frames came late under load. After the flight every waiting sample is
scored (extrapolated past the last gate sample).

Why a PX4 flight's printed gate line once said 0.05 m while summary.json's truth said 0.121 m: the line was
re-scored from the flight log, the truth judged live here, on other samples (rows stamped when written, the gate
extrapolated). The printed line reads this judge's record (``GateResult.as_dict`` keeps the crossing time for
it; tests/app/test_outcome.py reproduces the case).
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.app.states import Reason
from companion.engagement import GatePass
from companion.frames import ned_to_enu
from companion.scoring import GatePlane, PlaneCrossing, PullUpScorer, distance_to_rect, rect_basis, signed_distance

# m: closer than this to the target's box after a pull-up is an impact (a 500 mm quadrotor's half-span with its
# propellers is ~0.4 m; the truth is the vehicle's centre).
IMPACT_DISTANCE = 0.5
TRACK_MAX = 60_000  # vehicle samples kept per target for the intercept score (20 min at 50 Hz)


GATE_HISTORY = 64  # gate samples kept per gate for interpolation (~2 s at 30 Hz)
MAX_WAIT = 0.5  # s: a vehicle sample waits at most this long for the gate sample after it, then extrapolates


@dataclass
class _Gate:
    k: int
    radius: float
    plane: GatePlane
    first: PlaneCrossing | None = None  # the first crossing: the gate's score
    samples: deque = field(default_factory=lambda: deque(maxlen=GATE_HISTORY))  # (t, centre NED), time order
    # vehicle samples (t, p, v) not yet scored: they wait for a gate sample at or after their time, so the gate
    # is interpolated to them (as a re-score of the flight log does) rather than extrapolated, however late the
    # camera's frames come under load
    pending: deque = field(default_factory=deque)
    # (t, vehicle position, vehicle velocity, centre, centre velocity), NED: the intercept's score reads it
    track: deque = field(default_factory=lambda: deque(maxlen=TRACK_MAX))

    def centre_at(self, t: float) -> np.ndarray:
        """Interpolated between the samples around ``t``; extrapolated from the last two beyond them."""
        s = self.samples
        (t1, c1) = s[-1]
        if len(s) < 2:
            return c1
        if t < t1:
            for i in range(len(s) - 2, -1, -1):
                t0, c0 = s[i]
                if t0 <= t:
                    ta, ca = s[i + 1]
                    return c0 + (ca - c0) * ((t - t0) / (ta - t0))
            return s[0][1]  # older than every sample kept
        t0, c0 = s[-2]
        return c1 + (c1 - c0) * ((t - t1) / (t1 - t0))

    def velocity(self, t: float) -> np.ndarray:
        s = self.samples
        if len(s) < 2:
            return np.zeros(3)
        i = len(s) - 1
        while i > 1 and s[i - 1][0] > t:
            i -= 1
        (t0, c0), (t1, c1) = s[i - 1], s[i]
        return (c1 - c0) / (t1 - t0)

    def drain(self, t_now: float | None) -> None:
        """Score the waiting vehicle samples the gate's samples now reach (all of them when ``t_now`` is None:
        the flight is over; also those older than ``MAX_WAIT`` before ``t_now``: the camera stopped)."""
        while self.pending and self.samples:
            t, p, v = self.pending[0]
            if t > self.samples[-1][0] and t_now is not None and t_now - t <= MAX_WAIT:
                return
            self.pending.popleft()
            c = self.centre_at(t)
            if self.first is None:
                self.first = self.plane.update(t, p, c)
            self.track.append((t, p, v, c, self.velocity(t)))


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


@dataclass(frozen=True)
class InterceptResult:
    """One pull-up against the true target (companion/scoring.py PullUpScorer's numbers)."""

    gate: int  # the judge's target (the synthetic camera's gate number)
    t_pullup: float  # monotonic time of the pull-up decision
    predicted_miss: float | None  # m from the target's centre; None: not closing on its plane at the pull-up
    on_target: bool  # that crossing inside the target's box
    clearance: float | None  # m, least distance to the target's box after the pull-up; None: no sample after it
    speed_at_pullup: float | None  # m/s, true
    range_at_pullup: float | None  # m, to the target's box at the last sample before the pull-up
    box: tuple[float, float]  # (width, height), m

    @property
    def impact(self) -> bool:
        return self.clearance is not None and self.clearance < IMPACT_DISTANCE

    def as_dict(self) -> dict:
        return {"gate": self.gate, "t_monotonic_s": self.t_pullup, "predicted_miss_m": self.predicted_miss,
                "on_target": self.on_target, "clearance_m": self.clearance, "speed_at_pullup_mps": self.speed_at_pullup,
                "range_at_pullup_m": self.range_at_pullup, "width_m": self.box[0], "height_m": self.box[1],
                "impact": self.impact}


class GateJudge:
    """Feed it gate samples and vehicle positions (NED, metres, one monotonic clock); ask ``results``, and for
    the pull-ups of an intercept, ``intercepts``.

    ``box``: the targets' (width, height) in metres, for the intercept's clearance (None: a ring's bounding
    square, 2 x its radius)."""

    def __init__(self, box: tuple[float, float] | None = None) -> None:
        self._gates: dict[int, _Gate] = {}
        self.vehicle_samples = 0
        self.box = box
        self._prev: tuple[float, np.ndarray] | None = None
        self._lock = threading.Lock()

    @classmethod
    def for_config(cls, cfg: Any) -> GateJudge:
        """The synthetic camera's targets: a ring's box, or sim.target's rectangle (companion/app/synthcam.py)."""
        return cls(tuple(cfg.sim.target.size(cfg.app.synthetic.radius)))

    def gate(self, t: float, k: int, centre_ned: np.ndarray, normal_ned: np.ndarray, radius: float) -> None:
        with self._lock:
            g = self._gates.get(k)
            if g is None:
                g = self._gates[k] = _Gate(k, float(radius), GatePlane(np.asarray(normal_ned, dtype=float)))
            if g.samples and t <= g.samples[-1][0]:
                return
            g.samples.append((float(t), np.asarray(centre_ned, dtype=float).copy()))
            g.drain(self._prev[0] if self._prev is not None else t)

    def vehicle(self, t: float, p_ned: np.ndarray, v_ned: np.ndarray | None = None) -> None:
        """One true sample; without a velocity it is the difference from the previous sample."""
        p = np.asarray(p_ned, dtype=float)
        if not np.isfinite(p).all():
            return
        if v_ned is not None and np.isfinite(np.asarray(v_ned, dtype=float)).all():
            v = np.asarray(v_ned, dtype=float).copy()
        elif self._prev is not None and t > self._prev[0]:
            v = (p - self._prev[1]) / (t - self._prev[0])
        else:
            v = np.zeros(3)
        if self._prev is not None and t <= self._prev[0]:
            return  # the same sample again (the telemetry loop logs the latest one every period)
        self._prev = (t, p.copy())
        self.vehicle_samples += 1
        with self._lock:  # the image camera adds gates and samples from its worker thread
            for g in self._gates.values():
                g.pending.append((t, p.copy(), v))
                g.drain(t)

    def _flush(self) -> None:
        """Score every waiting sample (the flight is over: no later gate sample will come)."""
        with self._lock:
            for g in self._gates.values():
                g.drain(None)

    @property
    def has_truth(self) -> bool:
        return bool(self._gates) and self.vehicle_samples >= 2

    def results(self) -> list[GateResult]:
        self._flush()
        out = []
        for k in sorted(self._gates):
            g = self._gates[k]
            r = g.first
            out.append(GateResult(k, g.radius, False) if r is None else GateResult(k, g.radius, True, r.t, r.d_center))
        return out

    def intercepts(self, passes: list[GatePass]) -> dict[int, InterceptResult]:
        """Each pulled-up pass (keyed by its gate number) scored against the target in front of the vehicle and
        nearest to it at the pull-up. A pass with no target ahead, or no sample before its pull-up, is left out."""
        self._flush()
        out: dict[int, InterceptResult] = {}
        for gp in passes:
            if gp.status != "pulled_up" or gp.t_end is None:
                continue
            r = self._intercept(gp.t_end)
            if r is not None:
                out[gp.gate] = r
        return out

    def _intercept(self, t_pullup: float) -> InterceptResult | None:
        best: tuple[float, _Gate] | None = None
        for g in list(self._gates.values()):
            before = [s for s in g.track if s[0] < t_pullup]
            if not before:
                continue
            _, p, _, c, _ = before[-1]
            if signed_distance(g.plane.normal, p, c) <= 0.0:
                continue  # behind it already: not the target pulled up from
            w, h = self.box or (2.0 * g.radius, 2.0 * g.radius)
            d = distance_to_rect(p, c, rect_basis(g.plane.normal), 0.5 * w, 0.5 * h)
            if best is None or d < best[0]:
                best = (d, g)
        if best is None:
            return None
        rng, g = best
        w, h = self.box or (2.0 * g.radius, 2.0 * g.radius)
        # ENU for the scorer (its min_altitude reads z up); distances do not depend on the frame.
        sc = PullUpScorer(ned_to_enu(g.plane.normal), 0.5 * w, 0.5 * h)
        for t, p, v, c, cv in g.track:
            sc.update(t, ned_to_enu(p), ned_to_enu(v), ned_to_enu(c), ned_to_enu(cv), t >= t_pullup)
        d = sc.as_dict()
        return InterceptResult(g.k, t_pullup, d["predicted_miss_m"], bool(d["on_target"]), d["clearance_m"],
                               d["speed_at_pullup_mps"], rng, (w, h))


def verdict(passes: list[GatePass], truth: list[GateResult] | None,
            intercepts: dict[int, InterceptResult] | None = None) -> tuple[Reason, str]:
    """(reason, one line) for a flight that ended normally, from what was claimed and, if any, the truth.

    ``intercepts``: the judge's score of each pulled-up pass (``GateJudge.intercepts``); the targets they name are
    intercepts, not gates, and are not scored as gates."""
    claimed = [p for p in passes if p.status in ("confirmed", "not_confirmed")]
    pulled = [p for p in passes if p.status == "pulled_up"]
    icpt = intercepts or {}
    if truth is not None:
        targets = {r.gate for r in icpt.values()}
        for p in pulled:  # an intercept's verdict first: an impact outranks anything a gate says
            r = icpt.get(p.gate)
            if r is not None and r.impact:
                return Reason.INTERCEPT_IMPACT, (f"intercept: the pull-up did not clear target {r.gate}: came within "
                                                 f"{r.clearance:.2f} m of its box (ground truth; an impact is < "
                                                 f"{IMPACT_DISTANCE:.1f} m)")
        for p in pulled:
            r = icpt.get(p.gate)
            if r is not None and not r.on_target:
                miss = "not closing on its plane" if r.predicted_miss is None else \
                    f"predicted miss {r.predicted_miss:.2f} m, outside its {r.box[0]:g} x {r.box[1]:g} m box"
                return Reason.TARGET_MISSED, f"intercept: target {r.gate} missed at the pull-up ({miss}; ground truth)"
        gates = [g for g in truth if g.gate not in targets]
        missed = [g for g in gates if g.crossed and not g.through]
        through = [g for g in gates if g.through]
        if missed:
            g = missed[0]
            return Reason.GATE_MISSED, (f"gate {g.gate} missed: crossed its plane {g.d_center:.2f} m from the centre "
                                        f"(radius {g.radius:.2f} m)")
        if len(through) < len(claimed):
            return Reason.GATE_MISSED, (f"{len(claimed)} pass(es) claimed but ground truth saw {len(through)} gate(s) "
                                        "flown through")
        lines = [_intercept_line(icpt.get(p.gate)) for p in pulled]
        if claimed or not pulled:
            lines.insert(0, f"ground truth: {len(through)} gate(s) flown through")
        return Reason.OK, "; ".join(lines)
    unconf = [p for p in passes if p.status == "not_confirmed"]
    if unconf:
        return Reason.PASS_NOT_CONFIRMED, (f"gate {unconf[0].gate}: pass not confirmed ({unconf[0].evidence}); "
                                           "no ground truth")
    if pulled:
        return Reason.OK, f"intercept: pulled up ({len(pulled)}); no ground truth"
    return Reason.OK, "no ground truth; every pass confirmed by the camera"


def _intercept_line(r: InterceptResult | None) -> str:
    if r is None:
        return "intercept: pulled up; no ground truth of a target ahead"
    speed = "" if r.speed_at_pullup is None else f" at {r.speed_at_pullup:.1f} m/s"
    rng = "" if r.range_at_pullup is None else f" {r.range_at_pullup:.1f} m before target {r.gate}"
    miss = "" if r.predicted_miss is None else f", predicted miss {r.predicted_miss:.2f} m"
    clear = "not measured (no sample after it)" if r.clearance is None else f"by {r.clearance:.2f} m"
    return f"intercept: pulled up{rng}{speed}{miss}, cleared {clear} (ground truth)"
