"""Zoomed detection: a small target looked at again at the camera's own resolution.

The detector sees the whole frame letterboxed to its input (320x320 for the shipped models: a 640x480 frame at
half size), so a gate 25 m away (39 px) reaches it as 20 px, and its recall falls with the size: on rendered frames
(60 per range, random heading and pitch) 50/60 at 39 px, 43/60 at 32 px, 30/60 at 28 px. Where the pipeline knows
where the target is (a track's prediction, an acquisition candidate, a lost track's last box) and it is small, the
detector also runs on a crop of its own input size around that place, at full resolution: 60/60 at 28-39 px on the
same frames (docs/perception.md, "Zoomed detection"). The crop's boxes replace the frame's boxes of the same
objects; the frame's others stay.

Pure geometry: which crop (``zoom_crop``) and how the two lists of boxes become one (``merge``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from perception.tracker import iou
from perception.types import BoundingBox

EDGE_PX = 2.0  # a crop box this close to a crop edge inside the frame may be cut by the crop: the frame's box counts


@dataclass(frozen=True, slots=True)
class Crop:
    """A window of the frame, in frame pixels (integers), and which of its edges are inside the frame."""

    x0: int
    y0: int
    w: int
    h: int
    frame_w: int
    frame_h: int

    def of(self, frame: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(frame[self.y0:self.y0 + self.h, self.x0:self.x0 + self.w])

    def to_frame(self, b: BoundingBox) -> BoundingBox:
        return replace(b, cx=b.cx + self.x0, cy=b.cy + self.y0)

    def holds(self, b: BoundingBox) -> bool:
        """Is ``b`` (frame pixels) wholly inside the crop, clear of every crop edge that is not the frame's own
        (a box touching such an edge may be an object the crop cuts)?"""
        x0, y0, x1, y1 = b.xyxy
        left = self.x0 + (EDGE_PX if self.x0 > 0 else -EDGE_PX)
        top = self.y0 + (EDGE_PX if self.y0 > 0 else -EDGE_PX)
        right = self.x0 + self.w - (EDGE_PX if self.x0 + self.w < self.frame_w else -EDGE_PX)
        bottom = self.y0 + self.h - (EDGE_PX if self.y0 + self.h < self.frame_h else -EDGE_PX)
        return x0 >= left and y0 >= top and x1 <= right and y1 <= bottom


def zoom_crop(focus: BoundingBox, frame_w: int, frame_h: int, input_hw: tuple[int, int],
              below_px: float) -> Crop | None:
    """The detector-input-sized crop centred on ``focus`` (clamped to the frame), or None: zoom off
    (``below_px`` <= 0), ``focus`` not smaller than ``below_px`` on its larger side, or a frame the detector
    already sees at full resolution or more."""
    in_h, in_w = input_hw
    if below_px <= 0.0 or max(focus.w, focus.h) >= below_px:
        return None
    if min(in_w / frame_w, in_h / frame_h) >= 1.0:
        return None
    w, h = min(in_w, frame_w), min(in_h, frame_h)
    x0 = round(min(max(focus.cx - w / 2, 0.0), frame_w - w))
    y0 = round(min(max(focus.cy - h / 2, 0.0), frame_h - h))
    return Crop(x0, y0, w, h, frame_w, frame_h)


def scan_crop(k: int, frame_w: int, frame_h: int, input_hw: tuple[int, int]) -> Crop | None:
    """The ``k``-th (modulo their number) of the detector-input-sized crops that tile the frame with half a crop of
    overlap (640x480 at 320x320: 3 x 2), row by row; None for a frame the detector already sees at full resolution.
    While nothing is being confirmed, the search looks at one a frame: a gate too small to be found in the whole
    frame is found there, then zoomed on as a candidate."""
    in_h, in_w = input_hw
    if min(in_w / frame_w, in_h / frame_h) >= 1.0:
        return None
    w, h = min(in_w, frame_w), min(in_h, frame_h)
    xs = _starts(frame_w, w)
    ys = _starts(frame_h, h)
    i = k % (len(xs) * len(ys))
    return Crop(xs[i % len(xs)], ys[i // len(xs)], w, h, frame_w, frame_h)


def _starts(size: int, crop: int) -> list[int]:
    """Crop origins along one side: 0, then every half crop, the last one flush with the far edge."""
    if crop >= size:
        return [0]
    n = -(-2 * (size - crop) // crop) + 1  # ceil((size - crop) / (crop / 2)) + 1
    return [round(i * (size - crop) / (n - 1)) for i in range(n)]


def same_object(a: BoundingBox, b: BoundingBox, dup_iou: float) -> bool:
    """Two boxes of one object: IoU at least ``dup_iou``, or each one's centre inside the other (the half-size
    frame's box of a small gate is up to ~1.5x the full-resolution one: IoU ~0.45)."""
    if iou(a, b) >= dup_iou:
        return True
    return abs(a.cx - b.cx) <= 0.5 * min(a.w, b.w) and abs(a.cy - b.cy) <= 0.5 * min(a.h, b.h)


def merge(full: list[BoundingBox], zoomed: list[BoundingBox], crop: Crop, dup_iou: float) -> list[BoundingBox]:
    """One list of boxes, best first: the crop's boxes (``zoomed``, crop pixels) that it holds wholly, and the
    frame's boxes that none of them shows again (``same_object``). A frame's box the crop missed stays: the
    crop's recall is higher, not perfect."""
    inside = [z for z in map(crop.to_frame, zoomed) if crop.holds(z)]
    rest = [b for b in full if not any(same_object(b, z, dup_iou) for z in inside)]
    return sorted(inside + rest, key=lambda b: -b.confidence)
