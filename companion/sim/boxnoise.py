"""Box error models for the geometric camera: ``white`` (i.i.d. Gaussian, the historic default) and ``detector``.

The ``detector`` model reproduces what tools/measure_box_error.py measures when rendered frames go through the
shipped detector (docs/noise.md): a centre error whose std grows with the box (interpolated in log width between
the measured bins), coloured in time (an AR(2) process per coordinate, fitted by Yule-Walker to the measured
lag-1 and lag-2 autocorrelations), a lag behind the ring's image motion (the rendered pipeline's error correlates
with the exact box's image velocity: -0.58 / -0.45 in x / y), a box-size bias and noise, occasional wrong-target
boxes (a box elsewhere in the image, probability by width), 15-50 px glitches and misses.
Pure numpy; the state (the AR history, the last exact box) lives in ``DetectorNoise``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from perception.types import BoundingBox

NOISE_MODELS = ("white", "detector")


@dataclass(frozen=True)
class DetectorNoiseParams:
    """Fitted parameters; tables are by exact box width (px), interpolated in log width and held at the ends."""

    widths: tuple[float, ...]  # px, representative width of each measured bin
    std_x: tuple[float, ...]  # px, stationary std of the horizontal centre error
    std_y: tuple[float, ...]  # px, vertical
    wrong: tuple[float, ...]  # probability that a frame's box is a wrong target (> 50 px off)
    glitch: tuple[float, ...]  # probability of a gross centre error of 15-50 px (part of the ring, a merged box)
    rho1: float  # lag-1 autocorrelation of the centre error (frames)
    rho2: float  # lag-2
    miss: tuple[float, ...]  # by width: share of the frames with the gate in view that give no box
    size_bias: tuple[float, ...]  # relative, by width: the box is this much larger than the ring's extent
    size_std: float  # relative std of the size error (white)
    miss_stay: float = 0.0  # misses and wrong targets come in spells: the chance that one goes on next frame
    wrong_stay: float = 0.0
    lag_x: float = 0.0  # s: the box trails the ring's image motion by this (error = -lag * image velocity)
    lag_y: float = 0.0

    def __post_init__(self) -> None:
        n = len(self.widths)
        if n == 0 or any(len(x) != n for x in (self.std_x, self.std_y, self.wrong, self.glitch, self.size_bias,
                                                     self.miss)):
            raise ValueError("DetectorNoiseParams: the tables by width need the same non-zero length")
        if list(self.widths) != sorted(self.widths) or self.widths[0] <= 0.0:
            raise ValueError(f"DetectorNoiseParams: widths must be positive and increasing, got {self.widths}")
        if not (0.0 <= self.miss_stay < 1.0 and 0.0 <= self.wrong_stay < 1.0):
            raise ValueError(f"DetectorNoiseParams: miss_stay/wrong_stay must be in [0, 1): {self.miss_stay}, "
                             f"{self.wrong_stay}")
        a1, a2 = ar2_coefficients(self.rho1, self.rho2)
        if not (abs(a2) < 1.0 and a1 + a2 < 1.0 and a2 - a1 < 1.0):
            raise ValueError(f"DetectorNoiseParams: autocorrelations {self.rho1}, {self.rho2} give no stationary AR(2)")

    def at(self, width: float) -> tuple[float, float, float, float, float, float]:
        """(std_x, std_y, wrong-target share, glitch probability, size bias, miss share) for a box of this width."""
        lw = math.log(max(width, 1e-3))
        xs = np.log(self.widths)
        return (float(np.interp(lw, xs, self.std_x)), float(np.interp(lw, xs, self.std_y)),
                float(np.interp(lw, xs, self.wrong)), float(np.interp(lw, xs, self.glitch)),
                float(np.interp(lw, xs, self.size_bias)), float(np.interp(lw, xs, self.miss)))


def ar2_coefficients(rho1: float, rho2: float) -> tuple[float, float]:
    """Yule-Walker: the AR(2) ``e_k = a1 e_{k-1} + a2 e_{k-2} + w_k`` with these lag-1 and lag-2 autocorrelations."""
    den = 1.0 - rho1 * rho1
    if den <= 1e-9:
        raise ValueError(f"lag-1 autocorrelation {rho1} must be inside (-1, 1)")
    return rho1 * (1.0 - rho2) / den, (rho2 - rho1 * rho1) / den


def ar2_innovation_scale(rho1: float, rho2: float) -> float:
    """std of the AR(2)'s driving noise for a unit stationary std: ``1 - a1 rho1 - a2 rho2`` is its variance."""
    a1, a2 = ar2_coefficients(rho1, rho2)
    return math.sqrt(max(1.0 - a1 * rho1 - a2 * rho2, 1e-12))


# Fitted to tools/measure_box_error.py (rendered frames through the shipped detector), docs/noise.md: the model's
# parameters are set so that the tool, run on the model (--camera geometric), reads what it reads on rendered
# frames (its short per-run windows bias the autocorrelation low, so rho1/rho2 here are above the measured ones).
# Bins by the exact box width: < 40, 40-80, 80-160, 160-400, > 400 px; wrong targets step up at 400 px.
PROFILES: dict[str, DetectorNoiseParams] = {
    "x500": DetectorNoiseParams(
        widths=(38.0, 60.0, 113.0, 253.0, 400.0, 450.0),
        std_x=(1.0, 3.4, 4.3, 5.9, 4.9, 4.9), std_y=(1.6, 3.5, 2.2, 3.1, 3.2, 3.2),
        wrong=(0.1, 0.04, 0.05, 0.02, 0.03, 0.5),
        glitch=(0.0, 0.02, 0.01, 0.08, 0.15, 0.2),
        miss=(0.17, 0.08, 0.02, 0.0, 0.0, 0.0), miss_stay=0.63, wrong_stay=0.46,
        rho1=0.85, rho2=0.55, size_bias=(0.08, 0.04, 0.03, 0.0, -0.12, -0.2),
        size_std=0.04, lag_x=0.0094, lag_y=0.0055,
    ),
    "sih": DetectorNoiseParams(
        widths=(38.0, 60.0, 113.0, 253.0, 400.0, 450.0),
        std_x=(1.4, 3.2, 4.2, 6.2, 6.5, 6.5), std_y=(1.3, 2.3, 2.9, 4.2, 3.6, 3.6),
        wrong=(0.1, 0.03, 0.05, 0.07, 0.1, 0.55),
        glitch=(0.0, 0.0, 0.02, 0.27, 0.3, 0.25),
        miss=(0.02, 0.02, 0.02, 0.02, 0.02, 0.02), miss_stay=0.63, wrong_stay=0.46,
        rho1=0.88, rho2=0.68, size_bias=(0.1, 0.06, 0.04, 0.07, -0.1, -0.2),
        size_std=0.04,
    ),
}


class DetectorNoise:
    """Applies the detector model to exact boxes, frame by frame (one instance per camera, i.e. per run)."""

    def __init__(self, params: DetectorNoiseParams, rng: np.random.Generator, width: int, height: int) -> None:
        self.p = params
        self.rng = rng
        self.width, self.height = float(width), float(height)
        self._a1, self._a2 = ar2_coefficients(params.rho1, params.rho2)
        self._scale = ar2_innovation_scale(params.rho1, params.rho2)
        self.reset()

    def reset(self) -> None:
        # Unit-variance AR(2) states per coordinate (the previous two), scaled by the width's std when applied.
        self._e = np.zeros((2, 2))
        self._started = False
        self._prev: tuple[float, float, float] | None = None  # last exact box centre and its time
        self._state = "ok"  # ok | miss | wrong: the last frame's outcome (spells)
        self._wrong_offset = (0.0, 0.0, 1.0)  # the wrong target's offset from the ring (px) and size ratio

    def _advance(self) -> np.ndarray:
        if not self._started:
            # Start in the stationary distribution (the two states correlated by rho1), not at zero.
            e0 = self.rng.normal(0.0, 1.0, 2)
            e1 = self.p.rho1 * e0 + math.sqrt(1.0 - self.p.rho1 ** 2) * self.rng.normal(0.0, 1.0, 2)
            self._e = np.vstack((e1, e0))
            self._started = True
        e = self._a1 * self._e[0] + self._a2 * self._e[1] + self._scale * self.rng.normal(0.0, 1.0, 2)
        self._e = np.vstack((e, self._e[0]))
        return e

    def apply(self, box: BoundingBox | None) -> BoundingBox | None:
        """The detector's box for this frame's exact box (None: the gate not in view, or missed)."""
        if box is None:
            self._prev = None
            self._state = "ok"
            return None
        e = self._advance()  # the error process runs on every frame with the gate in view
        vx = vy = 0.0
        if self._prev is not None and 0.0 < box.t - self._prev[2] <= 0.1:
            dt = box.t - self._prev[2]
            vx, vy = (box.cx - self._prev[0]) / dt, (box.cy - self._prev[1]) / dt
        self._prev = (box.cx, box.cy, box.t)
        sx, sy, wrong, glitch, bias, miss = self.p.at(box.w)
        state = self._next_state(miss, wrong)
        if state == "miss":
            return None
        if state == "wrong":
            return self._offset_box(box, *self._wrong_offset)
        if self.rng.random() < glitch:
            return self._offset_box(box, *self._draw_offset(15.0, 50.0, 0.7))
        k = 1.0 + bias
        n = self.rng.normal(0.0, self.p.size_std, 2)
        cx = min(max(box.cx - self.p.lag_x * vx + sx * float(e[0]), 0.0), self.width)
        cy = min(max(box.cy - self.p.lag_y * vy + sy * float(e[1]), 0.0), self.height)
        return BoundingBox(cx, cy, max(box.w * (k + n[0]), 1.0), max(box.h * (k + n[1]), 1.0), 1.0, box.t)

    def _next_state(self, miss: float, wrong: float) -> str:
        """This frame: a miss, a wrong target or the ring. A spell goes on with its ``*_stay`` chance; new spells
        start at the rate that keeps the long-run shares at ``miss`` and ``wrong``: in the stationary chain a new
        draw happens with probability ``r = 1 - miss stay_m - wrong stay_w`` and ``share (1 - stay) = r start``."""
        u = self.rng.random()
        if self._state == "miss" and u < self.p.miss_stay:
            return "miss"
        if self._state == "wrong" and u < self.p.wrong_stay:
            return "wrong"
        u = self.rng.random()
        r = max(1.0 - miss * self.p.miss_stay - wrong * self.p.wrong_stay, 1e-9)
        p_miss = miss * (1.0 - self.p.miss_stay) / r
        p_wrong = wrong * (1.0 - self.p.wrong_stay) / r
        if u < p_miss:
            self._state = "miss"
        elif u < p_miss + p_wrong:
            self._state = "wrong"
            self._wrong_offset = self._draw_offset(50.0, max(60.0, 0.5 * max(self.width, self.height)), 0.3)
        else:
            self._state = "ok"
        return self._state

    def _draw_offset(self, r_min: float, r_max: float, s_min: float) -> tuple[float, float, float]:
        """An offset of r_min..r_max px in a random direction and a size ratio in s_min..1."""
        ang = self.rng.uniform(0.0, 2.0 * math.pi)
        r = self.rng.uniform(r_min, r_max)
        return r * math.cos(ang), r * math.sin(ang), self.rng.uniform(s_min, 1.0)

    def _offset_box(self, box: BoundingBox, dx: float, dy: float, s: float) -> BoundingBox:
        cx = min(max(box.cx + dx, 0.0), self.width)
        cy = min(max(box.cy + dy, 0.0), self.height)
        return BoundingBox(cx, cy, max(box.w * s, 2.0), max(box.h * s, 2.0), 1.0, box.t)
