#!/usr/bin/env python3
"""Build a second real-frame evaluation set from the WashingtonOBRace frames (evaluation only).

WashingtonOBRace (the TU Delft AE4317 course set: 308 frames, 360 px high, of printed AIRR panel gates in a
hall, ``img_N.png`` + ``mask_N.png`` + ``corners.csv``) has no licence stated where it is found
(Sunyouh/ae4317_individual_assignment, commit fd98a27, folder ``WashingtonOBRace/``): it is used to MEASURE,
never to train, and stays outside this repository.

``corners.csv`` holds the INNER corners of each gate's opening; the gate's box (the box of its pixels, as in
the dev set and the training frames) is the outer edge of the printed panel. It is taken from the gate mask:
the mask pixels inside the inner quadrilateral scaled by ``OUTER_SEARCH`` about its centre (on this set the
panel's outer box is 1.38-1.46x the inner box, median 1.40), clipped to the image.

    tools/make_washington_eval_set.py SRC OUT     # SRC: the WashingtonOBRace folder; OUT: YOLO layout

Every frame holds at least one labelled gate (no gate-free frames). Caveat: a far gate that was not labelled
(no corners, no mask) counts as a false box when the detector finds it.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import cv2
import numpy as np

OUTER_SEARCH = 1.7
RIM = 1.15


def gate_box(mask: np.ndarray, comps: np.ndarray, inner: np.ndarray) -> tuple[float, float, float, float] | None:
    """Pixel box (x0, y0, x1, y1) of the gate whose opening has the (4, 2) inner corners: the mask components
    that touch the rim just outside the opening, within the opening scaled by OUTER_SEARCH (so a far gate
    seen through a near one does not take in the near gate's panel)."""
    c = inner.mean(axis=0)

    def poly(scale: float) -> np.ndarray:
        r = np.zeros(mask.shape, np.uint8)
        cv2.fillPoly(r, [np.round(c + (inner - c) * scale).astype(np.int32)], 1)
        return r > 0

    ids = np.unique(comps[poly(RIM) & ~poly(1.0) & (mask > 0)])
    ids = ids[ids > 0]
    if len(ids) == 0:
        return None
    ys, xs = np.nonzero(np.isin(comps, ids) & poly(OUTER_SEARCH))
    if len(xs) < 10:
        return None
    return float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1)


def build(src: Path, out: Path) -> dict[str, int]:
    labels: dict[str, list[np.ndarray]] = {}
    with (src / "corners.csv").open(newline="") as f:
        for row in csv.reader(f):
            if row:
                labels.setdefault(row[0], []).append(np.array(row[1:9], float).reshape(4, 2))
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "labels").mkdir(parents=True, exist_ok=True)
    counts = {"frames": 0, "gates": 0, "no_mask": 0}
    for name, quads in sorted(labels.items()):
        img = cv2.imread(str(src / name), cv2.IMREAD_COLOR)
        mask = cv2.imread(str(src / name.replace("img_", "mask_")), cv2.IMREAD_GRAYSCALE)
        if img is None or mask is None:
            continue
        h, w = img.shape[:2]
        m = (mask > 127).astype(np.uint8)
        _, comps = cv2.connectedComponents(m)
        lines = []
        for q in quads:
            b = gate_box(m, comps, q)
            if b is None:
                counts["no_mask"] += 1
                continue
            x0, y0, x1, y1 = b
            lines.append(f"0 {(x0 + x1) / 2 / w:.6f} {(y0 + y1) / 2 / h:.6f} {(x1 - x0) / w:.6f} {(y1 - y0) / h:.6f}")
        stem = f"washington_{Path(name).stem}"
        cv2.imwrite(str(out / "images" / f"{stem}.jpg"), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
        (out / "labels" / f"{stem}.txt").write_text("".join(line + "\n" for line in lines))
        counts["frames"] += 1
        counts["gates"] += len(lines)
    return counts


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("src", type=Path, help="the WashingtonOBRace folder (img_N.png, mask_N.png, corners.csv)")
    p.add_argument("out", type=Path, help="evaluation set folder to write (YOLO layout)")
    a = p.parse_args()
    if not (a.src / "corners.csv").is_file():
        print(f"make_washington_eval_set: {a.src}: no corners.csv", file=sys.stderr)
        return 2
    print(build(a.src, a.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
