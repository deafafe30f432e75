"""tools/convert_tii_labels.py and tools/make_washington_eval_set.py on hand-made files in their layouts."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))

from convert_tii_labels import convert_line, main
from make_washington_eval_set import build

from perception.evaluate import load_dataset


def _yolo(path: Path) -> list[list[float]]:
    return [[float(v) for v in line.split()] for line in path.read_text().splitlines()]


def _tii_tree(root: Path) -> None:
    fl = root / "autonomous" / "flight-01a-ellipse"
    cam, lab = fl / "camera_flight-01a-ellipse", fl / "labels_flight-01a-ellipse"
    cam.mkdir(parents=True)
    lab.mkdir(parents=True)
    for n in range(4):
        cv2.imwrite(str(cam / f"0000{n}_169175615{n}.jpg"), np.zeros((48, 64, 3), np.uint8))
    kp = " 0.3 0.3 2 0.5 0.3 2 0.5 0.5 2 0.3 0.5 2"
    (lab / "00000_1691756150.txt").write_text("0 0.4 0.4 0.3 0.3" + kp + "\n0 0.95 0.5 0.2 0.4" + kp + "\n")
    (lab / "00001_1691756151.txt").write_text("")  # gate-free
    (lab / "00002_1691756152.txt").write_text("0 0.5 0.5 0.1 0.1" + kp + "\n")
    # 00003: no label file -> unlabelled


def test_tii_line_keeps_the_box_clipped() -> None:
    line = "0 0.4 0.4 0.3 0.3 0.3 0.3 2 0.5 0.3 2 0.5 0.5 2 0.3 0.5 2"
    assert convert_line(line) == "0 0.400000 0.400000 0.300000 0.300000"
    # cut by the right border: x 0.85..1.05 -> 0.85..1.0
    assert [float(v) for v in convert_line("0 0.95 0.5 0.2 0.4").split()] == pytest.approx([0, 0.925, 0.5, 0.15, 0.4])
    assert convert_line("0 0.5 0.5 0 0.1") is None
    assert convert_line("") is None


def test_tii_tree_to_yolo_layout(tmp_path: Path) -> None:
    _tii_tree(tmp_path / "data")
    out = tmp_path / "ds"
    assert main([str(tmp_path / "data"), str(out), "--every", "1"]) == 0
    names = sorted(p.name for p in (out / "labels").iterdir())
    assert names == ["flight-01a-ellipse_00000_1691756150.txt", "flight-01a-ellipse_00001_1691756151.txt",
                     "flight-01a-ellipse_00002_1691756152.txt"]
    assert len(_yolo(out / "labels" / names[0])) == 2
    assert (out / "labels" / names[1]).read_text() == ""
    ds = load_dataset(out)  # what companion perception eval and --finetune read
    assert len(ds.frames) == 3
    assert sum(len(f.boxes) for f in ds.frames) == 3
    # every 2nd frame, as a sequence: the unlabelled frame is kept (tracked through, not scored)
    seq = tmp_path / "seq"
    assert main([str(tmp_path / "data"), str(seq), "--every", "2", "--sequences"]) == 0
    s = load_dataset(seq).sequences["flight-01a-ellipse"]
    assert [f.boxes is not None for f in s] == [True, True]
    assert main([str(tmp_path / "nothing"), str(tmp_path / "x")]) == 2


def test_washington_box_is_the_panel_not_the_opening(tmp_path: Path) -> None:
    src = tmp_path / "WashingtonOBRace"
    src.mkdir()
    img = np.zeros((200, 200, 3), np.uint8)
    mask = np.zeros((200, 200), np.uint8)
    cv2.rectangle(mask, (40, 40), (159, 159), 255, -1)  # panel 40..159
    cv2.rectangle(mask, (60, 60), (139, 139), 0, -1)  # opening 60..139 (inner corners)
    cv2.rectangle(mask, (93, 93), (106, 106), 255, -1)  # a far gate seen through the opening: panel 93..106
    cv2.rectangle(mask, (95, 95), (104, 104), 0, -1)  # (1.4x its opening, as on the real set)
    cv2.imwrite(str(src / "img_1.png"), img)
    cv2.imwrite(str(src / "mask_1.png"), mask)
    (src / "corners.csv").write_text("img_1.png,60,60,140,60,140,140,60,140\nimg_1.png,95,95,105,95,105,105,95,105\n")
    assert build(src, tmp_path / "ds") == {"frames": 1, "gates": 2, "no_mask": 0}
    near, far = _yolo(tmp_path / "ds" / "labels" / "washington_img_1.txt")
    assert near == pytest.approx([0, 0.5, 0.5, 0.6, 0.6], abs=1e-6)  # 40..160 of 200
    assert far == pytest.approx([0, 0.5, 0.5, 0.07, 0.07], abs=1e-6)  # 93..107: not the near panel
