"""Tracker pieces (Kalman box, association, NanoTrack checks) and the pipeline policy."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from companion.config import load_config
from companion.config_perception import PerceptionConfig
from companion.configbase import ConfigError
from perception.bench import sweep_frames
from perception.detector import SHIPPED_MODEL, Detector
from perception.pipeline import Pipeline
from perception.tracker import BoxKalman, NanoTracker, TrackerError, associate, iou
from perception.types import BoundingBox

FRAME = np.zeros((480, 640, 3), np.uint8)


class ScriptedDetector:
    """Stands in for the ONNX detector where the policy is under test: returns given boxes per frame."""

    # One detect() a frame: an input that takes the 640x480 frame unshrunk, so the pipeline never zooms
    # (perception/zoom.py; tested in test_zoom.py with the real detector).
    input_hw = (640, 640)

    def __init__(self, script: list[list[BoundingBox]]) -> None:
        self.script = script
        self.k = 0
        self.last_ms = 0.0

    def detect(self, image: np.ndarray, t: float = 0.0) -> list[BoundingBox]:
        out = self.script[self.k] if self.k < len(self.script) else []
        self.k += 1
        return out


def B(cx: float, cy: float, w: float = 40.0, h: float = 40.0, c: float = 0.9) -> BoundingBox:
    return BoundingBox(cx, cy, w, h, c)


def test_iou_and_association() -> None:
    a = B(100, 100)
    assert iou(a, a) == pytest.approx(1.0)
    assert iou(a, B(120, 100)) == pytest.approx(20 * 40 / (2 * 1600 - 20 * 40))
    assert iou(a, B(300, 100)) == 0.0
    best, rejected = associate(a, [B(400, 400), B(110, 104, c=0.5), B(104, 100, c=0.9)], 50.0, 0.05)
    assert (best.cx, best.cy) == (104, 100) and rejected == 1
    # no overlap but within the jump radius (50 px + half the diagonal): still the same target
    best, rejected = associate(a, [B(175, 100)], 50.0, 0.05)
    assert best is not None and rejected == 0
    assert associate(a, [B(200, 300)], 50.0, 0.05) == (None, 1)


def test_kalman_smooths_and_predicts() -> None:
    rng = np.random.default_rng(3)
    kf = BoxKalman(B(100, 200, 50, 50), smoothing=0.5)
    dt, v = 1 / 30, np.array([60.0, -30.0])  # px/s
    raw_err, filt_err = [], []
    for k in range(1, 90):
        true = np.array([100, 200]) + v * k * dt
        kf.predict(dt)
        meas = true + rng.normal(0, 3.0, 2)
        out = kf.correct(B(meas[0], meas[1], 50 + rng.normal(0, 3), 50 + rng.normal(0, 3)))
        if k > 30:
            raw_err.append(np.linalg.norm(meas - true))
            filt_err.append(np.linalg.norm([out.cx - true[0], out.cy - true[1]]))
    assert np.mean(filt_err) < 0.7 * np.mean(raw_err)
    assert kf.velocity[:2] == pytest.approx(v, abs=15.0)
    # Through a miss the prediction continues along the estimated velocity.
    before = kf.box
    pred = kf.predict(0.2)
    assert (pred.cx, pred.cy) == pytest.approx((before.cx + 0.2 * kf.velocity[0], before.cy + 0.2 * kf.velocity[1]))


def test_nanotrack_needs_its_two_files(tmp_path: Path) -> None:
    msg = r"perception\.nanotrack_backbone: .*nope\.onnx: NanoTrack model file not found"
    with pytest.raises(TrackerError, match=msg):
        NanoTracker(tmp_path / "nope.onnx", tmp_path / "nh.onnx")
    junk = tmp_path / "bb.onnx"
    junk.write_bytes(b"\x08\x07junk" * 100)
    with pytest.raises(TrackerError, match=r"perception\.nanotrack_neckhead: <empty>"):
        NanoTracker(junk, "")
    with pytest.raises(TrackerError) as ei:
        NanoTracker(junk, junk)  # files exist but are not NanoTrack models
    assert "cannot load NanoTrack" in str(ei.value) and "\n" not in str(ei.value)
    # the config refuses the nanotrack tracker without its files, naming the key
    with pytest.raises(ConfigError, match="nanotrack needs nanotrack_backbone and nanotrack_neckhead"):
        load_config(overrides=["perception.tracker=nanotrack"])


def _pipe(script: list[list[BoundingBox]], **kw) -> Pipeline:
    pc = PerceptionConfig(**kw)
    return Pipeline(ScriptedDetector(script), pc, 640, 480)  # type: ignore[arg-type]


def test_acquire_needs_consistent_detections_and_rejects_jumps() -> None:
    script = [
        [B(100, 100)],  # single false alarm...
        [B(500, 400)],  # ...then the target, twice in a row: acquired on the second
        [B(502, 400)],
        [B(504, 400)],
        [B(100, 60), B(506, 400)],  # a far distractor next to the target: target kept
        [B(100, 60)],  # only the far distractor: a jump, rejected -> coast
        [B(510, 400)],
    ]
    p = _pipe(script, confirm_frames=2, coast_time=0.3, acquire_confidence=1.0)  # the confirm rule alone
    outs = [p.process(FRAME, k / 30) for k in range(len(script))]
    assert outs[0] is None and outs[1] is None
    assert outs[2] is not None and outs[2].cx == pytest.approx(502, abs=1e-6)
    for o in outs[3:]:
        assert o is not None and abs(o.cx - 505) < 8 and abs(o.cy - 400) < 5
    assert p.stats.rejected_jumps == 2 and p.stats.coasted == 1 and p.stats.acquisitions == 1
    assert outs[5].confidence < outs[4].confidence  # a coasted box says it is a prediction


def test_coast_then_lose_then_reacquire() -> None:
    track = [[B(300 + 3 * k, 200)] for k in range(10)]
    gap = [[] for _ in range(12)]  # 0.4 s of nothing: longer than coast_time
    new = [[B(100, 300)] for _ in range(4)]
    p = _pipe(track + gap + new, confirm_frames=2, coast_time=0.2, acquire_confidence=1.0)  # confirm rule alone
    outs = [p.process(FRAME, k / 30) for k in range(len(track + gap + new))]
    coasted = [o for o in outs[10:22] if o is not None]
    # coasting continues the motion at ~90 px/s for up to 0.2 s (6 frames), then the target is lost
    assert 5 <= len(coasted) <= 7
    assert coasted[-1].cx > outs[9].cx + 5
    assert all(o is None for o in outs[10 + len(coasted):22])
    assert outs[22] is None and outs[23] is not None and outs[23].cx == pytest.approx(100, abs=1e-6)
    assert p.stats.losses == 1 and p.stats.acquisitions == 2


def test_a_confident_detection_acquires_on_its_own_frame() -> None:
    script = [
        [B(100, 100, c=0.45)],  # weak: waits for a second agreeing detection ...
        [B(102, 100, c=0.45)],  # ... acquired here
        [],
        [],
        [],
        [],
        [],
        [],
        [],
        [],
        [],
        [],  # lost (coast 0.3 s)
        [B(400, 300, c=0.7)],  # confident: acquired on its first frame
        [B(402, 300, c=0.7)],
    ]
    # memory_time 0: the new target is 360 px from the lost one 0.37 s later, which the memory of the lost track
    # (tests/perception/test_consistency.py) would hold back; this test is about confident acquisition alone
    p = _pipe(script, confirm_frames=2, coast_time=0.3, acquire_confidence=0.5, memory_time=0.0)
    outs = [p.process(FRAME, k / 30) for k in range(len(script))]
    assert outs[0] is None and outs[1] is not None and outs[1].cx == pytest.approx(102, abs=1e-6)
    assert outs[11] is None
    assert outs[12] is not None and outs[12].cx == pytest.approx(400, abs=1e-6)
    assert p.stats.acquisitions == 2 and p.stats.losses == 1
    # the same confident detection with the rule off (1.0) waits for confirm_frames
    p = _pipe(script[12:], confirm_frames=2, acquire_confidence=1.0)
    assert p.process(FRAME, 0.0) is None and p.process(FRAME, 1 / 30) is not None


def test_an_uncertain_prediction_is_no_box_but_keeps_the_track() -> None:
    # a gate moving steadily, one missed frame, then the gate again
    script = [[B(300 + 6 * k, 200, 60, 60)] for k in range(6)] + [[]] + [[B(342, 200, 60, 60)]]
    # 30 fps: the prediction over 33 ms is certain enough: a coasted box
    p = _pipe(script, confirm_frames=2, coast_time=0.3)
    outs = [p.process(FRAME, k / 30) for k in range(len(script))]
    assert outs[6] is not None and p.stats.coasted == 1
    # 5 Hz: the same miss spans 0.2 s; the centre's uncertainty exceeds a quarter of the box: no box, ...
    p = _pipe(script, confirm_frames=2, coast_time=0.3)
    outs = [p.process(FRAME, k / 5) for k in range(len(script))]
    assert outs[5] is not None and outs[6] is None and p.stats.coasted == 0 and p.stats.unconfident == 1
    # ... but the track survives: the next detection continues it (no new acquisition)
    assert outs[7] is not None and abs(outs[7].cx - 342) < 5 and p.stats.acquisitions == 1 and p.stats.losses == 0


def test_kalman_centre_uncertainty_grows_with_the_gap() -> None:
    kf = BoxKalman(B(300, 200, 60, 60), smoothing=0.3)
    for k in range(5):
        kf.predict(1 / 30)
        kf.correct(B(300 + k, 200, 60, 60))
    s0 = kf.centre_sigma
    kf.predict(1 / 30)
    s1 = kf.centre_sigma
    kf.predict(0.3)
    assert 0 < s0 < s1 < kf.centre_sigma


def test_box_smoothing_reduces_jitter() -> None:
    rng = np.random.default_rng(0)
    noisy = [[B(320 + rng.normal(0, 4), 240 + rng.normal(0, 4), 80 + rng.normal(0, 4), 80)] for _ in range(120)]
    p = _pipe(noisy, smoothing=0.5)
    outs = [p.process(FRAME, k / 30) for k in range(120)]
    raw = np.array([s[0].cx for s in noisy[40:]])
    filt = np.array([o.cx for o in outs[40:]])
    assert np.std(filt - 320) < 0.6 * np.std(raw - 320)
    p0 = _pipe(noisy, smoothing=0.0)
    outs0 = [p0.process(FRAME, k / 30) for k in range(120)]
    assert np.std([o.cx for o in outs0[40:]]) > np.std(filt)  # the knob does something


def test_pipeline_with_shipped_detector_tracks_rendered_gate() -> None:
    """Real detector on a rendered approach: box on the gate (IoU >= 0.5) in most frames after acquisition."""
    det = Detector(SHIPPED_MODEL, "gate")
    frames = sweep_frames(60, seed=3)
    p = Pipeline(det, PerceptionConfig(), 640, 480)
    good = boxed = 0
    centre_err = []
    for t, img, truth in frames:
        box = p.process(img, t)
        if box is not None and truth is not None:
            boxed += 1
            good += iou(box, truth) >= 0.5
            centre_err.append(math.hypot(box.cx - truth.cx, box.cy - truth.cy))
    assert boxed >= 50
    assert good / boxed >= 0.9
    assert np.median(centre_err) < 4.0
    s = p.stats.summary()
    assert s["frames"] == 60 and s["detector_runs"] == 60 and s["boxes"] == boxed
