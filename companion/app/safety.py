"""Pure safety logic of the flight app (no I/O, no asyncio): unit-testable with plain numbers.

* ``CloseDetector``: is the gate about to be passed? Time-to-contact from the box's expansion
  (tau = s / (ds/dt) for the box size s, which grows like 1/range) or the box size itself.
* ``SafetyLimits``: target lost for T seconds, barometric altitude floor, maximum engagement time.
* ``mode_is_pilot``: a flight mode the app did not ask for means the pilot has taken over.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from companion.app.config import AppConfig, SafetyConfig
from companion.app.states import Reason
from perception.types import BoundingBox


@dataclass(frozen=True)
class CloseEstimate:
    size_frac: float  # larger box side / image width
    ttc: float  # s; inf when the box is not growing
    close: bool
    why: str


class CloseDetector:
    """Box history of one engagement -> "the gate is about to be passed"."""

    def __init__(self, app: AppConfig, image_width: int, window_s: float = 0.25, min_samples: int = 7,
                 persist: int = 2) -> None:
        self.trigger = app.close_trigger
        self.ttc_threshold = app.ttc_threshold
        self.size_threshold = app.size_threshold
        self.width = float(image_width)
        self.window_s = window_s
        self.min_samples = min_samples
        self.persist = persist  # consecutive frames below the TTC threshold: one noisy slope is not a contact
        self._hist: deque[tuple[float, float]] = deque(maxlen=64)
        self._below = 0

    def reset(self) -> None:
        self._hist.clear()
        self._below = 0

    def ttc(self) -> float:
        """Least-squares slope of size over the recent window: noise on single frames averages out.

        Scalar Python on purpose: the window holds ~8 samples and this runs every frame of every simulated run.
        """
        if len(self._hist) < self.min_samples:
            return math.inf
        t_last = self._hist[-1][0]
        pts = []
        for t, s in reversed(self._hist):  # newest first; stop at the window's start
            if t_last - t > self.window_s:
                break
            pts.append((t, s))
        pts.reverse()
        # A full window only: a slope over a few frames right after acquisition is mostly pixel noise.
        n = len(pts)
        if n < self.min_samples or pts[-1][0] - pts[0][0] < 0.8 * self.window_s:
            return math.inf
        t_mean = sum(t for t, _ in pts) / n
        s_mean = sum(s for _, s in pts) / n
        denom = sum((t - t_mean) ** 2 for t, _ in pts)
        if denom <= 0.0:
            return math.inf
        slope = sum((t - t_mean) * (s - s_mean) for t, s in pts) / denom
        if slope <= 0.0:
            return math.inf
        # The fit describes the window's centre; the contact time is the same instant, seen from now.
        return max(0.0, s_mean / slope - (t_last - t_mean))

    def update(self, t: float, box: BoundingBox | None, valid: bool) -> CloseEstimate:
        if valid and box is not None:
            self._hist.append((t, max(box.w, box.h)))
        size = self._hist[-1][1] / self.width if self._hist else 0.0
        tau = self.ttc()
        self._below = self._below + 1 if tau < self.ttc_threshold else 0
        by_ttc = self.trigger in ("ttc", "either") and self._below >= self.persist
        by_size = self.trigger in ("size", "either") and size > self.size_threshold
        why = ""
        if by_ttc:
            why = f"time-to-contact {tau:.2f} s < {self.ttc_threshold:.2f} s"
        elif by_size:
            why = f"box {size:.2f} of image width > {self.size_threshold:.2f}"
        return CloseEstimate(size, tau, by_ttc or by_size, why)


@dataclass(frozen=True)
class Abort:
    reason: Reason
    detail: str


class SafetyLimits:
    """Abort checks that run on every control step of an engagement."""

    def __init__(self, safety: SafetyConfig) -> None:
        self.cfg = safety

    def check(
        self,
        now: float,
        engage_start: float,
        last_valid_box: float,
        baro_rel_alt: float | None,
    ) -> Abort | None:
        c = self.cfg
        if baro_rel_alt is not None and math.isfinite(baro_rel_alt) and baro_rel_alt < c.altitude_floor:
            return Abort(Reason.ALTITUDE_FLOOR,
                         f"barometric altitude {baro_rel_alt:.1f} m below the floor {c.altitude_floor:.1f} m")
        lost = now - last_valid_box
        if lost > c.target_lost_timeout:
            return Abort(Reason.TARGET_LOST, f"no usable box for {lost:.2f} s (limit {c.target_lost_timeout:.2f} s)")
        engaged = now - engage_start
        if engaged > c.max_engagement_time:
            return Abort(Reason.MAX_ENGAGEMENT,
                         f"engaged for {engaged:.1f} s (limit {c.max_engagement_time:.1f} s)")
        return None


# PX4 modes the app itself puts the vehicle in (or that PX4 passes through on its own) per phase.
# Anything else while we are responsible means the pilot (or a failsafe) took over.
EXPECTED_MODES: dict[str, frozenset[str]] = {
    "takeoff": frozenset({"TAKEOFF", "HOLD", "READY", "UNKNOWN"}),
    "hold": frozenset({"HOLD"}),
    "offboard": frozenset({"OFFBOARD"}),
    "land": frozenset({"LAND", "HOLD", "READY", "UNKNOWN"}),
}


def mode_is_pilot(phase: str, mode: str, pilot_modes_ok: frozenset[str] = frozenset()) -> bool:
    """True when ``mode`` (MAVSDK FlightMode name) is not one this phase expects."""
    return mode not in EXPECTED_MODES[phase] and mode not in pilot_modes_ok
