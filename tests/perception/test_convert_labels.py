"""tools/convert_corner_labels.py on hand-made corner labels."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))

from convert_corner_labels import corners_to_yolo, main


def _yolo(path: Path) -> list[list[float]]:
    return [[float(v) for v in line.split()] for line in path.read_text().splitlines()]


def test_csv_corners_to_yolo(tmp_path: Path) -> None:
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    for n in ("a.jpg", "b.jpg", "c.jpg"):
        cv2.imwrite(str(imgs / n), np.zeros((100, 200, 3), np.uint8))
    (tmp_path / "c.csv").write_text(
        "image,x1,y1,x2,y2,x3,y3,x4,y4\n"
        "a.jpg,20,10,60,12,58,50,22,48\n"  # a gate seen a little obliquely: box x 20..60, y 10..50
        "a.jpg,150,70,250,70,250,130,150,130\n"  # a second gate cut by the border: clipped to x <= 200, y <= 100
        "b.jpg,,,,,,,,\n"  # gate-free frame
    )
    out = tmp_path / "ds"
    assert main(["--csv", str(tmp_path / "c.csv"), "--images", str(imgs), "--out", str(out)]) == 0
    a = _yolo(out / "labels" / "a.txt")
    assert a[0] == pytest.approx([0, 40 / 200, 30 / 100, 40 / 200, 40 / 100], abs=1e-6)
    assert a[1] == pytest.approx([0, 175 / 200, 85 / 100, 50 / 200, 30 / 100], abs=1e-6)
    assert (out / "labels" / "b.txt").read_text() == ""  # gate-free: empty label file
    assert not (out / "labels" / "c.txt").exists()  # not in the CSV: unlabelled, not converted


def test_mat_corners_rotated_like_the_source(tmp_path: Path) -> None:
    """GT_gate rows (flag, x1..x4, y1..y4) clicked on frames rotated by 90 deg (MATLAB imrotate(RGB, 90))."""
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    raw = np.zeros((120, 60, 3), np.uint8)  # stored portrait: 60 wide, 120 high
    raw[10:20, 5:15] = 255  # a white patch; rotated ccw it lands at x 10..20, y 45..55 of the 120x60 frame
    for k in (1, 2, 4):  # img_00003 was deleted after labelling
        cv2.imwrite(str(imgs / f"img_{k:05d}.png"), raw)
        (imgs / f"img_{k:05d}.png").rename(imgs / f"img_{k:05d}.jpg")
    gt = np.array([
        [1, 10, 20, 20, 10, 45, 45, 55, 55],
        [0, 0, 0, 0, 0, 0, 0, 0, 0],
        [1, 1, 2, 2, 1, 1, 1, 2, 2],  # img_00003: missing file
        [1, 30, 50, 50, 30, 20, 20, 40, 40],
    ], float)
    scipy.io.savemat(str(tmp_path / "gt.mat"), {"GT_gate": gt})
    out = tmp_path / "ds"
    assert main(["--mat", str(tmp_path / "gt.mat"), "--images", str(imgs), "--out", str(out), "--rotate", "ccw",
                 "--first-index", "1", "--by-index", "--prefix", "s"]) == 0
    img = cv2.imread(str(out / "images" / "s_img_00001.jpg"))
    assert img.shape[:2] == (60, 120)
    ys, xs = np.nonzero(img[..., 0] > 128)
    assert (xs.min(), xs.max(), ys.min(), ys.max()) == pytest.approx((10, 19, 45, 54), abs=1)  # the label's box
    first = _yolo(out / "labels" / "s_img_00001.txt")[0]
    assert first == pytest.approx([0, 15 / 120, 50 / 60, 10 / 120, 10 / 60], abs=1e-6)
    assert (out / "labels" / "s_img_00002.txt").read_text() == ""
    fourth = _yolo(out / "labels" / "s_img_00004.txt")[0]
    assert fourth == pytest.approx([0, 40 / 120, 30 / 60, 20 / 120, 20 / 60], abs=1e-6)
    assert not (out / "labels" / "s_img_00003.txt").exists()


def test_bad_rows_are_one_line_and_boxes_clip(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "imgs").mkdir()
    (tmp_path / "c.csv").write_text("image,x1,y1,x2,y2,x3,y3,x4,y4\na.jpg,1,2,3,x,5,6,7,8\n")
    assert main(["--csv", str(tmp_path / "c.csv"), "--images", str(tmp_path / "imgs"), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "c.csv:2: corners must be 8 numbers" in err and err.count("\n") == 1
    assert corners_to_yolo(np.array([[-10, -10], [-5, -10], [-5, -5], [-10, -5]]), 100, 100) is None  # off-image


def test_finetune_on_a_yolo_folder_is_one_command(tmp_path: Path) -> None:
    """tools/train_detector.py --finetune DATASET: two steps from the shipped model, exported and loadable."""
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    import subprocess

    from perception.detector import Detector

    ds = tmp_path / "ds"
    (ds / "images").mkdir(parents=True)
    (ds / "labels").mkdir()
    img = np.full((240, 320, 3), 120, np.uint8)
    cv2.rectangle(img, (100, 60), (180, 140), (0, 90, 255), 8)
    cv2.imwrite(str(ds / "images" / "f.jpg"), img)
    (ds / "labels" / "f.txt").write_text("0 0.4375 0.4167 0.2625 0.35\n")
    out = tmp_path / "model"
    tool = Path(__file__).resolve().parents[2] / "tools" / "train_detector.py"
    r = subprocess.run([sys.executable, str(tool), "--finetune", str(ds), "--steps", "2", "--batch", "2", "--pool", "2",
                        "--eval-frames", "2", "--out", str(out)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "fine-tune: 1 frames" in r.stdout
    Detector(out / "gate_detector.onnx", "gate")  # a valid model in the shipped layout
