"""Box error models for the geometric camera: ``white`` (i.i.d. Gaussian, the historic default) and ``detector``.

The ``detector`` model reproduces what tools/measure_box_error.py measures when rendered frames go through the
shipped detector (docs/noise.md): a centre error whose std grows with the box (interpolated in log width between
the measured bins), coloured in time (an AR(2) process per coordinate, fitted by Yule-Walker to the measured
lag-1 and lag-2 autocorrelations), a box-size bias and noise, occasional wrong-target boxes (a box elsewhere in
the image, probability by width) and misses. Pure numpy; the state (the AR history) lives in ``DetectorNoise``.
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
    miss: float  # probability that a frame with the gate in view gives no box
    size_bias: float  # relative, the box is this much larger than the ring's extent
    size_std: float  # relative std of the size error (white)

    def __post_init__(self) -> None:
        n = len(self.widths)
        if n == 0 or any(len(x) != n for x in (self.std_x, self.std_y, self.wrong, self.glitch)):
            raise ValueError("DetectorNoiseParams: widths, std_x, std_y, wrong, glitch need the same non-zero length")
        if list(self.widths) != sorted(self.widths) or self.widths[0] <= 0.0:
            raise ValueError(f"DetectorNoiseParams: widths must be positive and increasing, got {self.widths}")
        a1, a2 = ar2_coefficients(self.rho1, self.rho2)
        if not (abs(a2) < 1.0 and a1 + a2 < 1.0 and a2 - a1 < 1.0):
            raise ValueError(f"DetectorNoiseParams: autocorrelations {self.rho1}, {self.rho2} give no stationary AR(2)")

    def at(self, width: float) -> tuple[float, float, float, float]:
        """(std_x, std_y, wrong-target probability, glitch probability) for a box of this width."""
        lw = math.log(max(width, 1e-3))
        xs = np.log(self.widths)
        return (float(np.interp(lw, xs, self.std_x)), float(np.interp(lw, xs, self.std_y)),
                float(np.interp(lw, xs, self.wrong)), float(np.interp(lw, xs, self.glitch)))


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
        std_x=(1.2, 4.2, 5.3, 7.2, 6.0, 6.0), std_y=(1.8, 3.9, 2.5, 3.4, 3.6, 3.6),
        wrong=(0.0, 0.015, 0.015, 0.02, 0.03, 0.55),
        glitch=(0.0, 0.02, 0.02, 0.15, 0.2, 0.2),
        rho1=0.85, rho2=0.55, miss=0.04, size_bias=0.05, size_std=0.04,
    ),
    "sih": DetectorNoiseParams(
        widths=(38.0, 60.0, 113.0, 253.0, 400.0, 450.0),
        std_x=(1.4, 3.2, 4.2, 6.2, 6.5, 6.5), std_y=(1.3, 2.3, 2.9, 4.2, 3.6, 3.6),
        wrong=(0.1, 0.03, 0.05, 0.07, 0.1, 0.55),
        glitch=(0.0, 0.0, 0.02, 0.27, 0.3, 0.25),
        rho1=0.88, rho2=0.68, miss=0.02, size_bias=0.05, size_std=0.04,
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
            return None
        e = self._advance()  # the error process runs on every frame with the gate in view
        if self.rng.random() < self.p.miss:
            return None
        sx, sy, wrong, glitch = self.p.at(box.w)
        u = self.rng.random()
        if u < wrong:
            return self._wrong_target(box, 50.0, max(60.0, 0.5 * max(self.width, self.height)), 0.3)
        if u < wrong + glitch:
            return self._wrong_target(box, 15.0, 50.0, 0.7)
        k = 1.0 + self.p.size_bias
        n = self.rng.normal(0.0, self.p.size_std, 2)
        cx = min(max(box.cx + sx * float(e[0]), 0.0), self.width)
        cy = min(max(box.cy + sy * float(e[1]), 0.0), self.height)
        return BoundingBox(cx, cy, max(box.w * (k + n[0]), 1.0), max(box.h * (k + n[1]), 1.0), 1.0, box.t)

    def _wrong_target(self, box: BoundingBox, r_min: float, r_max: float, s_min: float) -> BoundingBox:
        """A box off the ring by r_min..r_max px in a random direction, s_min..1 of its size."""
        ang = self.rng.uniform(0.0, 2.0 * math.pi)
        r = self.rng.uniform(r_min, r_max)
        cx = min(max(box.cx + r * math.cos(ang), 0.0), self.width)
        cy = min(max(box.cy + r * math.sin(ang), 0.0), self.height)
        s = self.rng.uniform(s_min, 1.0)
        return BoundingBox(cx, cy, max(box.w * s, 2.0), max(box.h * s, 2.0), 1.0, box.t)
