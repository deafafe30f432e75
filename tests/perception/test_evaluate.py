"""`companion perception eval` on tiny labelled sets written here, with answers known in advance."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.cli import main as cli_main
from perception.evaluate import DatasetError, load_dataset, match, size_bin
from perception.render import TRAIN_STYLE, Gate, PinholeCamera, look_at, render_gate_frame
from perception.types import BoundingBox
from tests.perception.onnx_fixtures import constant_yolo_model


def _write(root: Path, name: str, img: np.ndarray, boxes_xyxy: list[tuple[float, float, float, float]] | None) -> None:
    """One frame in YOLO layout; boxes None = no label file (unlabelled), [] = gate-free (empty file)."""
    (root / "images").mkdir(parents=True, exist_ok=True)
    (root / "labels").mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(root / "images" / f"{name}.png"), img)
    if boxes_xyxy is None:
        return
    h, w = img.shape[:2]
    lines = [f"0 {(x0 + x1) / 2 / w} {(y0 + y1) / 2 / h} {(x1 - x0) / w} {(y1 - y0) / h}\n"
             for x0, y0, x1, y1 in boxes_xyxy]
    (root / "labels" / f"{name}.txt").write_text("".join(lines))


def test_eval_counts_with_a_model_of_known_output(tmp_path: Path) -> None:
    """A real ONNX model that always answers one box at (16..48, 8..40), conf 0.9, through the real command."""
    out = np.zeros((1, 5, 8), np.float32)  # 8 anchors
    out[0, :, :] = np.array([5, 5, 2, 2, 0.01], np.float32)[:, None]  # below the confidence threshold: no box
    out[0, :, 0] = [32, 24, 32, 32, 0.9]  # cx, cy, w, h (input px), score
    model = constant_yolo_model(tmp_path / "const.onnx", out)
    ds = tmp_path / "ds"
    grey = np.full((64, 64, 3), 128, np.uint8)
    _write(ds, "a_hit", grey, [(17, 9, 49, 41)])  # IoU with the model's box = 31*31 / (2*1024 - 961) ~ 0.88
    _write(ds, "b_miss", grey, [(0, 44, 20, 64)])  # gate elsewhere: a miss AND a false box
    _write(ds, "c_free", grey, [])  # gate-free: one false box
    _write(ds, "d_unlabelled", grey, None)  # no label file: not evaluated
    rep = tmp_path / "rep"
    rc = cli_main(["perception", "eval", str(ds), "--out", str(rep),
                   "--set", f"perception.model={model}", "--set", "perception.classes=[gate]"])
    assert rc == 0
    r = json.loads((rep / "report.json").read_text())["frames"]
    assert r["frames"] == 3 and r["gates"] == 2 and r["gate_free_frames"] == 1
    assert r["recall"] == pytest.approx(0.5)
    assert r["precision"] == pytest.approx(1 / 3, abs=1e-4)
    assert r["false_boxes_per_gate_free_frame"] == pytest.approx(1.0)
    assert r["median_centre_error_px"] == pytest.approx(math.hypot(1.0, 1.0), abs=0.01)
    # both gates are 20-32 px wide in a 64 px frame: "large" (0.3-0.6 of the width)
    assert r["gates_by_size"] == {"small": 0, "medium": 0, "large": 2, "huge": 0}
    sheet = cv2.imread(str(rep / "worst.png"))
    assert sheet is not None and sheet.shape[1] >= 320  # the two bad frames, tiled


def _approach(n: int) -> list[tuple[np.ndarray, BoundingBox | None]]:
    """A clean, large orange ring gate getting closer (easy for any gate detector)."""
    cam = PinholeCamera.default()
    rng = np.random.default_rng(0)
    R = look_at(np.zeros(3), np.array([1.0, 0.0, 0.0]))
    bg = np.full((480, 640, 3), 150, np.uint8)
    out = []
    for k in range(n):
        gate = Gate(np.array([9.0 - 0.5 * k, 0.3, 0.0]), np.array([1.0, 0.0, 0.0]), 1.0, "ring", (0, 90, 255), 0.2)
        out.append(render_gate_frame(cam, R, np.zeros(3), gate, TRAIN_STYLE, rng, background=bg))
    return out


def test_eval_real_detector_on_rendered_frames_and_a_sequence(tmp_path: Path) -> None:
    ds = tmp_path / "ds"
    frames = _approach(6)
    for k, (img, box) in enumerate(frames[:3]):
        _write(ds, f"g{k}", img, [box.xyxy])
    _write(ds, "free", np.full((480, 640, 3), 150, np.uint8), [])
    seq = ds / "sequences" / "approach"
    for k, (img, box) in enumerate(frames):
        _write(seq, f"f{k:02d}", img, [box.xyxy])
    _write(seq, "f99_free", np.full((480, 640, 3), 150, np.uint8), [])  # the gate has left the view
    rep = tmp_path / "rep"
    assert cli_main(["perception", "eval", str(ds), "--out", str(rep), "--fps", "30",
                     "--set", "perception.acquire_confidence=1.0"]) == 0
    r = json.loads((rep / "report.json").read_text())
    f, t = r["frames"], r["tracking"]
    assert f["recall"] == 1.0 and f["precision"] == 1.0 and f["false_boxes_per_gate_free_frame"] == 0.0
    assert f["median_centre_error_px"] < 5.0
    s = t["per_sequence"]["approach"]
    # confirm_frames = 2 (single-frame acquisition off): the first frame has no box, every later one is on the gate
    assert s["gate_visible_frames"] == 6 and s["on_gate"] == pytest.approx(5 / 6, abs=1e-3)
    assert s["on_wrong_target"] == 0.0 and s["switches_to_wrong"] == 0
    assert t["boxes_on_gate_free_frames"] <= 1  # at most a coasted box right after the gate left


def test_dataset_errors_are_one_line(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="not a dataset"):
        load_dataset(tmp_path)
    _write(tmp_path, "x", np.zeros((8, 8, 3), np.uint8), [])
    (tmp_path / "labels" / "x.txt").write_text("0 0.5 0.5 nan 0.2\n")
    with pytest.raises(DatasetError, match=r"x\.txt:1: YOLO label"):
        load_dataset(tmp_path)
    rc = cli_main(["perception", "eval", str(tmp_path / "nowhere")])
    assert rc == 2


def test_match_is_greedy_by_confidence_and_size_bins() -> None:
    gts = np.array([[0, 0, 10, 10], [100, 100, 140, 140]], float)
    dets = [BoundingBox(5, 5, 10, 10, 0.5), BoundingBox(6, 5, 10, 10, 0.9), BoundingBox(300, 300, 5, 5, 0.8)]
    d2g, g2d = match(dets, gts)
    assert d2g == [-1, 0, -1] and g2d == [1, -1]  # the more confident duplicate takes the gate
    assert [size_bin(np.array([0, 0, w, 1.0]), 100) for w in (5, 10, 29, 59, 60)] == [
        "small", "medium", "medium", "large", "huge"]


def test_a_shipped_model_by_file_name(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from companion.config_perception import PerceptionConfig
    from perception.detector import SHIPPED_MODEL, Detector, DetectorError

    monkeypatch.chdir(tmp_path)  # no such file here: the name is looked up in perception/models/
    assert Detector.from_config(PerceptionConfig(model=SHIPPED_MODEL.name)).path == SHIPPED_MODEL
    with pytest.raises(DetectorError, match=r"nope\.onnx"):
        Detector.from_config(PerceptionConfig(model="nope.onnx"))
