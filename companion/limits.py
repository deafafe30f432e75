"""Pure safety logic of the flight app (no I/O, no asyncio): unit-testable with plain numbers.

* ``CloseDetector``: is the gate about to be passed? Time-to-contact from the box's expansion
  (tau = s / (ds/dt) for the box size s, which grows like 1/range) or the box size itself.
* ``SafetyLimits``: target lost for T seconds, barometric altitude floor, maximum engagement time.
* ``mode_is_pilot``: a flight mode the app did not ask for means the pilot has taken over.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from companion.config_app import AppConfig, SafetyConfig
from companion.reasons import Reason
from perception.fastinit import fast_init
from perception.types import BoundingBox


@fast_init  # one a frame: the slot-descriptor __init__ (perception/fastinit.py)
@dataclass(frozen=True, slots=True)
class CloseEstimate:
    size_frac: float  # larger box side / image width
    ttc: float  # s; inf when the box is not growing
    close: bool
    why: str


class CloseDetector:
    """Box history of one engagement -> "the gate is about to be passed"."""

    # A box more than this many times the previous one (within JUMP_WINDOW_S) is another object, not the gate
    # come nearer: an approach at time-to-contact tau grows the box by tau / (tau - dt), 1.15x per frame at
    # 0.25 s. Seen in the app on a world-fixed background: a 43 px gate, two missed frames, then a 448 px box of
    # clutter for one frame made the gate "close" and its disappearance a claimed pass, 3 s before the gate.
    MAX_STEP = 2.0
    JUMP_WINDOW_S = 0.25

    def __init__(self, app: AppConfig, image_width: int, window_s: float = 0.25, frame_rate: float = 30.0,
                 persist: int = 2) -> None:
        self.trigger = app.close_trigger
        self.ttc_threshold = app.ttc_threshold
        self.size_threshold = app.size_threshold
        self.width = float(image_width)
        # The slope needs a few frames: a slow camera gets a longer window (6 frame periods at least).
        self.window_s = max(window_s, 6.0 / frame_rate)
        # Samples the window must hold: 60 % of what the camera rate gives, at least 4. A fixed 7 (a 30 Hz
        # camera's whole window) made the time-to-contact infinite whenever frames came a little late or a few
        # were coasted (a loaded machine delivering 25 Hz; any 20 Hz camera): a gate filling 80 % of the image
        # was never "close", the pass never began, and the vehicle coasted tilted after it into the floor.
        self.min_samples = max(4, math.ceil(0.6 * self.window_s * frame_rate))
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
        ts: list[float] = []
        ss: list[float] = []
        for t, s in reversed(self._hist):  # newest first; stop at the window's start
            if t_last - t > self.window_s:
                break
            ts.append(t)
            ss.append(s)
        ts.reverse()
        ss.reverse()
        # A full window only: a slope over a few frames right after acquisition is mostly pixel noise.
        n = len(ts)
        if n < self.min_samples or ts[-1] - ts[0] < 0.8 * self.window_s:
            return math.inf
        # The sums over lists, not generators (every frame): sum adds in the same order either way.
        t_mean = sum(ts) / n
        s_mean = sum(ss) / n
        dts = [t - t_mean for t in ts]
        denom = sum([d ** 2 for d in dts])
        if denom <= 0.0:
            return math.inf
        slope = sum([d * (s - s_mean) for d, s in zip(dts, ss, strict=True)]) / denom
        if slope <= 0.0:
            return math.inf
        # The fit describes the window's centre; the contact time is the same instant, seen from now.
        return max(0.0, s_mean / slope - (t_last - t_mean))

    def peak(self, t: float, window_s: float, until: float | None = None) -> float:
        """The largest box of the last ``window_s`` seconds before ``t``, as a fraction of the width (0: none);
        ``until``: only boxes seen at or before it."""
        best = 0.0
        for ts, s in reversed(self._hist):
            if t - ts > window_s:
                break
            if until is None or ts <= until:
                best = max(best, s)
        return best / self.width

    def update(self, t: float, box: BoundingBox | None, valid: bool) -> CloseEstimate:
        if valid and box is not None:
            s = max(box.w, box.h)
            prev = self._hist[-1] if self._hist else None
            if prev is None or t - prev[0] > self.JUMP_WINDOW_S or s <= self.MAX_STEP * prev[1]:
                self._hist.append((t, s))
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


_sum = np.add.reduce


class SafetyLimits:
    """Abort checks that run on every control step of an engagement."""

    SINK_WINDOW_S = 0.5  # barometric sink rate: least-squares slope over this window (baro noise averages out)

    def __init__(self, safety: SafetyConfig) -> None:
        self.cfg = safety
        # The barometer window as two deques of floats (times, altitudes): the fit reads each as an array with
        # np.fromiter, a third of the cost of a list comprehension and np.array (every frame).
        self._baro_t: deque[float] = deque(maxlen=256)
        self._baro_h: deque[float] = deque(maxlen=256)
        self.climb_rate: float | None = None  # m/s, up positive: the last fitted barometric slope (None: too few)

    def floor(self, now: float, baro_rel_alt: float | None,
              arrest: Callable[[float], float] | None = None) -> Abort | None:
        """The altitude floor, with a look-ahead: a vehicle diving at 10 m/s (seen on PX4 when the app engaged a
        false detection) passes a 2 m floor in 0.2 s, faster than Hold can brake it, so the floor also trips
        when the altitude extrapolated ``floor_lookahead`` seconds at the current sink rate would be below it.

        ``arrest`` (climb rate m/s -> height lost, m): a pull-up is planned (companion/pullup.py arrest_loss), so
        the look-ahead is the altitude after that pull-up's sink arrest instead: a dive at a target on the ground
        is safe as long as the pull-up can still stop it above the floor."""
        c = self.cfg
        if baro_rel_alt is None or not math.isfinite(baro_rel_alt) or not math.isfinite(now):
            return None
        if baro_rel_alt < c.altitude_floor:
            return Abort(Reason.ALTITUDE_FLOOR,
                         f"barometric altitude {baro_rel_alt:.1f} m below the floor {c.altitude_floor:.1f} m")
        bt, bh = self._baro_t, self._baro_h
        if bt and now <= bt[-1]:
            return None  # the same sample again (or time running backwards): no new slope
        bt.append(now)
        bh.append(baro_rel_alt)
        while bt and now - bt[0] > self.SINK_WINDOW_S:
            bt.popleft()
            bh.popleft()
        n = len(bt)
        if c.floor_lookahead <= 0.0 or n < 4 or now - bt[0] < 0.6 * self.SINK_WINDOW_S:
            return None
        t = np.fromiter(bt, float, n)
        h = np.fromiter(bh, float, n)
        # Every frame: ndarray.mean's Python wrapper costs more than its sum; add.reduce / n is the same float
        # (the mean is np.add.reduce(a) / a.size), and h's mean is computed once instead of twice. The division
        # on Python floats: the same IEEE division as numpy's scalar one, without its scalar objects.
        t_mean = float(_sum(t)) / n
        h_mean = float(_sum(h)) / n
        t = t - t_mean
        rate = float(t.dot(h - h_mean)) / float(t.dot(t))
        self.climb_rate = rate
        now_fit = h_mean + rate * (now - t_mean)  # the fitted altitude now: less noisy than one sample
        if arrest is not None:
            ahead = now_fit - arrest(rate)
            if ahead < c.altitude_floor:
                return Abort(Reason.ALTITUDE_FLOOR,
                             f"sinking at {-rate:.1f} m/s at {baro_rel_alt:.1f} m: a pull-up now would bottom out "
                             f"at {ahead:.1f} m, below the floor {c.altitude_floor:.1f} m")
            return None
        ahead = now_fit + min(0.0, rate) * c.floor_lookahead
        if ahead < c.altitude_floor:
            return Abort(Reason.ALTITUDE_FLOOR,
                         f"sinking at {-rate:.1f} m/s at {baro_rel_alt:.1f} m: below the floor "
                         f"{c.altitude_floor:.1f} m within {c.floor_lookahead:.1f} s")
        return None

    def check(
        self,
        now: float,
        engage_start: float,
        last_valid_box: float,
        baro_rel_alt: float | None,
        arrest: Callable[[float], float] | None = None,
    ) -> Abort | None:
        c = self.cfg
        floor = self.floor(now, baro_rel_alt, arrest)
        if floor is not None:
            return floor
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
