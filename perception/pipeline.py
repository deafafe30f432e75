"""Frame -> the target's box (or None): detector + tracker policy + box smoothing.

Policy (one state machine, both tracker kinds):

* searching: run the detector every frame; ``confirm_frames`` consecutive detections that agree
  with each other (re)acquire the target (a single false alarm does not).
* tracking: predict the box with the Kalman filter; measure it with the detector (every frame for
  ``tracker: detect``; every ``redetect_every`` frames or whenever NanoTrack's score drops below
  ``redetect_below`` for ``tracker: nanotrack``, the tracker in between); a measurement that
  neither overlaps the prediction nor lies within reach of it is a jump and is rejected (reach: ``max_jump_rate``
  image diagonals per second of the frame gap, at most ``max_jump``, plus half the predicted box's diagonal).
  The Kalman-filtered box (smoothing before the LOS) is the output.
* misses: the Kalman prediction is output for up to ``coast_time`` with decaying confidence, then
  the target is lost and the search starts again. A prediction whose centre is too uncertain
  (``COAST_MAX_SIGMA``: a long gap between frames, an erratic track) is not output (no box), though the
  track is kept until ``coast_time``.
* consistency (perception/tracker.py): only plausible boxes (aspect of a gate unless cut by the border)
  acquire or continue a track, and only measurements whose size change an approach explains continue it.
* a better candidate: the best detection that does not continue the track is followed as a challenger;
  once it has been seen ``switch_frames`` frames in a row and scores clearly better than the track
  (``TrackScore``), it takes the track. While such a challenger is building up, the target is uncertain:
  no box is output (the app treats that as no target), rather than a box that may be the wrong thing.
* no confident target: no box either while the track's score is below ``min_track_score``.
* a confident detection (``acquire_confidence``) acquires on its own frame: on real frames the detector's
  false boxes score low (on the dev set 3 % of the boxes at >= 0.5 are false) while waiting for
  ``confirm_frames`` after every miss left the gate unboxed; weaker detections still need confirming.
* memory of a lost track (``memory_time``; only a track whose score was at least ``memory_min_score`` at its
  last measurement: a weak track may have been the wrong thing): for that long after its last measurement, a new
  acquisition must be consistent with it (size change at most ``memory_growth_rate`` over the elapsed time,
  centre within ``max_jump`` plus ``memory_reach_rate`` per second of it); anything else waits until the
  memory ends (and still needs ``confirm_frames``). ``reset`` (a gate was passed) forgets it: the next gate
  is new. ``memory_growth_rate`` is below ``max_growth_rate`` because ``max_growth_rate`` (speed / distance)
  is reached only in the last moments before a pass, not over a second out of sight of a far gate.
* an acquisition or a switch needs a box wholly in view: a box cut by the image border is clutter at the edge
  or a gate whose centre the box does not show; a near gate cut by the border is followed only by a track
  that already holds it (on the dev sequences, re-acquiring border boxes consistent with the lost track
  put the track on a tall border box instead of the gate).
* a switch to a challenger must also be size-consistent with the track (over the time since the track's
  last measurement); a track gone weak (score below ``min_track_score``) is treated like a lost one (the
  memory rules if it was sure when last measured, else anything may take it); a challenger that may not
  switch does not make the target uncertain either. Why: on real PX4 a 45 px gate track gave way to a
  198 px panorama object 370 px away after the 2 "uncertain" frames of its build-up, and the engagement
  read the jump as the gate coming near.

* an object the app refused (``refuse``: its verification, companion/verify.py, refused the candidate several
  frames in a row): the track or candidate is dropped and, for ``refuse_time``, the detection that continues that
  object (followed frame to frame, as a track is) may not acquire, continue or challenge a track. Why: on real PX4
  (x500, 2026-12-07, run091) a 330x345 px box 5 px from the border was acquired by the pipeline, refused by
  verification as cut every frame, and held for 15 s while the 39 px gate crossed the view: the search never ran.
  Once the time is up it may acquire again (a gate refused while cut, now in view, is taken back).

* zoomed detection (perception/zoom.py): a target under ``zoom_below`` px (the track's prediction, under
  ``zoom_track_below``; the candidate being confirmed, or the lost track's last box) is also detected in a crop of
  the detector's input size at full resolution around it, whose boxes replace the whole frame's boxes of the same
  objects; searching with nothing small to confirm, one full-resolution tile of the frame a frame (``zoom_scan``;
  auto = rendered frames only). The detector sees a 640x480 frame at half size: a 39 px ring 25 m away is 20 px
  to it, and a 100-180 px ring merges with background beside it, which it does much less at full resolution.

The output box's ``t`` is the frame's capture time.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from perception.appearance import descriptor
from perception.derotate import Derotation
from perception.detector import Detector
from perception.los import CameraModel
from perception.tracker import (
    BoxKalman,
    NanoTracker,
    TrackScore,
    associate,
    consistent,
    iou,
    plausible,
    touches_border,
)
from perception.types import BoundingBox
from perception.zoom import Crop, merge, referee, scan_crop, zoom_crop

if TYPE_CHECKING:
    from companion.config import Config
    from companion.config_perception import PerceptionConfig


# A coasted box is output only while the Kalman filter's centre uncertainty (1 sigma) is below this fraction of
# the box's smaller side: at 30 fps a 300 ms coast stays far below it; after a 0.2 s gap (5 Hz) on a jerky
# track it does not, and such predictions were the most frequent wrong-target boxes on the real dev sequences.
COAST_MAX_SIGMA = 0.25


@dataclass
class _Candidate:
    box: BoundingBox
    score: TrackScore
    misses: int = 0


@dataclass
class _Refused:
    """An object the app refused: its last box, when it was seen, and when it was refused."""

    box: BoundingBox
    t_seen: float
    t_refused: float


@dataclass(frozen=True)
class _Memory:
    """The lost track: its last filtered box and when it was last measured."""

    box: BoundingBox
    t: float


@dataclass
class PipelineStats:
    frames: int = 0
    detector_runs: int = 0
    zoom_runs: int = 0  # detector runs on a full-resolution crop around a small target (perception/zoom.py)
    tracker_runs: int = 0
    boxes: int = 0  # frames with an output box
    measured: int = 0  # frames whose box was corrected by a measurement
    coasted: int = 0  # frames whose box is a prediction
    derotated: int = 0  # frames whose track was moved by the camera's own rotation (perception/derotate.py)
    rejected_jumps: int = 0
    acquisitions: int = 0
    losses: int = 0
    rejected_inconsistent: int = 0  # implausible aspect or size change
    switches: int = 0  # the track moved to a persistently better candidate
    held_back: int = 0  # frames an acquisition or switch waited: inconsistent with the (lost) track, or border-cut
    unconfident: int = 0  # frames with no box because the target was uncertain
    refusals: int = 0  # objects the app refused as not the target (``Pipeline.refuse``)
    detector_ms: list[float] = field(default_factory=list)
    tracker_ms: list[float] = field(default_factory=list)
    total_ms: list[float] = field(default_factory=list)

    def summary(self) -> dict[str, float | int]:
        def med(x: list[float]) -> float:
            return round(float(np.median(x)), 3) if x else 0.0

        return {
            "frames": self.frames, "detector_runs": self.detector_runs, "zoom_runs": self.zoom_runs,
            "tracker_runs": self.tracker_runs,
            "boxes": self.boxes, "measured": self.measured, "coasted": self.coasted, "derotated": self.derotated,
            "rejected_jumps": self.rejected_jumps, "acquisitions": self.acquisitions, "losses": self.losses,
            "rejected_inconsistent": self.rejected_inconsistent, "switches": self.switches,
            "unconfident": self.unconfident, "held_back": self.held_back, "refusals": self.refusals,
            "detector_ms_median": med(self.detector_ms), "tracker_ms_median": med(self.tracker_ms),
            "pipeline_ms_median": med(self.total_ms),
        }


class Pipeline:
    """``process(frame, t) -> BoundingBox | None`` for one target; ``stats`` counts what happened."""

    def __init__(self, detector: Detector, pc: PerceptionConfig, width: int, height: int,
                 tracker: NanoTracker | None = None, appearance: bool = False, real_frames: bool = False,
                 camera: CameraModel | None = None) -> None:
        self.det = detector
        # The camera's own rotation out of the held boxes (perception/derotate.py) when frames come with an attitude.
        self.derotation = Derotation(camera) if camera is not None and pc.derotate else None
        # The search's tile scan (perception/zoom.py): zoom_scan auto = rendered frames only.
        self.scan = pc.zoom_scan is True or (pc.zoom_scan == "auto" and not real_frames)
        self.appearance = appearance  # attach the box's appearance descriptor (only the appearance rule reads it)
        self.pc = pc
        self.width, self.height = int(width), int(height)
        self.tracker = tracker
        self.diag_px = math.hypot(width, height)
        self.max_jump_px = float(pc.max_jump) * self.diag_px
        self.stats = PipelineStats()
        self.weigh_rivals = False  # see acquiring()
        self.reset()

    @classmethod
    def from_config(cls, cfg: Config, detector: Detector | None = None, real_frames: bool = False) -> Pipeline:
        """``real_frames``: frames of a real camera (perception/detector.py model_path picks the model)."""
        pc = cfg.perception
        det = detector if detector is not None else Detector.from_config(pc, real_frames)
        trk = NanoTracker(pc.nanotrack_backbone, pc.nanotrack_neckhead) if pc.tracker == "nanotrack" else None
        v = cfg.app.verify
        return cls(det, pc, cfg.camera.width, cfg.camera.height, trk, appearance=v.enabled and v.min_similarity > 0,
                   real_frames=real_frames, camera=CameraModel.from_config(cfg.camera))

    def reset(self) -> None:
        self.kf: BoxKalman | None = None
        self.t_prev: float | None = None
        self.t_measured: float | None = None
        self.candidate: BoundingBox | None = None
        self.candidate_count = 0
        self.frame_index = 0
        self.last_conf = 0.0
        self.last_detections: list[BoundingBox] = []
        self._others: list[BoundingBox] = []  # this frame's plausible detections other than the one given out
        self._looked_past: BoundingBox | None = None  # this frame's box of the refused object, if seen
        self.score: TrackScore | None = None
        self.challenger: _Candidate | None = None
        self.memory: _Memory | None = None
        self.last_box: BoundingBox | None = None
        self.held_score = 0.0  # the track's score at its last measurement
        self.refused: _Refused | None = None
        if self.tracker is not None:
            self.tracker.active = False

    def acquiring(self, on: bool) -> None:
        """Whether the app is acquiring (companion/core.py ``CoreStep.tell_tracker``): then a small other candidate
        is detected again at full resolution, so that it is weighed against the held box at the same scale (the
        held box is zoomed on as a track already); while engaged that detector run would be spent for nothing."""
        self.weigh_rivals = bool(on)

    def refuse(self) -> None:
        """The app refused the object this pipeline holds (the track, else the candidate) as not the target: drop
        it and, for ``refuse_time``, look past it (its continuation is no detection). Without a refuse time,
        a reset."""
        box = self.last_box if self.kf is not None else self.candidate
        t = self.t_prev
        self.reset()
        if box is not None and t is not None and self.pc.refuse_time > 0.0:
            self.refused = _Refused(box, t, t)
        self.stats.refusals += 1

    def _past_refused(self, dets: list[BoundingBox], t: float) -> list[BoundingBox]:
        """``dets`` without the one continuing the refused object (which it follows); all once the time is up."""
        r = self.refused
        if r is None:
            return dets
        if t - r.t_refused > self.pc.refuse_time:
            self.refused = None
            return dets
        dt = t - r.t_seen
        fits = [d for d in dets if consistent(r.box, d, dt, self.pc.max_growth_rate)]
        m, _ = associate(r.box, fits, self._jump_px(dt), self.pc.min_iou)
        if m is None:
            return dets
        r.box, r.t_seen = m, t
        self._looked_past = m
        return [d for d in dets if d is not m]

    @property
    def tracking(self) -> bool:
        return self.kf is not None

    def process(self, frame: np.ndarray, t: float, R_world_body: np.ndarray | None = None) -> BoundingBox | None:
        """The target's box in ``frame`` captured at ``t``. ``R_world_body``: the body's attitude at capture (FRD ->
        a fixed world frame, the one the app rotates the box with), to move what the pipeline holds by the camera's
        own rotation since the previous frame; None (a video without attitude): image-space prediction alone."""
        t0 = time.perf_counter()
        st = self.stats
        st.frames += 1
        self.frame_index += 1
        dt = (t - self.t_prev) if self.t_prev is not None else 0.0
        self.t_prev = t
        if self.derotation is not None:
            M = self.derotation.step(R_world_body, dt)
            if M is not None:
                self._derotate(M)
        self._others, self._looked_past = [], None
        out = self._track(frame, t, dt) if self.kf is not None else self._search(frame, t, dt)
        if out is not None:
            out = self._clip(out)
        if out is not None:
            st.boxes += 1
            r = self._rival(out)
            if r is not None and self.weigh_rivals:
                r = self._full_resolution(frame, r)
            if r is not None:
                out = replace(out, rival=r)
            if self.appearance:  # what the box shows, for verification's appearance rule (companion/verify.py)
                out = replace(out, appearance=descriptor(frame, out))
        st.total_ms.append((time.perf_counter() - t0) * 1e3)
        return out

    def _derotate(self, M: np.ndarray) -> None:
        """Move every box the pipeline holds (track, candidate, challenger, memory, refused object) by the camera's
        rotation ``M`` since the previous frame: they are compared with this frame's detections."""
        d = self.derotation
        assert d is not None

        def mv(b: BoundingBox) -> BoundingBox:
            p = d.move(M, b.cx, b.cy)
            return b if p is None else replace(b, cx=p[0], cy=p[1])

        if self.kf is not None:
            b = self.kf.box
            p = d.move(M, b.cx, b.cy)
            if p is not None:
                self.kf.shift(p[0] - b.cx, p[1] - b.cy)
                self.stats.derotated += 1
        if self.last_box is not None:
            self.last_box = mv(self.last_box)
        if self.candidate is not None:
            self.candidate = mv(self.candidate)
        if self.challenger is not None:
            self.challenger.box = mv(self.challenger.box)
        if self.memory is not None:
            self.memory = replace(self.memory, box=mv(self.memory.box))
        if self.refused is not None:
            self.refused.box = mv(self.refused.box)

    # -- states ------------------------------------------------------------------------------

    def _zoom(self, frame: np.ndarray, focus: BoundingBox | None) -> Crop | None:
        """Where to look again at full resolution (perception/zoom.py): around ``focus`` (where the target is
        thought to be) when it is small; while searching with no small focus, the next tile of the scan: a big
        candidate (a border box the search holds but may not acquire) must not stop the search looking for a small
        gate elsewhere."""
        if self.pc.zoom_below <= 0.0 or frame.shape[0] != self.height or frame.shape[1] != self.width:
            return None
        crop = None
        if focus is not None:
            # A track is zoomed on up to a larger size than a search focus: at half size the detector boxes a
            # 100-180 px ring together with background beside it, and a track that takes such a box grows frame by
            # frame (PX4 SIH merge ramps); a search keeps zoom_below so a big candidate does not stop the scan.
            below = max(self.pc.zoom_below, self.pc.zoom_track_below) if self.kf is not None else self.pc.zoom_below
            crop = zoom_crop(focus, self.width, self.height, self.det.input_hw, below)
        if crop is None and self.kf is None and self.scan:
            crop = scan_crop(self.frame_index, self.width, self.height, self.det.input_hw)
        return crop

    def _detect(self, frame: np.ndarray, t: float, focus: BoundingBox | None = None) -> list[BoundingBox]:
        """The detector's boxes on the frame, and where ``_zoom`` says, on a full-resolution crop too, whose boxes
        replace the frame's boxes of the same objects."""
        dets = self.det.detect(frame, t)
        ms = self.det.last_ms
        self.stats.detector_runs += 1
        crop = self._zoom(frame, focus)
        if crop is not None:
            zoomed = self.det.detect(crop.of(frame), t)
            if self.kf is not None and focus is not None and max(focus.w, focus.h) >= self.pc.zoom_below:
                # a track zoomed on for merges only (zoom_track_below): the crop referees the frame's box
                dets = referee(dets, zoomed, crop, self.pc.nms_iou, focus)
            else:
                dets = merge(dets, zoomed, crop, self.pc.nms_iou)
            ms += self.det.last_ms
            self.stats.zoom_runs += 1
        self.stats.detector_ms.append(ms)
        self.last_detections = dets
        return dets

    def _plausible(self, dets: list[BoundingBox]) -> list[BoundingBox]:
        ok = [d for d in dets if plausible(d, self.width, self.height, self.pc.max_aspect)]
        self.stats.rejected_inconsistent += len(dets) - len(ok)
        return ok

    def _search(self, frame: np.ndarray, t: float, dt: float) -> BoundingBox | None:
        # Zoom on what is being confirmed, else on where the lost target was last seen.
        focus = self.candidate if self.candidate is not None else (self.memory.box if self.memory is not None else None)
        dets = self._past_refused(self._plausible(self._detect(frame, t, focus)), t)
        if self.memory is not None and t - self.memory.t > self.pc.memory_time:
            self.memory = None  # long enough without the old target: anything may acquire (the next gate)
        if not dets:
            self.candidate, self.candidate_count = None, 0
            return None
        # Boxes that may acquire now come first: a border box or one the lost track rules out must not keep the
        # candidate slot from the gate; when there are none, they are followed (acquired once the memory ends).
        pool = [d for d in dets if self._may_acquire(d, t)] or dets
        cont = None
        if self.candidate is not None:
            fits = [d for d in pool if consistent(self.candidate, d, dt, self.pc.max_growth_rate)]
            cont, _ = associate(self.candidate, fits, self._jump_px(dt), self.pc.min_iou)
        if cont is not None:
            best = cont
            self.candidate_count += 1
        else:
            best = pool[0]
            self.candidate_count = 1
        self.candidate = best
        self._others = [d for d in dets if d is not best]
        if self.candidate_count < self.pc.confirm_frames and best.confidence < self.pc.acquire_confidence:
            return None
        if not self._may_acquire(best, t):
            self.stats.held_back += 1
            return None
        # Acquired: start the box filter at this detection.
        self.kf = BoxKalman(best, self.pc.smoothing)
        self.t_measured = t
        self.last_conf = best.confidence
        self.last_box = best
        self.score = TrackScore(best.confidence)
        self.held_score = best.confidence
        self.challenger = None
        self.memory = None
        self.candidate, self.candidate_count = None, 0
        self.stats.acquisitions += 1
        self.stats.measured += 1
        if self.tracker is not None:
            self.tracker.init(frame, best)
        return BoundingBox(best.cx, best.cy, best.w, best.h, best.confidence, t)

    def _jump_px(self, dt: float) -> float:
        """How far (px) a box centre may move between two frames dt apart: ``max_jump_rate`` image diagonals per
        second, at most ``max_jump``. At 30 fps a far gate cannot cross 200 px in one frame; at 5 Hz it can."""
        return min(self.max_jump_px, self.pc.max_jump_rate * self.diag_px * max(dt, 0.0))

    def _may_acquire(self, d: BoundingBox, t: float) -> bool:
        """May ``d`` start a track now? Only a box wholly in view and, within the memory time, only as the lost
        track's continuation (size and position reachable in the elapsed time)."""
        if touches_border(d, self.width, self.height):
            return False
        m = self.memory
        return m is None or self._reachable(m.box, t - m.t, d)

    def _reachable(self, last: BoundingBox, elapsed: float, d: BoundingBox) -> bool:
        """Could the target last seen as ``last`` look like ``d`` after ``elapsed`` s unseen (memory rules)?"""
        if elapsed > self.pc.memory_time:
            return True
        reach = self.max_jump_px + 0.5 * math.hypot(last.w, last.h) + self.pc.memory_reach_rate * self.diag_px * elapsed
        return (consistent(last, d, elapsed, self.pc.memory_growth_rate)
                and math.hypot(d.cx - last.cx, d.cy - last.cy) <= reach)

    def _track(self, frame: np.ndarray, t: float, dt: float) -> BoundingBox | None:
        assert self.kf is not None
        pred = self.kf.predict(dt)
        meas: BoundingBox | None = None
        run_detector = True
        if self.tracker is not None and self.tracker.active:
            t1 = time.perf_counter()
            tb, score = self.tracker.update(frame, t)
            self.stats.tracker_runs += 1
            self.stats.tracker_ms.append((time.perf_counter() - t1) * 1e3)
            due = self.frame_index % self.pc.redetect_every == 0
            near = tb is not None and (
                iou(tb, pred) >= self.pc.min_iou or math.hypot(tb.cx - pred.cx, tb.cy - pred.cy) <= self.max_jump_px
            )
            if near and score >= self.pc.redetect_below and not due:
                meas, run_detector = tb, False
        if run_detector:
            dets = self._past_refused(self._plausible(self._detect(frame, t, pred)), t)
            fits = [d for d in dets if consistent(pred, d, dt, self.pc.max_growth_rate)]
            meas, rejected = associate(pred, fits, self._jump_px(dt), self.pc.min_iou)
            self.stats.rejected_jumps += rejected
            self.stats.rejected_inconsistent += len(dets) - len(fits)
            self._others = [d for d in dets if d is not meas]
            self._follow_challenger(self._others, dt)
            if meas is not None and self.tracker is not None:
                self.tracker.init(frame, meas)
        assert self.score is not None
        self.score.update(meas.confidence if meas is not None else None)
        ch = self.challenger
        rival = ch is not None and self._better(ch) and self._may_switch(ch, pred, t)
        if ch is not None and ch.score.streak >= self.pc.switch_frames and self._better(ch) and not rival:
            self.stats.held_back += 1
        if rival and ch is not None and ch.score.streak >= self.pc.switch_frames:
            return self._switch(frame, ch, t)
        # Uncertain: a clearly better candidate that may take the track is building up, or the track is weak.
        uncertain = (rival and ch is not None and ch.score.streak >= self.pc.switch_frames // 2 + 1) or (
            self.score.value < self.pc.min_track_score)
        if meas is not None:
            box = self.kf.correct(meas)
            self.last_box = box
            self.held_score = self.score.value
            self.t_measured = t
            self.last_conf = meas.confidence
            self.stats.measured += 1
            if uncertain:
                self.stats.unconfident += 1
                return None
            return BoundingBox(box.cx, box.cy, box.w, box.h, meas.confidence, t)
        # Miss: coast on the prediction, then give up and search again.
        since = t - (self.t_measured if self.t_measured is not None else t)
        if since > self.pc.coast_time or self.pc.coast_time <= 0.0:
            self.kf = None
            self.stats.losses += 1
            last, t_last = self.last_box, self.t_measured
            if last is not None and t_last is not None and self.held_score >= self.pc.memory_min_score:
                self.memory = _Memory(last, t_last)  # a sure track: what re-acquires must be consistent with it
            if self.tracker is not None:
                self.tracker.active = False
            # a challenger seen often enough becomes the search candidate: re-acquired on its next detection
            if ch is not None and ch.score.streak >= 1:
                self.candidate, self.candidate_count = ch.box, min(ch.score.streak, self.pc.confirm_frames - 1)
            self.challenger = None
            return None
        if self.kf.centre_sigma > COAST_MAX_SIGMA * min(pred.w, pred.h):
            # the prediction may have left the gate (a long frame gap, an erratic track): no box, keep the track
            self.stats.unconfident += 1
            return None
        self.stats.coasted += 1
        if uncertain:
            self.stats.unconfident += 1
            return None
        decay = 1.0 - since / self.pc.coast_time
        return BoundingBox(pred.cx, pred.cy, pred.w, pred.h, self.last_conf * decay, t)

    # -- challenger: the best other candidate, followed over frames ------------------------------

    _MARGIN = 0.1  # score a challenger must lead the track by (confidence units)

    def _better(self, ch: _Candidate) -> bool:
        assert self.score is not None
        return ch.score.value > self.score.value + self._MARGIN

    def _may_switch(self, ch: _Candidate, pred: BoundingBox, t: float) -> bool:
        """A challenger may take the track only wholly in view and at a size the track could have grown (or
        shrunk) to since its last measurement; a track gone weak through misses is treated like a lost one (the
        memory rules, if it was sure when last measured)."""
        assert self.score is not None
        if touches_border(ch.box, self.width, self.height):
            return False
        since = t - (self.t_measured if self.t_measured is not None else t)
        if self.score.value < self.pc.min_track_score:
            if self.last_box is None or self.held_score < self.pc.memory_min_score:
                return True
            return self._reachable(self.last_box, since, ch.box)
        return consistent(pred, ch.box, since, self.pc.max_growth_rate)

    def _follow_challenger(self, others: list[BoundingBox], dt: float) -> None:
        ch = self.challenger
        if ch is not None:
            fits = [d for d in others if consistent(ch.box, d, dt, self.pc.max_growth_rate)]
            nxt, _ = associate(ch.box, fits, self._jump_px(dt), self.pc.min_iou)
            if nxt is not None:
                ch.box = nxt
                ch.misses = 0
                ch.score.update(nxt.confidence)
                return
            ch.score.update(None)
            ch.misses += 1
            if ch.misses < 2:
                return
            self.challenger = None
        if others:
            best = max(others, key=lambda d: d.confidence)
            self.challenger = _Candidate(best, TrackScore(best.confidence))

    def _switch(self, frame: np.ndarray, ch: _Candidate, t: float) -> BoundingBox:
        self.kf = BoxKalman(ch.box, self.pc.smoothing)
        self.score, self.challenger = ch.score, None
        self.t_measured = t
        self.last_conf = ch.box.confidence
        self.last_box = ch.box
        self.held_score = ch.score.value
        self.stats.switches += 1
        self.stats.measured += 1
        if self.tracker is not None:
            self.tracker.init(frame, ch.box)
        b = ch.box
        return BoundingBox(b.cx, b.cy, b.w, b.h, b.confidence, t)

    def _rival(self, out: BoundingBox) -> BoundingBox | None:
        """The most confident other candidate in this frame: a detection (plausible; the refused object too: looked
        past, it is still there) wholly in view whose centre is more than half a box away from ``out``'s (a second
        box on the same ring is not another object). None when there is none."""
        best = None
        others = self._others if self._looked_past is None else [*self._others, self._looked_past]
        for d in others:
            if ((best is None or d.confidence > best.confidence) and not touches_border(d, self.width, self.height)
                    and math.hypot(d.cx - out.cx, d.cy - out.cy) > 0.5 * max(out.w, out.h, d.w, d.h)):
                best = d
        return best

    def _full_resolution(self, frame: np.ndarray, b: BoundingBox) -> BoundingBox:
        """``b`` as the detector sees it in a full-resolution crop around it, when it is small enough to zoom on
        (``zoom_below``): the detector sees the frame at half size, where a 40 px ring 25 m away scored 0.51-0.55
        against a 180 px clutter arc's 0.75 (real PX4 SIH, 2026-12-07, seed 3 run003) and 0.94-0.97 in a crop. The
        held box, when small, is detected in a crop already. ``b`` itself when the crop does not show it again."""
        if frame.shape[0] != self.height or frame.shape[1] != self.width:
            return b
        crop = zoom_crop(b, self.width, self.height, self.det.input_hw, self.pc.zoom_below)
        if crop is None:
            return b
        zoomed = [z for z in map(crop.to_frame, self.det.detect(crop.of(frame), b.t)) if crop.holds(z)]
        self.stats.zoom_runs += 1
        same = [z for z in zoomed if math.hypot(z.cx - b.cx, z.cy - b.cy) <= 0.5 * max(b.w, b.h)]
        return max(same, key=lambda z: z.confidence) if same else b

    def _clip(self, b: BoundingBox) -> BoundingBox | None:
        """Clip to the image; a box whose centre left the image is no box (the LOS would be invented)."""
        x0, y0, x1, y1 = b.xyxy
        x0, y0 = max(0.0, x0), max(0.0, y0)
        x1, y1 = min(float(self.width), x1), min(float(self.height), y1)
        if x1 - x0 < 1.0 or y1 - y0 < 1.0:
            return None
        c = BoundingBox.from_xyxy(x0, y0, x1, y1, b.confidence, b.t)
        return c if c.is_valid(self.width, self.height) else None
