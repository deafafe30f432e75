"""What a box shows, as a small descriptor that stays the same while the box stays on the same object.

A normalised hue-saturation histogram (``HUE_BINS`` x ``SAT_BINS``) of the box's pixels, on a copy shrunk to at
most ``MAX_SIDE`` px (cost independent of the box size: ~0.1 ms). Hue and saturation, not brightness: the gate's
colour survives exposure changes; a cabinet, a wall edge or the background behind it has other colours.
companion/verify.py compares it (Bhattacharyya coefficient) with the box a track began with.
"""

from __future__ import annotations

import cv2
import numpy as np

from perception.types import BoundingBox

HUE_BINS = 8
SAT_BINS = 4
MAX_SIDE = 32


def descriptor(frame: np.ndarray, box: BoundingBox) -> tuple[float, ...] | None:
    """The box's hue-saturation histogram (sums to 1), None for a box with no pixels in the frame."""
    h, w = frame.shape[:2]
    x0, y0, x1, y1 = box.xyxy
    x0, y0 = max(0, int(x0)), max(0, int(y0))
    x1, y1 = min(w, int(np.ceil(x1))), min(h, int(np.ceil(y1)))
    if x1 - x0 < 2 or y1 - y0 < 2:
        return None
    crop = frame[y0:y1, x0:x1]
    s = MAX_SIDE / max(crop.shape[0], crop.shape[1])
    if s < 1.0:
        crop = cv2.resize(crop, (max(1, round(crop.shape[1] * s)), max(1, round(crop.shape[0] * s))),
                          interpolation=cv2.INTER_AREA)
    if crop.ndim == 2:
        crop = cv2.cvtColor(crop, cv2.COLOR_GRAY2BGR)
    hsv = cv2.cvtColor(crop, cv2.COLOR_BGR2HSV)
    hist = cv2.calcHist([hsv], [0, 1], None, [HUE_BINS, SAT_BINS], [0, 180, 0, 256]).ravel()
    tot = float(hist.sum())
    return tuple(float(v) / tot for v in hist) if tot > 0 else None
