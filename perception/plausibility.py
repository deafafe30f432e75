"""Plausibility at perception's two boundaries: camera frames coming in, detector candidates going out.

Nothing here repairs data. An implausible frame is a camera fault (``FrameFault``, one line saying
what); an implausible detector candidate is dropped before NMS, so it can neither become a box nor
cost time.

Frames (``FrameChecker``):
* shape, dtype and channels must be the configured camera's (``camera.width`` x ``camera.height``,
  BGR uint8): the intrinsics the LOS uses are only right for that image;
* the capture time must be finite, strictly increasing (the controller differences the LOS over
  it: a repeat is a division by zero, a step back is a negative rate), not in the future and
  not older than ``max_age`` (the attitude at capture time would be a guess). A forward jump
  either lands in the future (refused) or closes a gap of dropped frames (not a fault here:
  the flight's watchdog owns stalls);
* frozen content: a stream that repeats one image with fresh timestamps (a hung driver that
  re-sends its last buffer) is the dangerous fault: the box stays put while the vehicle turns,
  which PN reads as LOS rate and answers with ever larger demands (the probe: pitch -86 deg at
  thrust 0.1 within ~1 s). Rule: byte-identical content (sampled on a 4-pixel grid) for longer
  than ``frozen_timeout`` and at least ``FROZEN_MIN_FRAMES`` frames. Why identical and not "similar":
  a real sensor's frames always differ by noise, even of a static scene, while a re-sent buffer is
  identical to the bit; a video with duplicated frames (frame-rate conversion) repeats one frame
  once or twice, well under the timeout. Why a timeout and not the first repeat: a compressed
  stream of a truly static view may repeat a frame now and then, and 0.3 s is a third of the
  time the probe needed to dive.

Detector candidates (``plausible_candidates``): non-finite coordinates or scores, scores outside
[0, 1], non-positive or absurd sizes, absurd aspect ratios and boxes wholly outside the model input
are dropped; then at most ``MAX_CANDIDATES`` (best score first) go to NMS, whose cost grows with the
square of its input (200k candidates took 2.9 s per frame).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MAX_CANDIDATES = 1000  # NMS input cap (Ultralytics caps at 30000 for 80 classes; one class needs far fewer)
MAX_ASPECT = 8.0  # a ring seen at a grazing angle, or cut by the image edge, stays well inside this
MAX_SIZE_FACTOR = 4.0  # a box may exceed the input (a gate closer than the view), not by this much
FROZEN_MIN_FRAMES = 3  # identical frames in a row, besides the timeout, before "frozen"
FUTURE_TOLERANCE = 0.05  # s: a capture time this far ahead of the app's clock is a broken clock


class FrameFault(ValueError):
    """An implausible camera frame: one line saying what (the flight names it CAMERA_FAILED)."""


@dataclass
class FrameChecker:
    """Checks every frame of one camera stream (see the module doc for the rules)."""

    width: int
    height: int
    frozen_timeout: float = 0.3
    max_age: float = 1.0
    _last_t: float | None = None
    _sample: np.ndarray | None = None
    _same_since: float | None = None
    _same_frames: int = 0

    def check(self, t: float, image: np.ndarray | None, now: float) -> None:
        """Raise FrameFault if the frame captured at ``t`` (app clock; ``now`` = read time) is implausible."""
        self._check_time(t, now)
        if image is not None:
            self._check_image(image)
            self._check_frozen(t, image)
        self._last_t = t

    def _check_time(self, t: float, now: float) -> None:
        if not math.isfinite(t):
            raise FrameFault(f"frame timestamp is not finite ({t})")
        if t > now + FUTURE_TOLERANCE:
            raise FrameFault(f"frame timestamp {t - now:.3f} s in the future (camera clock is not the app's)")
        if now - t > self.max_age:
            raise FrameFault(f"frame is {now - t:.2f} s old (limit {self.max_age:.2f} s)")
        if self._last_t is None:
            return
        if t == self._last_t:
            raise FrameFault(f"frame timestamp did not advance (t = {t:.3f} s twice)")
        if t < self._last_t:
            raise FrameFault(f"frame timestamp went back {self._last_t - t:.3f} s")

    def _check_image(self, image: np.ndarray) -> None:
        want = (self.height, self.width, 3)
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.shape != want:
            got = (f"{'x'.join(map(str, image.shape))} {image.dtype}" if isinstance(image, np.ndarray)
                   else type(image).__name__)
            raise FrameFault(f"frame is {got}, expected {want[0]}x{want[1]}x3 uint8 (camera.height x camera.width, "
                             "BGR)")

    def _check_frozen(self, t: float, image: np.ndarray) -> None:
        sample = image[::4, ::4]  # a view: the copy below is 1/16 of the frame
        if self._sample is not None and np.array_equal(sample, self._sample):
            self._same_frames += 1
            assert self._same_since is not None
            frozen_for = t - self._same_since
            if self._same_frames >= FROZEN_MIN_FRAMES and frozen_for > self.frozen_timeout:
                raise FrameFault(f"camera frozen: {self._same_frames + 1} identical frames over {frozen_for:.2f} s "
                                 f"(limit {self.frozen_timeout:.2f} s)")
            return
        self._sample = sample.copy()
        self._same_since, self._same_frames = t, 0


def plausible_candidates(xywh: np.ndarray, scores: np.ndarray, input_hw: tuple[int, int],
                         max_candidates: int = MAX_CANDIDATES) -> tuple[np.ndarray, np.ndarray]:
    """Detector candidates (centre x, centre y, w, h in model-input pixels; score) that make sense, best
    ``max_candidates`` by score. Returns (xywh, scores) as float64, possibly empty."""
    b = np.asarray(xywh, dtype=np.float64).reshape(-1, 4)
    s = np.asarray(scores, dtype=np.float64).reshape(-1)
    H, W = input_hw
    with np.errstate(invalid="ignore", divide="ignore"):
        w, h = b[:, 2], b[:, 3]
        ok = np.isfinite(b).all(axis=1) & np.isfinite(s) & (s >= 0.0) & (s <= 1.0)
        ok &= (w > 0) & (h > 0) & (w <= MAX_SIZE_FACTOR * W) & (h <= MAX_SIZE_FACTOR * H)
        ok &= np.maximum(w / h, h / w) <= MAX_ASPECT
        # Wholly outside the model input (the letterboxed image lies inside it): nothing there to see.
        ok &= (b[:, 0] + w / 2 > 0) & (b[:, 0] - w / 2 < W) & (b[:, 1] + h / 2 > 0) & (b[:, 1] - h / 2 < H)
    b, s = b[ok], s[ok]
    if len(s) > max_candidates:
        top = np.argpartition(-s, max_candidates - 1)[:max_candidates]
        b, s = b[top], s[top]
    return b, s
