#!/usr/bin/env python3
"""Convert gate corner labels into the YOLO layout that ``companion perception eval`` reads.

Output layout (DATASET):

    DATASET/images/NAME.jpg     the frame (rotated if asked)
    DATASET/labels/NAME.txt     one line per gate: ``0 cx cy w h`` normalised to 0..1; EMPTY = gate-free frame

Input, one of:

* ``--csv FILE``: a CSV with a header ``image,x1,y1,x2,y2,x3,y3,x4,y4`` (pixels of the image as stored);
  several rows for one image are several gates; a row with empty corners marks a gate-free frame.
* ``--mat FILE``: the MATLAB layout of shuoli-robotics/gate_detection (``GT_gate``: one row per existing
  ``img_NNNNN.jpg`` in index order, ``flag, x1..x4, y1..y4``, flag 0 = no gate), labelled on frames rotated
  by 90 deg (``imrotate(RGB, 90)``): use ``--rotate ccw``.

The box of a gate is the box of its corners, clipped to the image. ``--exclude NAMES`` (a file, one image
name a line) drops frames that were checked by eye and found mislabelled (e.g. "no gate" flags on frames
that show one). ``--prefix`` names the frames (sequence name) so several sources can share one DATASET.

    tools/convert_corner_labels.py --mat GT_basement.mat --images basement --rotate ccw --first-index 1 \\
        --by-index --out /work/data/percep/dev --prefix basement
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import cv2
import numpy as np

ROTATIONS = {"none": None, "ccw": cv2.ROTATE_90_COUNTERCLOCKWISE, "cw": cv2.ROTATE_90_CLOCKWISE}


class LabelError(ValueError):
    """A label file that cannot be converted, as one line naming the file and row."""


def corners_to_yolo(corners: np.ndarray, width: int, height: int) -> tuple[float, float, float, float] | None:
    """(4, 2) pixel corners -> normalised (cx, cy, w, h) of their box clipped to the image, None if empty."""
    c = np.asarray(corners, float).reshape(-1, 2)
    if not np.isfinite(c).all():
        return None
    x0, y0 = max(float(c[:, 0].min()), 0.0), max(float(c[:, 1].min()), 0.0)
    x1, y1 = min(float(c[:, 0].max()), float(width)), min(float(c[:, 1].max()), float(height))
    if x1 - x0 < 1.0 or y1 - y0 < 1.0:
        return None
    return ((x0 + x1) / 2 / width, (y0 + y1) / 2 / height, (x1 - x0) / width, (y1 - y0) / height)


def read_csv_labels(path: Path) -> dict[str, list[np.ndarray]]:
    """image name -> list of (4, 2) corner arrays (empty list: gate-free frame)."""
    out: dict[str, list[np.ndarray]] = {}
    with path.open(newline="") as f:
        rows = csv.DictReader(f)
        need = ["image"] + [f"{a}{i}" for i in range(1, 5) for a in "xy"]
        missing = [k for k in need if k not in (rows.fieldnames or [])]
        if missing:
            raise LabelError(f"{path}: header lacks {', '.join(missing)} (need {','.join(need)})")
        for n, row in enumerate(rows, start=2):
            name = (row["image"] or "").strip()
            if not name:
                raise LabelError(f"{path}:{n}: empty image name")
            vals = [(row[f"{a}{i}"] or "").strip() for a in "xy" for i in range(1, 5)]
            out.setdefault(name, [])
            if not any(vals):
                continue  # gate-free frame
            try:
                xs = [float(row[f"x{i}"]) for i in range(1, 5)]
                ys = [float(row[f"y{i}"]) for i in range(1, 5)]
            except (TypeError, ValueError):
                raise LabelError(f"{path}:{n}: corners must be 8 numbers or all empty, got {vals}") from None
            out[name].append(np.stack([xs, ys], axis=1))
    return out


def read_mat_labels(path: Path, images: Path, first_index: int, by_index: bool = False) -> dict[str, list[np.ndarray]]:
    """shuoli-robotics/gate_detection ``GT_gate``: row k is the k-th existing img_NNNNN.jpg from first_index,
    or (``by_index``: frames deleted after labelling) img number first_index + k."""
    import scipy.io

    gt = np.asarray(scipy.io.loadmat(str(path))["GT_gate"], float)
    if gt.ndim != 2 or gt.shape[1] != 9:
        raise LabelError(f"{path}: GT_gate must be N x 9 (flag, x1..x4, y1..y4), got {gt.shape}")
    files = sorted(images.glob("img_*.jpg"), key=lambda p: int(p.stem.split("_")[1]))
    files = [p for p in files if int(p.stem.split("_")[1]) >= first_index]
    if by_index:
        files = [images / f"img_{first_index + k:05d}.jpg" for k in range(len(gt))]
    out: dict[str, list[np.ndarray]] = {}
    for row, p in zip(gt, files, strict=False):
        out[p.name] = [np.stack([row[1:5], row[5:9]], axis=1)] if row[0] == 1 else []
    return out


def convert(labels: dict[str, list[np.ndarray]], images: Path, out: Path, rotate: str = "none",
            prefix: str = "", exclude: set[str] | None = None) -> dict[str, int]:
    """Write DATASET/images + labels; returns counts (frames, gates, gate_free, excluded, missing)."""
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "labels").mkdir(parents=True, exist_ok=True)
    counts = {"frames": 0, "gates": 0, "gate_free": 0, "excluded": 0, "missing": 0}
    exclude = exclude or set()
    for name, gates in sorted(labels.items()):
        if name in exclude:
            counts["excluded"] += 1
            continue
        img = cv2.imread(str(images / name), cv2.IMREAD_COLOR)
        if img is None:
            counts["missing"] += 1
            continue
        if ROTATIONS[rotate] is not None:
            img = cv2.rotate(img, ROTATIONS[rotate])
        h, w = img.shape[:2]
        stem = f"{prefix}_{Path(name).stem}" if prefix else Path(name).stem
        lines = []
        for c in gates:
            b = corners_to_yolo(c, w, h)
            if b is not None:
                lines.append("0 " + " ".join(f"{v:.6f}" for v in b))
        cv2.imwrite(str(out / "images" / f"{stem}.jpg"), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
        (out / "labels" / f"{stem}.txt").write_text("".join(line + "\n" for line in lines))
        counts["frames"] += 1
        counts["gates"] += len(lines)
        counts["gate_free"] += int(not lines)
    return counts


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--csv", type=Path, help="CSV: image,x1,y1,x2,y2,x3,y3,x4,y4")
    src.add_argument("--mat", type=Path, help="MATLAB GT_gate file (shuoli-robotics/gate_detection layout)")
    p.add_argument("--images", type=Path, required=True, help="folder of the labelled images")
    p.add_argument("--out", type=Path, required=True, help="DATASET folder (images/, labels/) to write into")
    p.add_argument("--rotate", choices=sorted(ROTATIONS), default="none",
                   help="rotate each frame (labels are taken in the rotated frame)")
    p.add_argument("--first-index", type=int, default=0, help="--mat: index of the first labelled img_NNNNN.jpg")
    p.add_argument("--by-index", action="store_true",
                   help="--mat: row k labels img number first-index + k (frames deleted after labelling)")
    p.add_argument("--prefix", default="", help="prefix of the written names (e.g. the sequence name)")
    p.add_argument("--exclude", type=Path, default=None, help="file of image names to leave out (checked by eye)")
    args = p.parse_args(argv)
    if not args.images.is_dir():
        print(f"convert: --images {args.images}: not a folder", file=sys.stderr)
        return 2
    try:
        if args.csv:
            labels = read_csv_labels(args.csv)
        else:
            labels = read_mat_labels(args.mat, args.images, args.first_index, args.by_index)
        exclude = set(args.exclude.read_text().split()) if args.exclude else set()
    except (LabelError, OSError, KeyError) as e:
        print(f"convert: {e}", file=sys.stderr)
        return 2
    counts = convert(labels, args.images, args.out, args.rotate, args.prefix, exclude)
    print(" ".join(f"{k} {v}" for k, v in counts.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
