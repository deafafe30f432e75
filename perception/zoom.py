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

import math
from dataclasses import dataclass, replace

import numpy as np

from perception.tracker import iou
from perception.types import BoundingBox

EDGE_PX = 2.0  # a crop box this close to a crop edge inside the frame may be cut by the crop: the frame's box counts
# A frame box this much larger (sqrt of area) than the crop's box it holds is the object merged with background
# beside it. In process (rendered frames, 20 runs, tracked rings of 80-200 px, n=377) the frame's box is at most
# 1.22x the crop's (p99 1.12-1.20); on the PX4 SIH merge ramps (re-rendered) it was 1.31-1.6x.
MERGED_RATIO = 1.25


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


def referee(full: list[BoundingBox], zoomed: list[BoundingBox], crop: Crop, dup_iou: float,
            expected: BoundingBox, merged_ratio: float = MERGED_RATIO) -> list[BoundingBox]:
    """One list of boxes, best first, for a tracked target too big for ``merge``'s reason (recall): the frame's
    boxes stand, except one that holds a crop box of the same object, is more than ``merged_ratio`` its size (sqrt
    of area), and is farther than it from the size the track expects (``expected``, its prediction): at half size
    the detector boxed the object together with background beside it, and the crop's box replaces it. Elsewhere the
    frame's box is kept: at full resolution a 200-240 px ring fills most of the crop and its box is less accurate
    than the frame's (in process: IoU with the truth p50 0.86 vs 0.94), and a crop box farther from the expected
    size than the frame's is a part of the object (in process a 211 px ring's crop box was 0.84x it, 26 px off, and
    the track followed it off the ring). Crop boxes the crop holds of objects the frame missed are added."""
    inside = [z for z in map(crop.to_frame, zoomed) if crop.holds(z)]
    out: list[BoundingBox] = []
    seen: set[int] = set()
    s_exp = _size(expected)
    for b in full:
        dups = [i for i, z in enumerate(inside) if same_object(b, z, dup_iou)]
        seen.update(dups)
        merged = [inside[i] for i in dups if _size(b) > merged_ratio * _size(inside[i]) and _within(inside[i], b)
                  and abs(math.log(_size(inside[i]) / s_exp)) < abs(math.log(_size(b) / s_exp))]
        out.append(max(merged, key=lambda z: z.confidence) if merged else b)
    out += [z for i, z in enumerate(inside) if i not in seen]
    return sorted(out, key=lambda b: -b.confidence)


def _size(b: BoundingBox) -> float:
    return math.sqrt(max(b.w * b.h, 1.0))


def _within(inner: BoundingBox, outer: BoundingBox, share: float = 0.9) -> bool:
    """Is at least ``share`` of ``inner``'s area inside ``outer`` (the frame's box took the crop's object in)?"""
    ax0, ay0, ax1, ay1 = inner.xyxy
    bx0, by0, bx1, by1 = outer.xyxy
    inter = max(0.0, min(ax1, bx1) - max(ax0, bx0)) * max(0.0, min(ay1, by1) - max(ay0, by0))
    return inter >= share * inner.w * inner.h
