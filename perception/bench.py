"""Perception benchmark: ms per 640x480 frame for the detector, the tracker policy and the whole pipeline.

One core (``cv2.setNumThreads(1)``, onnxruntime with one intra-op thread), rendered frames of a
gate sweeping across the view while it approaches, so the tracker and the association run as in
flight. Speed is measured and reported, never asserted. Also reports the fraction of frames where
the pipeline's box overlaps the ground truth at IoU >= 0.5 (a sanity check that the timed work
was real work).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from perception.detector import Detector
from perception.render import TRAIN_STYLE, Gate, PinholeCamera, make_background, render_gate_frame
from perception.tracker import iou
from perception.types import BoundingBox


def sweep_frames(n: int, seed: int = 0, width: int = 640, height: int = 480,
                 fps: float = 30.0) -> list[tuple[float, np.ndarray, BoundingBox | None]]:
    """``n`` frames (t, BGR, truth) of a ring gate approaching from 25 m to 6 m while it sweeps sideways."""
    rng = np.random.default_rng(seed)
    cam = PinholeCamera.default(width, height)
    bg = make_background(width, height, rng, TRAIN_STYLE)
    R_wc = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    colour = (30, 60, 240)
    out = []
    for k in range(n):
        s = k / max(n - 1, 1)
        t = k / fps
        centre = np.array([25.0 - 19.0 * s, 3.0 * math.sin(2 * math.pi * s), 1.0 * math.cos(2 * math.pi * s)])
        gate = Gate(centre, np.array([1.0, 0.2, 0.0]), 1.0, "ring", colour, 0.15)
        img, box = render_gate_frame(cam, R_wc, np.zeros(3), gate, TRAIN_STYLE, rng, background=bg, t=t)
        out.append((t, img, box))
    return out


def _stat(x: list[float]) -> dict[str, float]:
    a = np.asarray(x, float)
    return {"median": round(float(np.median(a)), 3), "p95": round(float(np.percentile(a, 95)), 3)}


def _run(detector: Detector, frames: list, pc: Any) -> dict[str, Any]:
    from perception.pipeline import Pipeline

    det_ms = []
    for _, img, _ in frames:  # detector alone
        t0 = time.perf_counter()
        detector.detect(img)
        det_ms.append((time.perf_counter() - t0) * 1e3)
    pipe = Pipeline(detector, pc, frames[0][1].shape[1], frames[0][1].shape[0])
    tot_ms, trk_ms, good, truth_n = [], [], 0, 0
    for t, img, truth in frames:
        runs = len(pipe.stats.detector_ms)
        t0 = time.perf_counter()
        box = pipe.process(img, t)
        total = (time.perf_counter() - t0) * 1e3
        tot_ms.append(total)
        # policy + association + Kalman + clipping: the frame's detector time (whole frame and any zoomed crop,
        # perception/zoom.py) taken out
        inner = pipe.stats.detector_ms[-1] if len(pipe.stats.detector_ms) > runs else 0.0
        trk_ms.append(max(total - inner, 0.0))
        if truth is not None:
            truth_n += 1
            good += int(box is not None and iou(box, truth) >= 0.5)
    return {
        "detector_ms_per_frame": _stat(det_ms),
        "tracker_ms_per_frame": _stat(trk_ms),
        "pipeline_ms_per_frame": _stat(tot_ms),
        "iou50_fraction": round(good / max(truth_n, 1), 4),
        "pipeline_stats": pipe.stats.summary(),
    }


def bench_perception(frames: int = 90, model: str | Path | None = None, seed: int = 0,
                     backends: tuple[str, ...] = ("onnxruntime", "cv2"), pc: Any = None) -> dict[str, Any]:
    """Per-frame times (median, p95, ms) at 640x480 on one core, for each backend.

    ``pc`` is the perception config to time (model, input size, confidence, tracker rules: what ``--set
    perception.*`` chose), the defaults without one; ``model`` overrides its model. The headline figures are
    those of the first backend that loads: onnxruntime, which the default ``perception.backend: auto`` uses
    when installed; cv2.dnn otherwise.
    """
    from companion.config_perception import PerceptionConfig

    cv2.setNumThreads(1)
    pc = PerceptionConfig() if pc is None else pc
    if model is not None:
        pc = pc.model_copy(update={"model": str(model)})
    seq = sweep_frames(frames, seed)
    res: dict[str, Any] = {"frames": frames, "width": 640, "height": 480, "threads": 1,
                           "model": str(pc.model or "gate_detector.onnx"), "tracker": "detect+kalman", "backends": {}}
    for be in backends:
        try:
            det = Detector.from_config(pc.model_copy(update={"backend": be, "threads": 1}))
        except ValueError as e:  # onnxruntime not installed: report, don't fail
            res["backends"][be] = {"error": str(e)}
            continue
        res["model"] = str(det.path)
        for _, img, _ in seq[:5]:  # warm-up: first inferences allocate
            det.detect(img)
        res["input_size"] = list(det.input_hw)
        res["backends"][be] = _run(det, seq, pc)
    first = next((b for b in backends if "error" not in res["backends"].get(b, {"error": 1})), None)
    if first is not None:
        for k in ("detector_ms_per_frame", "tracker_ms_per_frame", "pipeline_ms_per_frame", "iou50_fraction"):
            res[k] = res["backends"][first][k]
        res["backend"] = first
    return res


if __name__ == "__main__":
    import json
    import sys

    print(json.dumps(bench_perception(int(sys.argv[1]) if len(sys.argv) > 1 else 90), indent=2))
