"""Detector: YOLOv8-layout decoding through letterbox, class filter, NMS, model validation, shipped model."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from onnx_fixtures import constant_yolo_model

from perception.detector import SHIPPED_MODEL, Detector, DetectorError, letterbox
from perception.render import TRAIN_STYLE, PinholeCamera, random_scene

BACKENDS = ["cv2"]
try:
    import onnxruntime  # noqa: F401

    BACKENDS.append("onnxruntime")
except ImportError:
    pass


def _raw(n: int = 8, nc: int = 2) -> np.ndarray:
    out = np.zeros((1, 4 + nc, n), np.float32)
    out[0, :4, :] = 5.0  # low-score filler anchors
    return out


def _iou(a, b) -> float:
    ax0, ay0, ax1, ay1 = a
    bx0, by0, bx1, by1 = b
    inter = max(0, min(ax1, bx1) - max(ax0, bx0)) * max(0, min(ay1, by1) - max(ay0, by0))
    return inter / ((ax1 - ax0) * (ay1 - ay0) + (bx1 - bx0) * (by1 - by0) - inter)


@pytest.mark.parametrize("backend", BACKENDS)
def test_decode_letterbox_class_filter_and_nms(tmp_path: Path, backend: str) -> None:
    out = _raw()
    out[0, :, 0] = [32, 32, 20, 10, 0.9, 0.1]  # gate, centre of the 64x64 input
    out[0, :, 1] = [33, 32, 20, 10, 0.7, 0.1]  # overlapping gate, lower score: removed by NMS
    out[0, :, 2] = [10, 20, 4, 4, 0.6, 0.8]  # best class is "car": not a gate
    out[0, :, 3] = [50, 40, 6, 8, 0.5, 0.0]  # second gate, bottom right
    out[0, :, 4] = [20, 20, 6, 6, 0.2, 0.0]  # below the confidence threshold
    path = constant_yolo_model(tmp_path / "m.onnx", out, metadata={"names": "{0: 'gate', 1: 'car'}"})
    det = Detector(path, "gate", conf=0.35, nms_iou=0.5, backend=backend)
    assert det.classes == ["gate", "car"] and det.input_hw == (64, 64)
    boxes = det.detect(np.zeros((480, 640, 3), np.uint8), t=1.5)
    # 640x480 -> 64x48, scale 0.1, padded 8 px top: image = (input - (0, 8)) / 0.1.
    assert len(boxes) == 2
    b0, b1 = boxes
    assert (b0.cx, b0.cy, b0.w, b0.h) == pytest.approx((320, 240, 200, 100), abs=1e-3)
    assert b0.confidence == pytest.approx(0.9, abs=1e-6) and b0.t == 1.5
    assert (b1.cx, b1.cy, b1.w, b1.h) == pytest.approx((500, 320, 60, 80), abs=1e-3)
    # The car detector of the same file: only the car.
    cars = Detector(path, "car", backend=backend).detect(np.zeros((480, 640, 3), np.uint8))
    assert len(cars) == 1 and (cars[0].cx, cars[0].cy) == pytest.approx((100, 120), abs=1e-3)


def test_letterbox_geometry() -> None:
    img = np.zeros((480, 640, 3), np.uint8)
    img[:, :320] = 255
    lb, s, dx, dy = letterbox(img, (320, 320))
    assert (s, dx, dy) == (0.5, 0, 40)
    assert lb[0, 0, 0] == 114 and lb[319, 0, 0] == 114  # pad rows
    assert lb[40, 0, 0] == 255 and lb[200, 300, 0] == 0


def test_class_list_from_sidecar_and_argument(tmp_path: Path) -> None:
    out = _raw(nc=3)
    out[0, :, 0] = [32, 32, 20, 10, 0.1, 0.1, 0.9]
    path = constant_yolo_model(tmp_path / "three.onnx", out)
    with pytest.raises(DetectorError, match=r"three\.onnx: model has 3 classes but no class list"):
        Detector(path, "gate")
    det = Detector(path, "ring", classes=["a", "b", "ring"])
    assert det.class_index == 2 and len(det.detect(np.zeros((64, 64, 3), np.uint8))) == 1
    (tmp_path / "three.json").write_text(json.dumps({"classes": ["x", "gate", "y"]}))
    assert Detector(path, "gate").class_index == 1


def test_bad_models_are_refused_with_one_line(tmp_path: Path) -> None:
    def refused(match: str, *args, **kw) -> None:
        with pytest.raises(DetectorError, match=match) as ei:
            Detector(*args, **kw)
        assert "\n" not in str(ei.value)

    refused(r"nope\.onnx: model file not found", tmp_path / "nope.onnx")
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    refused(r"junk\.onnx: (not an ONNX model|model does not load)", junk)
    cut = tmp_path / "cut.onnx"
    cut.write_bytes(SHIPPED_MODEL.read_bytes()[:100_000])  # a truncated download
    refused(r"cut\.onnx: (not an ONNX model|model does not load)", cut)
    gray = constant_yolo_model(tmp_path / "gray.onnx", _raw(nc=1), in_shape=(1, 1, 64, 64))
    refused(r"gray\.onnx: input 'images' is \[1, 1, 64, 64\], expected 1x3xHxW", gray)
    two = constant_yolo_model(tmp_path / "two.onnx", _raw(nc=2))
    refused(r"two\.onnx: output has 2 class scores but the class list has 1 names", two, "gate", classes=["gate"])
    refused(r"two\.onnx: class 'gate' not in the model's classes \['a', 'b'\]", two, "gate", classes=["a", "b"])
    refused(r"two\.onnx: input is 64x64, configured input size is 320x320", two, "a", 320, classes=["a", "b"])
    flat = constant_yolo_model(tmp_path / "flat.onnx", np.zeros((1, 8400, 5), np.float32))
    refused(r"flat\.onnx: output is \[1, 8400, 5\], looks transposed", flat)
    refused(r"backend must be 'auto', 'cv2' or 'onnxruntime'", two, "a", backend="tensorrt", classes=["a", "b"])


def test_shipped_model_metadata_and_size() -> None:
    meta = json.loads(SHIPPED_MODEL.with_suffix(".json").read_text())
    assert meta["classes"] == ["gate"]
    assert SHIPPED_MODEL.stat().st_size < 5e6
    det = Detector(SHIPPED_MODEL, "gate")
    assert det.input_hw == tuple(meta["input_size"])
    for key in ("heldout_frames", "heldout_style"):
        m = meta["metrics"][key]
        assert 0.0 <= m["precision"] <= 1.0 and 0.0 <= m["recall"] <= 1.0 and m["frames"] >= 100


def test_shipped_model_finds_rendered_gates() -> None:
    """Seeded frames, disjoint from training seeds: most gates of >= 24 px found at IoU 0.5.

    Only the training style: on the held-out style the shipped model is weak (recall ~0.12 in its JSON
    metrics), a known gap, not something to assert here.
    """
    det = Detector(SHIPPED_MODEL, "gate")
    cam = PinholeCamera.default()
    for style, min_recall in ((TRAIN_STYLE, 0.7),):
        rng = np.random.default_rng(4242)
        hits = gates = false = 0
        for _ in range(40):
            img, gt = random_scene(rng, cam, style, p_empty=0.0)
            if gt is None or max(gt.w, gt.h) < 24:  # the detector is not meant for tiny specks here
                continue
            gates += 1
            boxes = det.detect(img)
            ok = [b for b in boxes if _iou(b.xyxy, gt.xyxy) >= 0.5]
            hits += bool(ok)
            false += len(boxes) - len(ok[:1])
        assert gates >= 25
        assert hits / gates >= min_recall, f"{style.name}: recall {hits}/{gates}"
        assert false <= 0.3 * gates, f"{style.name}: {false} false boxes on {gates} frames"


@pytest.mark.skipif("onnxruntime" not in BACKENDS, reason="onnxruntime not installed")
def test_backends_agree_on_shipped_model() -> None:
    rng = np.random.default_rng(7)
    cam = PinholeCamera.default()
    a, b = Detector(SHIPPED_MODEL, "gate"), Detector(SHIPPED_MODEL, "gate", backend="onnxruntime")
    n = 0
    for _ in range(6):
        img, _gt = random_scene(rng, cam, TRAIN_STYLE, p_empty=0.0)
        da, db = a.detect(img), b.detect(img)
        if da and db:
            n += 1
            assert math.hypot(da[0].cx - db[0].cx, da[0].cy - db[0].cy) < 0.5
            assert da[0].confidence == pytest.approx(db[0].confidence, abs=1e-3)
    assert n >= 3


def test_shipped_model_copy_with_wrong_class_name(tmp_path: Path) -> None:
    p = tmp_path / "gd.onnx"
    shutil.copy(SHIPPED_MODEL, p)  # no sidecar: one-class model takes class_name
    assert Detector(p, "ring").classes == ["ring"]
    shutil.copy(SHIPPED_MODEL.with_suffix(".json"), tmp_path / "gd.json")
    with pytest.raises(DetectorError, match="class 'ring' not in the model's classes"):
        Detector(p, "ring")
