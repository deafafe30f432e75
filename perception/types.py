"""Data passed from perception to the controller."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from perception.fastinit import fast_init


@fast_init
@dataclass(frozen=True, slots=True)
class BoundingBox:
    """An axis-aligned box in pixels (image x right, y down), centre + size, with its frame time."""

    cx: float
    cy: float
    w: float
    h: float
    confidence: float = 1.0
    t: float = 0.0  # capture time of the frame it came from, s (monotonic clock of the source)
    # What the box shows (perception/appearance.py: a normalised hue-saturation histogram), for the target
    # verification (companion/verify.py); None where no image was seen (geometric boxes).
    appearance: tuple[float, ...] | None = field(default=None, compare=False, repr=False)
    # The most confident other candidate the detector saw in the same frame (a plausible box wholly in view, not this
    # object's; perception/pipeline.py), None when there was none or no detection ran: is another object in view as
    # likely the target (companion/rival.py)?
    rival: BoundingBox | None = field(default=None, compare=False, repr=False)

    def is_valid(self, width: int, height: int) -> bool:
        """Finite, positive size, centre inside the image: anything else is garbage from a detector."""
        isf = math.isfinite  # no generator: this runs several times a frame (engagement, controller, lock)
        if not (isf(self.cx) and isf(self.cy) and isf(self.w) and isf(self.h) and isf(self.confidence)):
            return False
        return self.w > 0 and self.h > 0 and 0.0 <= self.cx <= width and 0.0 <= self.cy <= height

    @property
    def xyxy(self) -> tuple[float, float, float, float]:
        return (self.cx - self.w / 2, self.cy - self.h / 2, self.cx + self.w / 2, self.cy + self.h / 2)

    @classmethod
    def from_xyxy(cls, x0: float, y0: float, x1: float, y1: float, confidence: float = 1.0, t: float = 0.0):
        return cls((x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0, confidence, t)
