#!/usr/bin/env python3
"""Build the real-frame development set from a checkout of shuoli-robotics/gate_detection (evaluation only).

That repository states no licence: its frames are used to MEASURE, never to train, and stay outside this
repository. Its corner labels are converted with tools/convert_corner_labels.py. Its "no gate" flags are
unreliable (many such frames show a gate, whole, cut by the border or far away), so only frames checked by
eye here are used as gate-free frames; the other "no gate" frames are left unlabelled (not scored) in the
sequences and left out of the frame set.

    tools/make_gate_dev_set.py SRC OUT        # SRC: the repository's files; OUT: the YOLO-layout dev set

OUT/images + labels: every labelled gate frame + the checked gate-free frames; OUT/sequences/{cyberzoo,
basement}: the flights' frames in order (5 Hz snapshots: evaluate with ``--fps 5``).

The repository keeps the basement flight's frames in two folders whose names differ only in case, ``basement/``
and ``Basement/`` (images 00111-00148, 32 labelled: one folder on its authors' Windows). Both are read; before
2026-12-07 only ``basement/`` was, and every real-video figure up to then is on 459 basement frames, not 491.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from convert_corner_labels import convert, read_mat_labels

# Checked by eye at full size (2026-11-27): these "no gate" frames show no gate, pole or gate edge.
CHECKED_GATE_FREE = {
    "cyberzoo": "00006 00022 00028 00034 00037 00045 00058 00079 00083 00086 00095 00098 00101 00108 00113 00124 "
                "00127 00130 00133 00136 00149 00159 00200 00206 00210 00236 00245 00248 00254 00257 00260 00291 "
                "00294 00297 00321 00324 00346 00358 00361 00371 00376 00386 00405 00408 00422 00426 00436 00461 "
                "00464 00473 00500 00510 00524 00529 00545",
    "basement": "00017 00021 00071 00075 00079 00083 00087 00091 00095 00125 00160 00216 00220 00224 00228 00243 "
                "00247 00251 00255 00285 00289 00293 00297 00344 00348 00352 00356 00360 00364 00368 00372 00394 "
                "00398 00417 00421 00425 00429",
}
# (sequence, label file, image folder, first index, rows by image number)
SOURCES = (
    ("cyberzoo", "2018_2_2_ground_truth_gate_selection.mat", "pic_cyberzoo", 0, False),
    ("basement", "GT_basement.mat", "basement", 1, True),
)
_FIT = "fit_distance_with_gate_area"
EXTRA = (("czdist", f"{_FIT}/4_16_cyberzoo_dis.mat", f"{_FIT}/cyberzoo_distance", 0, False),)


def image_folder(src: Path, images: str, tmp: Path) -> Path:
    """``src/images``, or when the repository splits it over folders whose names differ only in case (basement/
    and Basement/), their files together in a folder under ``tmp``."""
    parent = (src / images).parent
    name = Path(images).name
    same = sorted(d for d in parent.iterdir() if d.is_dir() and d.name.lower() == name.lower())
    if len(same) <= 1:
        return src / images
    merged = tmp / "merged" / name
    merged.mkdir(parents=True)
    for d in same:
        for f in d.iterdir():
            if f.is_file() and not (merged / f.name).exists():
                shutil.copy(f, merged / f.name)
    return merged


def build(src: Path, out: Path) -> dict[str, dict[str, int]]:
    counts = {}
    for name, mat, images, first, by_index in SOURCES + EXTRA:
        with tempfile.TemporaryDirectory() as tmp:
            t = Path(tmp)
            folder = image_folder(src, images, t)
            labels = read_mat_labels(src / mat, folder, first, by_index)
            counts[name] = convert(labels, folder, t, "ccw", prefix=name)
            checked = {f"{name}_img_{n}" for n in CHECKED_GATE_FREE.get(name, "").split()}
            seq = out / "sequences" / name
            if name in CHECKED_GATE_FREE:
                (seq / "images").mkdir(parents=True, exist_ok=True)
                (seq / "labels").mkdir(parents=True, exist_ok=True)
            (out / "images").mkdir(parents=True, exist_ok=True)
            (out / "labels").mkdir(parents=True, exist_ok=True)
            for img in sorted((t / "images").iterdir()):
                lab = t / "labels" / (img.stem + ".txt")
                gate = lab.stat().st_size > 0
                labelled = gate or img.stem in checked
                if labelled:
                    shutil.copy(img, out / "images" / img.name)
                    shutil.copy(lab, out / "labels" / lab.name)
                if name in CHECKED_GATE_FREE:
                    shutil.copy(img, seq / "images" / img.name)
                    if labelled:
                        shutil.copy(lab, seq / "labels" / lab.name)
    return counts


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("src", type=Path, help="files of shuoli-robotics/gate_detection")
    p.add_argument("out", type=Path, help="dev set folder to write (YOLO layout)")
    a = p.parse_args()
    if not (a.src / "GT_basement.mat").is_file():
        print(f"make_gate_dev_set: {a.src}: not a checkout of shuoli-robotics/gate_detection", file=sys.stderr)
        return 2
    for k, v in build(a.src, a.out).items():
        print(k, v)
    return 0


if __name__ == "__main__":
    sys.exit(main())
