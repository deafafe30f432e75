#!/usr/bin/env python3
"""Convert the TII "Race Against the Machine" drone-racing dataset into the YOLO layout of this project.

The dataset (github.com/tii-racing/drone-racing-dataset, README: "licensed under CC BY 4.0", by TII Racing
Jetsetters; scripts MIT) is real Arducam frames of square racing gates (fast flight, multiple light
settings) with a box and four corner keypoints per gate. Its images are in the repository's release assets,
not in its git tree: download them with that repository's ``data_downloader.sh`` first (this tool downloads
nothing). Layout read here:

    SRC/{autonomous,piloted}/flight-NAME/camera_flight-NAME/*.jpg
    SRC/{autonomous,piloted}/flight-NAME/label(s)_flight-NAME/*.txt   "0 cx cy w h tlx tly tlv ... blv"

Output (what ``companion perception eval`` and ``tools/train_detector.py --finetune`` read): the first five
columns of each label line (``0 cx cy w h``, the box clipped to the image); an empty label file stays a
gate-free frame; a frame without a label file is left out. ``--every N`` keeps every N-th frame of a flight
(a high-frame-rate camera: neighbours are near-duplicates); ``--sequences`` writes each flight as
``OUT/sequences/FLIGHT`` (time order) for the tracker measures instead of one flat ``OUT/images``.

    tools/convert_tii_labels.py SRC OUT --every 30 [--flights 'flight-0*'] [--sequences]

Attribution when frames or a model trained on them are shared: "Race Against the Machine" dataset, TII
Racing Jetsetters, CC BY 4.0 (Bosello et al., IEEE RA-L 2024).
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path


def convert_line(line: str) -> str | None:
    """One TII label line -> ``0 cx cy w h`` (box clipped to 0..1), None for an empty or degenerate box."""
    parts = line.split()
    if len(parts) < 5:
        return None
    cx, cy, w, h = (float(v) for v in parts[1:5])
    x0, y0 = max(cx - w / 2, 0.0), max(cy - h / 2, 0.0)
    x1, y1 = min(cx + w / 2, 1.0), min(cy + h / 2, 1.0)
    if x1 - x0 <= 0 or y1 - y0 <= 0:
        return None
    return f"0 {(x0 + x1) / 2:.6f} {(y0 + y1) / 2:.6f} {x1 - x0:.6f} {y1 - y0:.6f}"


def flights(src: Path, pattern: str) -> list[Path]:
    return sorted(p for p in src.glob(f"*/{pattern}") if p.is_dir() and p.name.startswith("flight-"))


def convert(src: Path, out: Path, every: int = 1, pattern: str = "flight-*",
            sequences: bool = False) -> dict[str, int]:
    counts = {"flights": 0, "frames": 0, "gates": 0, "gate_free": 0, "unlabelled": 0}
    for fl in flights(src, pattern):
        cams = sorted(fl.glob("camera_" + fl.name))
        labs = sorted(fl.glob("label*_" + fl.name))
        if not cams or not labs:
            continue
        dest = out / "sequences" / fl.name if sequences else out
        (dest / "images").mkdir(parents=True, exist_ok=True)
        (dest / "labels").mkdir(parents=True, exist_ok=True)
        counts["flights"] += 1
        for img in sorted(cams[0].glob("*.jpg"))[::max(every, 1)]:
            lab = labs[0] / (img.stem + ".txt")
            stem = img.stem if sequences else f"{fl.name}_{img.stem}"
            if not lab.is_file():
                counts["unlabelled"] += 1
                if sequences:  # tracked through, not scored
                    shutil.copy(img, dest / "images" / f"{stem}.jpg")
                continue
            lines = [c for c in (convert_line(line) for line in lab.read_text().splitlines()) if c]
            shutil.copy(img, dest / "images" / f"{stem}.jpg")
            (dest / "labels" / f"{stem}.txt").write_text("".join(line + "\n" for line in lines))
            counts["frames"] += 1
            counts["gates"] += len(lines)
            counts["gate_free"] += int(not lines)
    return counts


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("src", type=Path, help="the dataset's data/ folder (autonomous/, piloted/)")
    p.add_argument("out", type=Path, help="DATASET folder to write (YOLO layout)")
    p.add_argument("--every", type=int, default=30, help="keep every N-th frame of a flight")
    p.add_argument("--flights", default="flight-*", help="glob of the flight folders to take")
    p.add_argument("--sequences", action="store_true", help="write OUT/sequences/FLIGHT (for tracker measures)")
    a = p.parse_args(argv)
    counts = convert(a.src, a.out, a.every, a.flights, a.sequences)
    if not counts["flights"]:
        print(f"convert_tii_labels: {a.src}: no flight-*/camera_flight-* + labels_flight-* folders", file=sys.stderr)
        return 2
    print(counts)
    return 0


if __name__ == "__main__":
    sys.exit(main())
