"""Is another object in view as likely the target as the candidate? Pure, over the stable-track streak at ACQUIRE.

Why: on real PX4 SITL (SIH quad, rendered frames, 2026-12-07) the app began engagements on background boxes while
the 40 px ring 25 m away was in view and detected in every frame. Of 200 flights (seeds 1 and 3) whose
acquisitions were perceived again from their logs, 7 engaged a wrong box. In 4 the detector rated the ring higher
than the box the tracker held, by 0.08-0.17 on the mean over the 10 frames before the engagement: the tracker
cannot switch to a box of another size (that is what keeps a gate against background). In 2 it rated a clutter
arc 0.12-0.14 above the ring: at half size, as the detector sees the frame. In a full-resolution crop the same
ring scored 0.94-0.97 against the arc's 0.72-0.78, so while acquiring the pipeline weighs a small other candidate
at full resolution (the held box is zoomed on as a track already). In the 193 engagements begun on the ring the
best other candidate (at half size) stayed at least 0.25 below it.

Rule: over the last ``frames`` verified frames of one candidate, when the mean of the best other candidate's
confidence (``BoundingBox.rival``, perception/pipeline.py; 0 in frames without one; one that fails the cut, shape
or range rules does not count) comes within ``margin`` of the mean of the candidate's own, the candidate is not
engaged and perception is told to look past it (perception's ``refuse_time``). The other object then becomes the
candidate. An object looked past still counts as another candidate, so the app engages only a candidate that leads
every other in view: of two alike it engages neither and stays in ACQUIRE. With the operator's confirmation
(``app.engage confirm``) the operator is the judge of two alike: there a candidate is looked past only when another
leads it by more than ``margin`` (``add(..., operator=True)``), and the held one is shown.

While engaged (``engaged``): on real PX4 (SIH quad, linear-fast gate, 2026-12-07, seed 3 run012) the vehicle missed
a receding ring by its side; the tracker's box, 300-480 px, merged with background below it and grew away from the
ring, and its growth read as a time-to-contact: "gate passed" beside the ring, which the detector still saw, 100 px
wide, rated 0.42-0.49 against the merged box's 0.27-0.36. The detector sees the frame at half size, where a smaller
object scores lower, not higher: in 100 PX4 flights (SIH seed 3, x500 seed 4) another candidate led the engaged
ring by more than the margin in 55 frames, never one at most half the ring's size (clutter arcs beside 44-141 px
rings); it led a wrong box in 6, 3 of them at most half its size. So a candidate at most half the engaged box's
size (``SMALLER``) leading it by more than ``margin`` for ``engaged_frames`` frames in a row says the box is no
longer the ring: it counts as no box (coast; no close, no pass; its size history dropped) and perception looks past
it, so the other candidate may be tracked and the target lock judges whether it continues the gate.
"""

from __future__ import annotations

from collections import deque

from perception.types import BoundingBox

# While engaged, the other candidate counts only when at most this fraction of the engaged box's size. Two boxes of
# about one size near the gate can be two parts of one ring filling the view: on real PX4 (SIH seed 3 run016) at the
# moment of the pass the detector rated a 403 px box 0.72 against the held 420 px box's 0.47, both the ring's.
SMALLER = 0.5


class RivalWatch:
    """``reset()`` for a new candidate; ``add(confidence, rival)`` every verified frame of it at ACQUIRE."""

    def __init__(self, margin: float, frames: int, engaged_frames: int = 0) -> None:
        self.margin = margin
        self.frames = max(1, int(frames))
        self.engaged_frames = max(0, int(engaged_frames))  # 0: no rule while engaged
        self._ahead = 0  # engaged frames in a row with a much smaller candidate leading
        self.reset()

    def reset(self) -> None:
        self._seen: deque[tuple[float, float]] = deque(maxlen=self.frames)
        self._ahead = 0

    def add(self, confidence: float, rival: float, operator: bool = False) -> str:
        """"" while the candidate may be engaged; why not once its last ``frames`` frames say another candidate in
        view is as likely the target (``operator``: an operator confirms; only one clearly more likely counts)."""
        self._seen.append((confidence, rival))
        if len(self._seen) < self.frames:
            return ""
        own = sum(c for c, _ in self._seen) / len(self._seen)
        other = sum(r for _, r in self._seen) / len(self._seen)
        # Without an operator the candidate must lead by the margin; with one, only another leading by it refuses.
        if not (other > own + self.margin if operator else other >= own - self.margin):
            return ""
        how = "more likely" if operator else "as likely"
        return (f"another candidate in view is {how} the target (its confidence {other:.2f} against this one's "
                f"{own:.2f}, means over {len(self._seen)} frames; margin {self.margin:.2f})")

    def engaged(self, box: BoundingBox, rival: BoundingBox | None) -> str:
        """"" while the engaged ``box`` may still be the target; why not once another candidate ``rival`` (one that
        passes the cut, shape and range rules; None: none) at most half its size has led it by more than
        ``margin`` for ``engaged_frames`` frames in a row. ``reset()`` when an engagement begins."""
        if (self.engaged_frames == 0 or rival is None or max(rival.w, rival.h) > SMALLER * max(box.w, box.h)
                or rival.confidence <= box.confidence + self.margin):
            self._ahead = 0
            return ""
        self._ahead += 1
        if self._ahead < self.engaged_frames:
            return ""
        return (f"another candidate in view, at most half this box's size ({max(rival.w, rival.h):.0f} px against "
                f"{max(box.w, box.h):.0f} px), is more likely the target: its confidence {rival.confidence:.2f} "
                f"against this one's {box.confidence:.2f}, {self._ahead} frames in a row (margin {self.margin:.2f}; "
                "seen at half size, a smaller object is rated lower, not higher)")
