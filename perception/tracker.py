"""Box trackers: a constant-velocity Kalman filter on the box (weight-free default) and OpenCV NanoTrack.

``BoxKalman`` (cv2.KalmanFilter, state cx, cy, w, h and their rates) smooths detections and
predicts the box through missed frames. ``NanoTracker`` wraps ``cv2.TrackerNano`` (the paper's
tracker); it needs two ONNX files that cannot be downloaded here, so a missing or unreadable file
is refused with one line. ``associate`` picks the detection that continues a track.

Consistency rules (why a box is or is not the gate we track):

* ``plausible``: a gate (square or round) seen up to ~70 deg off-axis has a box aspect within
  ``max_aspect`` unless the image border cuts it; tall door panels, cabinets and strips are not gates.
* ``consistent``: a measurement's size may differ from the prediction only as much as an approach
  (or a retreat) allows in the elapsed time: ``|ln(size / predicted size)| <= max_growth_rate * dt``
  (floored, so detector jitter on one frame is not a switch).
* ``TrackScore``: the track's confidence averaged over frames, a miss counting 0; the pipeline
  outputs no box below ``min_track_score`` and compares candidates by it.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from perception.types import BoundingBox


class TrackerError(ValueError):
    """A tracker that cannot be built, as one line (file and what is wrong)."""


def iou(a: BoundingBox, b: BoundingBox) -> float:
    ax0, ay0, ax1, ay1 = a.xyxy
    bx0, by0, bx1, by1 = b.xyxy
    inter = max(0.0, min(ax1, bx1) - max(ax0, bx0)) * max(0.0, min(ay1, by1) - max(ay0, by0))
    union = a.w * a.h + b.w * b.h - inter
    return inter / union if union > 0 else 0.0


def associate(
    pred: BoundingBox, dets: list[BoundingBox], max_jump_px: float, min_iou: float
) -> tuple[BoundingBox | None, int]:
    """The detection that continues the track, and how many detections were rejected as jumps.

    A detection continues the track if it overlaps the prediction (IoU >= min_iou) or its centre is
    within ``max_jump_px`` (plus half the predicted size, so big near gates may move more). Among
    those, the one with the best IoU x confidence, ties broken by distance.
    """
    best, best_key, rejected = None, None, 0
    reach = max_jump_px + 0.5 * math.hypot(pred.w, pred.h)
    for d in dets:
        ov = iou(pred, d)
        dist = math.hypot(d.cx - pred.cx, d.cy - pred.cy)
        if ov < min_iou and dist > reach:
            rejected += 1
            continue
        key = (ov * d.confidence, -dist)
        if best_key is None or key > best_key:
            best, best_key = d, key
    return best, rejected


def touches_border(b: BoundingBox, width: int, height: int, margin: float = 2.0) -> bool:
    x0, y0, x1, y1 = b.xyxy
    return x0 <= margin or y0 <= margin or x1 >= width - margin or y1 >= height - margin


def plausible(b: BoundingBox, width: int, height: int, max_aspect: float) -> bool:
    """Could this box be a gate? Aspect within max_aspect (either way) unless the image border cuts it."""
    if b.w <= 0 or b.h <= 0:
        return False
    aspect = max(b.w / b.h, b.h / b.w)
    return aspect <= max_aspect or touches_border(b, width, height)


def consistent(pred: BoundingBox, meas: BoundingBox, dt: float, max_growth_rate: float,
               floor: float = math.log(1.5)) -> bool:
    """Is meas's size reachable from the predicted size in dt (approach/retreat at most max_growth_rate 1/s)?"""
    s_pred = math.sqrt(max(pred.w * pred.h, 1.0))
    s_meas = math.sqrt(max(meas.w * meas.h, 1.0))
    return abs(math.log(s_meas / s_pred)) <= max(max_growth_rate * max(dt, 0.0), floor)


class TrackScore:
    """Exponential average of detection confidence per frame (a miss is 0): how sure we are of a track."""

    def __init__(self, confidence: float, keep: float = 0.85) -> None:
        self.keep = float(keep)
        self.value = float(confidence)
        self.frames = 1  # frames since the track/candidate started
        self.streak = 1  # consecutive frames with a measurement

    def update(self, confidence: float | None) -> float:
        c = 0.0 if confidence is None else float(confidence)
        self.value = self.keep * self.value + (1.0 - self.keep) * c
        self.frames += 1
        self.streak = self.streak + 1 if confidence is not None else 0
        return self.value


class BoxKalman:
    """Constant-velocity Kalman filter on (cx, cy, w, h) with a variable time step."""

    def __init__(self, box: BoundingBox, smoothing: float = 0.5) -> None:
        self.smoothing = float(smoothing)
        kf = cv2.KalmanFilter(8, 4, 0, cv2.CV_64F)
        kf.measurementMatrix = np.hstack([np.eye(4), np.zeros((4, 4))])
        kf.transitionMatrix = np.eye(8)
        kf.statePost = np.array([[box.cx], [box.cy], [box.w], [box.h], [0.0], [0.0], [0.0], [0.0]])
        scale = max(box.w, box.h, 10.0)
        kf.errorCovPost = np.diag([4.0, 4.0, 4.0, 4.0, scale**2, scale**2, scale**2 / 4, scale**2 / 4])
        self.kf = kf
        # smoothing 0..1 sets the process noise (box acceleration the filter expects, at a box size of
        # 100 px) from 10^4 px/s^2 (follows every measurement) to 10 px/s^2 (heavy smoothing, more lag).
        self._meas_px = 2.0
        self._accel = 10.0 ** (4.0 - 3.0 * self.smoothing)

    def _noise(self, size: float) -> tuple[float, float]:
        # Noise grows with apparent size (near gates jitter and grow faster in px); floored so small far
        # gates are not over-smoothed against rotation-induced image motion.
        k = max(size, 50.0) / 100.0
        return self._meas_px * k + 0.3, self._accel * k

    @property
    def box(self) -> BoundingBox:
        s = self.kf.statePost[:, 0]
        return BoundingBox(float(s[0]), float(s[1]), max(float(s[2]), 1.0), max(float(s[3]), 1.0))

    @property
    def velocity(self) -> np.ndarray:
        return self.kf.statePost[4:, 0].copy()

    @property
    def centre_sigma(self) -> float:
        """Standard deviation (px) of the box centre, the larger axis: how far a prediction may have drifted."""
        p = self.kf.errorCovPost
        return math.sqrt(max(float(p[0, 0]), float(p[1, 1]), 0.0))

    def predict(self, dt: float) -> BoundingBox:
        dt = max(float(dt), 1e-3)
        f = np.eye(8)
        f[:4, 4:] = dt * np.eye(4)
        self.kf.transitionMatrix = f
        size = max(self.box.w, self.box.h)
        _, acc = self._noise(size)
        # Discrete white-noise acceleration model per coordinate.
        q1 = np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]]) * acc**2
        q = np.zeros((8, 8))
        for i in range(4):
            q[np.ix_([i, i + 4], [i, i + 4])] = q1
        self.kf.processNoiseCov = q
        s = self.kf.predict()
        # cv2 leaves statePost at the old value after predict(); copy so .box is the prediction.
        self.kf.statePost = s.copy()
        self.kf.errorCovPost = self.kf.errorCovPre.copy()
        return BoundingBox(float(s[0, 0]), float(s[1, 0]), max(float(s[2, 0]), 1.0), max(float(s[3, 0]), 1.0))

    def shift(self, du: float, dv: float) -> None:
        """Move the centre by (du, dv) px, velocity and uncertainty kept (the camera's own rotation, applied before
        :meth:`predict`: perception/derotate.py)."""
        self.kf.statePost[0, 0] += du
        self.kf.statePost[1, 0] += dv

    def correct(self, meas: BoundingBox) -> BoundingBox:
        r, _ = self._noise(max(meas.w, meas.h))
        self.kf.measurementNoiseCov = np.eye(4) * r**2
        self.kf.statePre = self.kf.statePost.copy()
        self.kf.errorCovPre = self.kf.errorCovPost.copy()
        self.kf.correct(np.array([[meas.cx], [meas.cy], [meas.w], [meas.h]], dtype=np.float64))
        return self.box


class NanoTracker:
    """cv2.TrackerNano (NanoTrack) with the two ONNX files checked up front."""

    def __init__(self, backbone: str | Path, neckhead: str | Path) -> None:
        for key, p in (("nanotrack_backbone", backbone), ("nanotrack_neckhead", neckhead)):
            if not p or not Path(p).is_file():
                raise TrackerError(f"perception.{key}: {p or '<empty>'}: NanoTrack model file not found")
        params = cv2.TrackerNano_Params()
        params.backbone = str(backbone)
        params.neckhead = str(neckhead)
        try:
            self._params = params
            self._tracker = cv2.TrackerNano_create(params)
        except cv2.error as e:
            msg = str(e).strip().splitlines()[-1] if str(e).strip() else "cv2.error"
            raise TrackerError(
                f"perception.nanotrack_*: {backbone}, {neckhead}: cannot load NanoTrack ({msg})"
            ) from None
        self.active = False

    def init(self, frame: np.ndarray, box: BoundingBox) -> None:
        x0, y0, _, _ = box.xyxy
        self._tracker = cv2.TrackerNano_create(self._params)  # a fresh state per (re)initialisation
        self._tracker.init(frame, (round(x0), round(y0), max(round(box.w), 2), max(round(box.h), 2)))
        self.active = True

    def update(self, frame: np.ndarray, t: float = 0.0) -> tuple[BoundingBox | None, float]:
        if not self.active:
            return None, 0.0
        ok, rect = self._tracker.update(frame)
        score = float(self._tracker.getTrackingScore())
        if not ok:
            return None, score
        x, y, w, h = rect
        return BoundingBox(x + w / 2.0, y + h / 2.0, float(w), float(h), score, t), score
