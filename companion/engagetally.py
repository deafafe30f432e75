"""Every engagement of a video, judged against ground-truth labels where they exist. Pure.

Replay (companion/replay.py) restarts the engagement after each end (HANDBACK, ABORT, LAND), so a long video
holds many engagements; this tally counts them frame by frame from what the core decided and the box it was
given, and, on labelled frames, whether that box was on the gate (its centre inside a labelled gate box, the
rule of ``companion perception eval``'s sequences):

* ``engagements``: engagements begun (the core's "gate N engaged" events);
* ``begun_on_wrong``: begun on a box that is not on a labelled gate (a gate-free frame counts as wrong);
* ``engaged_frames`` / ``engaged_frames_wrong`` / ``engaged_frames_on_gate``: labelled ENGAGE frames with a box;
* ``passes_claimed`` / ``passes_claimed_wrong``: "gate close" (PASS or pull-up) decisions, and those taken on a
  box that was not on the gate (the last box the engagement used when the close frame had none);
  ``passes_claimed_unlabelled``: claims that box's frame has no label for (neither right nor wrong: on the real
  dev sequences both models' one claim was such, on boxes of the background, 2026-12-07);
* ``begun_oversize`` / ``engaged_frames_oversize`` / ``passes_claimed_oversize``: of those on a gate by the centre
  rule, the boxes whose larger side is more than ``size_ratio`` (2) times the gate box's: a box of the gate merged
  with background, or another object centred on the gate (on real PX4 a same-coloured disc 3x the ring's size
  drawn behind it). The centre rule alone counts them as on the gate; their size is what the close detector reads
  as range, so a pass claimed on one is claimed at the wrong place. Kept apart so the centre rule's counts stay
  comparable with earlier tallies;
* ``gate_spells`` / ``never_engaged_spells``: runs of at least ``min_spell`` labelled frames with a gate in view,
  and those during which no engagement was flying (ENGAGE / PASS / RECOVER) nor began.

Frames without a label file are neither right nor wrong (``unlabelled_*`` counts them where it matters).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from perception.types import BoundingBox

COMMANDING = ("ENGAGE", "PASS", "RECOVER")


def on_gate(box: BoundingBox, gts: np.ndarray) -> bool:
    """The box's centre inside one labelled gate box (xyxy, px)."""
    return any(g[0] <= box.cx <= g[2] and g[1] <= box.cy <= g[3] for g in gts)


def oversize(box: BoundingBox, gts: np.ndarray, ratio: float, grown: float = 0.0) -> bool:
    """The box is on a labelled gate by its centre, but its larger side is more than ``ratio`` times that of every
    gate box its centre is in. ``grown``: px each label was grown by on every side (taken off again: a pose's
    error moves a box, it does not scale it)."""
    s = max(box.w, box.h)
    sides = [max(g[2] - g[0], g[3] - g[1]) - 2.0 * grown for g in gts
             if g[0] <= box.cx <= g[2] and g[1] <= box.cy <= g[3]]
    return bool(sides) and all(s > ratio * max(side, 1.0) for side in sides)


@dataclass
class EngagementTally:
    min_spell: int = 5  # frames: a shorter glimpse of the gate is not an engagement missed
    size_ratio: float = 2.0  # a box on a gate more than this times its size is oversize (the detector's box/truth
    # size between frames reached 1.37x at most on real PX4: docs/verification-px4.md)
    grown: float = 0.0  # px the labels given to add() were grown by (companion/logclutter.py's margin)
    engagements: int = 0
    begun_on_wrong: int = 0
    begun_unlabelled: int = 0
    engaged_frames: int = 0
    engaged_frames_wrong: int = 0
    engaged_frames_on_gate: int = 0
    passes_claimed: int = 0
    passes_claimed_wrong: int = 0
    passes_claimed_unlabelled: int = 0
    begun_oversize: int = 0
    engaged_frames_oversize: int = 0
    passes_claimed_oversize: int = 0
    gate_spells: int = 0
    never_engaged_spells: int = 0
    ends: dict[str, int] = field(default_factory=dict)
    _last: tuple[BoundingBox, np.ndarray | None] | None = None  # the last engaged box and its frame's labels
    _spell: int = 0  # frames of the current gate-in-view run
    _spell_flown: bool = False

    @staticmethod
    def _wrong(box: BoundingBox | None, gts: np.ndarray | None) -> bool | None:
        """True/False on a labelled frame with a box, None when it cannot be judged."""
        if box is None or gts is None:
            return None
        return not (len(gts) > 0 and on_gate(box, gts))

    def _oversize(self, box: BoundingBox | None, gts: np.ndarray | None) -> bool:
        """On a labelled gate by the centre rule, but too big to be its box."""
        return box is not None and gts is not None and oversize(box, gts, self.size_ratio, self.grown)

    def add(self, phase: str, events: tuple[str, ...], box: BoundingBox | None, gts: np.ndarray | None,
            end: str = "") -> None:
        """One frame: the phase after the core's step, its gate events, the box given to the core, the labels
        (None: unlabelled; (0, 4): gate-free) and, when the engagement ended on it, the end's name."""
        engaged = any(e.endswith(" engaged") for e in events)
        close = any(e.endswith(" close") or e.endswith("intercept: pulled up") for e in events)
        if engaged:
            self.engagements += 1
            w = self._wrong(box, gts)
            self.begun_on_wrong += bool(w)
            self.begun_unlabelled += w is None
            self.begun_oversize += w is False and self._oversize(box, gts)
        if phase == "ENGAGE" and box is not None:
            self._last = (box, gts)
            w = self._wrong(box, gts)
            if w is not None:
                self.engaged_frames += 1
                self.engaged_frames_wrong += w
                self.engaged_frames_on_gate += not w
                self.engaged_frames_oversize += not w and self._oversize(box, gts)
        if close:
            self.passes_claimed += 1
            b, g = (box, gts) if box is not None else (self._last or (None, None))
            w = self._wrong(b, g)
            self.passes_claimed_wrong += bool(w)
            self.passes_claimed_unlabelled += w is None
            self.passes_claimed_oversize += w is False and self._oversize(b, g)
        if end:
            self.ends[end] = self.ends.get(end, 0) + 1
        self._spell_step(gts, engaged or phase in COMMANDING)

    def _spell_step(self, gts: np.ndarray | None, flown: bool) -> None:
        if gts is not None and len(gts) > 0:
            self._spell += 1
            self._spell_flown |= flown
            return
        self._close_spell()

    def _close_spell(self) -> None:
        if self._spell >= self.min_spell:
            self.gate_spells += 1
            self.never_engaged_spells += not self._spell_flown
        self._spell, self._spell_flown = 0, False

    def finish(self) -> dict[str, Any]:
        """The counts (the video ended: an open gate-in-view run is closed)."""
        self._close_spell()
        d = {k: getattr(self, k) for k in (
            "engagements", "begun_on_wrong", "begun_unlabelled", "engaged_frames", "engaged_frames_wrong",
            "engaged_frames_on_gate", "passes_claimed", "passes_claimed_wrong", "passes_claimed_unlabelled",
            "begun_oversize", "engaged_frames_oversize", "passes_claimed_oversize", "gate_spells",
            "never_engaged_spells")}
        d["on_gate_share"] = (round(self.engaged_frames_on_gate / self.engaged_frames, 4)
                              if self.engaged_frames else None)
        d["ends"] = dict(self.ends)
        return d


def total(per_video: list[dict[str, Any]]) -> dict[str, Any]:
    """The tallies of several videos summed (shares recomputed from the sums)."""
    out: dict[str, Any] = {}
    ends: dict[str, int] = {}
    for d in per_video:
        for k, v in d.items():
            if k == "ends":
                for e, n in v.items():
                    ends[e] = ends.get(e, 0) + n
            elif isinstance(v, int):
                out[k] = out.get(k, 0) + v
    out["on_gate_share"] = (round(out["engaged_frames_on_gate"] / out["engaged_frames"], 4)
                            if out.get("engaged_frames") else None)
    out["ends"] = ends
    return out
