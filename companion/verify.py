"""Is this box the configured target? Pure checks of one box (and its predecessor) before and during an engagement.

Why: flying at something that is not the gate was the most common failure (issue 18): a lit cabinet engaged on
real video, a 135 px clutter box acquired on PX4 where the gate at 25 m is ~39 px. companion/targetlock.py
already rejects a box during ENGAGE whose size or direction no approach explains; these rules add what the
configured target itself allows, and are used at ACQUIRE (a candidate failing one breaks the stable-track
streak) and during ENGAGE (a failing box is no box: the controller coasts, then TARGET_LOST):

* ``shape``: a ring of radius r seen at an angle theta off its axis is an ellipse 2r x 2r cos(theta): a box
  not cut by the image border has min(w, h) / max(w, h) >= cos(max_view_angle).
* ``range``: the ring's larger box side is s = 2 f r / d at range d (f the focal length in px, r
  ``guidance.gate_radius``): a box smaller than ``size_tolerance`` x 2 f r / max_range is farther than the
  gate can be; at ACQUIRE a box larger than 2 f r / min_acquire_range / size_tolerance is nearer than an
  engagement starts. Needs a gate radius (0: off).
* ``cut`` (ACQUIRE only): a candidate cut by the image border is not one: its shape and size, what the rules
  above check, are not the ring's. On PX4 SITL every engagement begun on clutter (3 of 3 in the 530 logs read on
  2026-12-02) began on a flat box on the image's bottom border; the next two (2026-12-02 and -06) on boxes 2-7 px
  from a border, which a detector's wandering edges cut in some frames and not in others: at ACQUIRE an edge
  within ``acquire_margin`` of the width (2 %, 13 px at 640) counts as cut. During ENGAGE a cut box stays a box
  (the gate fills the view as the vehicle nears it; companion/engagement.py completes it).
* ``appearance``: the box's appearance descriptor (perception: a normalised hue-saturation histogram of the
  box, ``BoundingBox.appearance``) against the one the track / engagement began with: a Bhattacharyya
  coefficient below ``min_similarity`` is another object. Off when either has no descriptor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from perception.types import BoundingBox


@dataclass(frozen=True, slots=True)
class VerifyParams:
    focal_px: float  # camera focal length, px
    gate_radius: float  # m; 0 = unknown: no range rule
    width: int  # image size, px
    height: int
    max_range: float = 0.0  # m; 0 = no far limit
    min_acquire_range: float = 0.0  # m; 0 = no near limit at ACQUIRE
    max_view_angle: float = math.radians(75.0)  # rad; 0 = no shape rule
    size_tolerance: float = 0.7  # a detector's box may be this much tighter (or 1/this looser) than the ring
    min_similarity: float = 0.0  # Bhattacharyya coefficient 0..1; 0 = no appearance rule
    edge_px: float = 3.0  # a box edge this near the border is cut (its shape and size are not the ring's)
    acquire_cut: bool = False  # accept a candidate cut by the image border at ACQUIRE
    # At ACQUIRE an edge this near the border (a fraction of the width; edge_px at least) counts as cut: a detector's
    # edges wander by several px between frames, so a box that near is cut in some and its whole shape never seen.
    # PX4 SITL: the two engagements begun on clutter since the 3 px rule (x500 run065 2026-12-02, SIH run028
    # 2026-12-06) began on boxes 6-7 and 2-5 px from a border; the 40 gate engagements of the same SIH table began
    # 71-103 px inside.
    acquire_margin: float = 0.02

    @classmethod
    def from_config(cls, cfg: object) -> VerifyParams:
        from companion.config import camera_model  # built once per camera section: a simulated run builds these

        v = cfg.app.verify  # type: ignore[attr-defined]
        cam = camera_model(cfg.camera)  # type: ignore[attr-defined]
        return cls(float(cam.K[0, 0]), float(cfg.guidance.gate_radius), cam.width, cam.height,  # type: ignore
                   float(v.max_range), float(v.min_acquire_range), math.radians(float(v.max_view_angle)),
                   float(v.size_tolerance), float(v.min_similarity), acquire_cut=bool(v.acquire_cut),
                   acquire_margin=float(v.acquire_margin))


def similarity(a: tuple[float, ...] | np.ndarray, b: tuple[float, ...] | np.ndarray) -> float:
    """Bhattacharyya coefficient of two normalised histograms: 1 the same, 0 disjoint."""
    pa, pb = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    sa, sb = pa.sum(), pb.sum()
    if pa.shape != pb.shape or sa <= 0 or sb <= 0:
        return 1.0  # nothing to compare: not evidence of another object
    return float(np.sqrt(pa / sa * pb / sb).sum())


class TargetVerifier:
    """``check(box, acquiring)`` per frame; ``begin(box)`` when a track / an engagement starts on a box."""

    def __init__(self, params: VerifyParams) -> None:
        self.p = params
        self._ref_app: np.ndarray | None = None
        self.rejected: dict[str, int] = {}

    def reset(self) -> None:
        self._ref_app = None

    def begin(self, box: BoundingBox) -> None:
        """The appearance reference: the box a track or an engagement begins with."""
        a = getattr(box, "appearance", None)
        self._ref_app = None if a is None else np.asarray(a, dtype=float)

    def _cut(self, xyxy: tuple[float, float, float, float], e: float) -> bool:
        """Is a box (its corners, ``BoundingBox.xyxy``) within ``e`` px of the image border?"""
        x0, y0, x1, y1 = xyxy
        return x0 <= e or y0 <= e or x1 >= self.p.width - e or y1 >= self.p.height - e

    def acquire_edge_px(self) -> float:
        """At ACQUIRE a box edge this near the border counts as cut, px."""
        return max(self.p.edge_px, self.p.acquire_margin * self.p.width)

    def check(self, box: BoundingBox, acquiring: bool) -> str:
        """"" when ``box`` may be the target, else why not (one line)."""
        no = self._box_rules(box, acquiring)
        if no is not None:
            return self._no(*no)
        p = self.p
        a = getattr(box, "appearance", None)
        if p.min_similarity > 0.0 and a is not None and self._ref_app is not None:
            s = similarity(self._ref_app, a)
            if s < p.min_similarity:
                return self._no("appearance", f"appearance similarity {s:.2f} to the track's first box "
                                              f"(< {p.min_similarity:.2f})")
        return ""

    def may_be_candidate(self, box: BoundingBox, acquiring: bool = True) -> bool:
        """Would ``box`` pass the rules of one box (cut, shape, range) at ACQUIRE, or while engaged (``acquiring``
        False: only an edge within ``edge_px`` of the border is cut)? For another object in view
        (companion/rival.py): not counted among the rejections, no appearance reference."""
        return self._box_rules(box, acquiring) is None

    def _box_rules(self, box: BoundingBox, acquiring: bool) -> tuple[str, str] | None:
        """The rules that judge one box alone: (rule, why) of the first it fails, None when it passes."""
        p = self.p
        size, small = max(box.w, box.h), min(box.w, box.h)
        xyxy = box.xyxy  # the corners once for both border tests
        cut = self._cut(xyxy, p.edge_px)
        if acquiring and not p.acquire_cut and self._cut(xyxy, self.acquire_edge_px()):
            return ("cut", f"box {box.w:.0f}x{box.h:.0f} px at ({box.cx:.0f}, {box.cy:.0f}) is cut by the "
                           f"image border (an edge within {self.acquire_edge_px():.0f} px of it): its shape "
                           "and size cannot be checked")
        if not cut and p.max_view_angle > 0.0 and small < math.cos(p.max_view_angle) * size:
            return ("shape", f"box {box.w:.0f}x{box.h:.0f} px: no ring seen within "
                             f"{math.degrees(p.max_view_angle):.0f} deg of its axis is that narrow")
        if p.gate_radius > 0.0:
            full = 2.0 * p.focal_px * p.gate_radius  # px x m: size x range
            if not cut and p.max_range > 0.0 and size < p.size_tolerance * full / p.max_range:
                return ("range", f"box {size:.0f} px: the gate would be {full / size:.0f} m away "
                                 f"(max_range {p.max_range:.0f} m)")
            if acquiring and p.min_acquire_range > 0.0 and size * p.size_tolerance > full / p.min_acquire_range:
                return ("range", f"box {size:.0f} px: the gate would be {full / size:.1f} m away at "
                                 f"acquisition (min_acquire_range {p.min_acquire_range:.0f} m)")
        return None

    def _no(self, rule: str, why: str) -> str:
        self.rejected[rule] = self.rejected.get(rule, 0) + 1
        return f"not the target ({rule}): {why}"
