"""``companion perception eval DATASET``: the detector and the tracker on labelled real frames.

DATASET is a YOLO-layout folder:

    DATASET/images/NAME.jpg|png       frames
    DATASET/labels/NAME.txt           ``0 cx cy w h`` per gate (normalised); an EMPTY file = a gate-free frame;
                                      a frame without a label file is not evaluated (unlabelled)
    DATASET/sequences/SEQ/images|labels   optional: frames of one flight in time order (sorted names)

Frames (detector alone, IoU 0.5 at the configured confidence): recall and precision overall and by gate
size (box width as a fraction of the image width: small < 0.1, medium < 0.3, large < 0.6, huge >= 0.6),
median centre error of the hits, false boxes per gate-free frame, and a contact sheet of the worst frames.

Sequences (detector + tracker, ``perception.pipeline.Pipeline`` as in flight, frames at ``--fps``): on
frames where a gate is visible, the share where the output box is on the gate (its centre inside the
gate's box), on a wrong target, or absent; switches from the gate (or nothing) to a wrong target; time to
re-acquire the gate after it is lost while visible; and boxes output on gate-free frames.

``corner labels`` (four clicked corners per gate) are converted with tools/convert_corner_labels.py.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from perception.types import BoundingBox

IMAGE_EXT = (".jpg", ".jpeg", ".png", ".bmp")
SIZE_BINS = (("small", 0.1), ("medium", 0.3), ("large", 0.6), ("huge", math.inf))
IOU_HIT = 0.5


class DatasetError(ValueError):
    """A dataset that cannot be read, as one line naming the file."""


@dataclass(frozen=True)
class LabelledFrame:
    image: Path
    boxes: np.ndarray | None  # (K, 4) xyxy pixels; K = 0: gate-free; None: unlabelled (sequences only)
    width: int
    height: int


@dataclass
class Dataset:
    root: Path
    frames: list[LabelledFrame] = field(default_factory=list)
    sequences: dict[str, list[LabelledFrame]] = field(default_factory=dict)


def _read_labels(path: Path, w: int, h: int) -> np.ndarray:
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        parts = line.split()
        if not parts:
            continue
        try:
            vals = [float(v) for v in parts]
        except ValueError:
            raise DatasetError(f"{path}:{n}: YOLO label must be 'class cx cy w h' numbers, got {line!r}") from None
        if len(vals) != 5 or not all(math.isfinite(v) for v in vals):
            raise DatasetError(f"{path}:{n}: YOLO label must be 'class cx cy w h', got {line!r}")
        _, cx, cy, bw, bh = vals
        if bw <= 0 or bh <= 0:
            raise DatasetError(f"{path}:{n}: box width/height must be > 0, got {line!r}")
        rows.append(((cx - bw / 2) * w, (cy - bh / 2) * h, (cx + bw / 2) * w, (cy + bh / 2) * h))
    return np.array(rows, float).reshape(-1, 4)


def _load_folder(folder: Path, keep_unlabelled: bool = False) -> list[LabelledFrame]:
    images = sorted(p for p in (folder / "images").iterdir() if p.suffix.lower() in IMAGE_EXT)
    out = []
    for img in images:
        lab = folder / "labels" / (img.stem + ".txt")
        if not lab.is_file() and not keep_unlabelled:
            continue  # unlabelled: neither a gate nor a gate-free frame
        im = cv2.imread(str(img), cv2.IMREAD_COLOR)
        if im is None:
            raise DatasetError(f"{img}: cannot read the image")
        h, w = im.shape[:2]
        out.append(LabelledFrame(img, _read_labels(lab, w, h) if lab.is_file() else None, w, h))
    return out


def load_dataset(root: str | Path) -> Dataset:
    root = Path(root)
    if not (root / "images").is_dir() and not (root / "sequences").is_dir():
        raise DatasetError(f"{root}: not a dataset (needs images/ + labels/ and/or sequences/SEQ/images + labels)")
    ds = Dataset(root)
    if (root / "images").is_dir():
        ds.frames = _load_folder(root)
    if (root / "sequences").is_dir():
        for seq in sorted(p for p in (root / "sequences").iterdir() if (p / "images").is_dir()):
            ds.sequences[seq.name] = _load_folder(seq, keep_unlabelled=True)  # tracked through, not scored
    if not ds.frames and not any(f.boxes is not None for s in ds.sequences.values() for f in s):
        raise DatasetError(f"{root}: no labelled frames (each image needs labels/NAME.txt)")
    return ds


def _iou_xyxy(a: np.ndarray, b: np.ndarray) -> float:
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iw * ih
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def match(dets: list[BoundingBox], gts: np.ndarray, iou_min: float = IOU_HIT) -> tuple[list[int], list[int]]:
    """Greedy best-confidence-first matching. Returns (gt index hit by each det or -1, det index per gt or -1)."""
    det_to_gt = [-1] * len(dets)
    gt_to_det = [-1] * len(gts)
    for i in sorted(range(len(dets)), key=lambda k: -dets[k].confidence):
        d = np.array(dets[i].xyxy)
        best, best_iou = -1, iou_min
        for j, g in enumerate(gts):
            if gt_to_det[j] >= 0:
                continue
            v = _iou_xyxy(d, g)
            if v >= best_iou:
                best, best_iou = j, v
        if best >= 0:
            det_to_gt[i], gt_to_det[best] = best, i
    return det_to_gt, gt_to_det


def size_bin(box: np.ndarray, width: int) -> str:
    frac = (box[2] - box[0]) / max(width, 1)
    return next(name for name, hi in SIZE_BINS if frac < hi)


def evaluate_frames(detector: Any, frames: list[LabelledFrame], worst: int = 24) -> tuple[dict, list]:
    """Detector metrics on single frames, and the worst frames (for the contact sheet)."""
    tp = fp = n_gt = 0
    by = {name: [0, 0] for name, _ in SIZE_BINS}
    centre, fp_free, n_free = [], 0, 0
    scored = []
    for fr in frames:
        img = cv2.imread(str(fr.image), cv2.IMREAD_COLOR)
        dets = detector.detect(img)
        d2g, g2d = match(dets, fr.boxes)
        hits = sum(1 for j in g2d if j >= 0)
        false = [dets[i] for i, j in enumerate(d2g) if j < 0]
        tp += hits
        fp += len(false)
        n_gt += len(fr.boxes)
        for j, g in enumerate(fr.boxes):
            b = by[size_bin(g, fr.width)]
            b[1] += 1
            if g2d[j] >= 0:
                b[0] += 1
                d = dets[g2d[j]]
                centre.append(math.hypot(d.cx - (g[0] + g[2]) / 2, d.cy - (g[1] + g[3]) / 2))
        if len(fr.boxes) == 0:
            n_free += 1
            fp_free += len(false)
        badness = (len(fr.boxes) - hits) + sum(d.confidence for d in false)
        if badness > 0:
            scored.append((badness, fr, dets, d2g))
    scored.sort(key=lambda s: -s[0])
    report = {
        "frames": len(frames), "gates": n_gt, "gate_free_frames": n_free,
        "recall": round(tp / n_gt, 4) if n_gt else None,
        "precision": round(tp / (tp + fp), 4) if tp + fp else None,
        "recall_by_size": {k: (round(h / t, 4) if t else None) for k, (h, t) in by.items()},
        "gates_by_size": {k: t for k, (_, t) in by.items()},
        "median_centre_error_px": round(float(np.median(centre)), 2) if centre else None,
        "false_boxes_per_gate_free_frame": round(fp_free / n_free, 4) if n_free else None,
        "false_boxes": fp, "confidence": float(getattr(detector, "conf", float("nan"))), "iou": IOU_HIT,
    }
    return report, scored[:worst]


def _on_target(box: BoundingBox, gts: np.ndarray) -> bool:
    return any(g[0] <= box.cx <= g[2] and g[1] <= box.cy <= g[3] for g in gts)


def evaluate_sequence(pipeline: Any, frames: list[LabelledFrame], fps: float) -> dict:
    """Run the tracking pipeline over one sequence; count frames on / off the gate, switches, re-acquisition."""
    pipeline.reset()
    visible = on = wrong = absent = switches = false_free = 0
    state = "none"  # what the output was on the previous frame: on / wrong / none
    lost_at: int | None = None
    reacq: list[float] = []
    for k, fr in enumerate(frames):
        img = cv2.imread(str(fr.image), cv2.IMREAD_COLOR)
        box = pipeline.process(img, k / fps)
        if fr.boxes is None:  # unlabelled (e.g. an unchecked "no gate" flag): tracked through, not scored
            continue
        has_gate = len(fr.boxes) > 0
        if box is None:
            now = "none"
        elif has_gate and _on_target(box, fr.boxes):
            now = "on"
        else:
            now = "wrong"
        if has_gate:
            visible += 1
            on += now == "on"
            wrong += now == "wrong"
            absent += now == "none"
            if now != "on" and lost_at is None and state == "on":
                lost_at = k
            if now == "on" and lost_at is not None:
                reacq.append((k - lost_at) / fps)
                lost_at = None
        else:
            false_free += now != "none"
            lost_at = None  # the gate left the view: nothing to re-acquire
        if has_gate and now == "wrong" and state != "wrong":  # boxes on gate-free frames are counted apart
            switches += 1
        state = now
    return {
        "frames": len(frames), "gate_visible_frames": visible,
        "on_gate": round(on / visible, 4) if visible else None,
        "on_wrong_target": round(wrong / visible, 4) if visible else None,
        "no_box": round(absent / visible, 4) if visible else None,
        "switches_to_wrong": switches,
        "boxes_on_gate_free_frames": false_free,
        "reacquire_s_median": round(float(np.median(reacq)), 3) if reacq else None,
        "reacquire_s_max": round(float(np.max(reacq)), 3) if reacq else None,
        "losses_not_reacquired": int(lost_at is not None),
    }


def contact_sheet(worst: list, path: Path, cols: int = 6, tile_w: int = 320) -> None:
    """The worst frames: labels green, detections that hit blue, false ones red (with confidence)."""
    tiles = []
    for badness, fr, dets, d2g in worst:
        img = cv2.imread(str(fr.image), cv2.IMREAD_COLOR)
        for g in fr.boxes:
            cv2.rectangle(img, (int(g[0]), int(g[1])), (int(g[2]), int(g[3])), (0, 220, 0), 2)
        for d, j in zip(dets, d2g, strict=True):
            x0, y0, x1, y1 = (int(v) for v in d.xyxy)
            col = (255, 120, 0) if j >= 0 else (0, 0, 255)
            cv2.rectangle(img, (x0, y0), (x1, y1), col, 2)
            cv2.putText(img, f"{d.confidence:.2f}", (x0, max(y0 - 3, 10)), cv2.FONT_HERSHEY_SIMPLEX, 0.45, col, 1)
        s = tile_w / img.shape[1]
        img = cv2.resize(img, (tile_w, max(int(img.shape[0] * s), 1)))
        cv2.putText(img, f"{fr.image.name[:30]} {badness:.2f}", (3, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (255, 255, 255), 1)
        tiles.append(img)
    if not tiles:
        tiles = [np.full((60, tile_w, 3), 255, np.uint8)]
        cv2.putText(tiles[0], "no misses, no false boxes", (5, 35), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
    th = max(t.shape[0] for t in tiles)
    tiles = [cv2.copyMakeBorder(t, 0, th - t.shape[0], 0, 0, cv2.BORDER_CONSTANT, value=(0, 0, 0)) for t in tiles]
    while len(tiles) % cols and len(tiles) > cols:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.hstack(tiles[i:i + cols]) for i in range(0, len(tiles), cols)]
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.vstack(rows))


def run(dataset: str | Path, cfg: Any, out: Path, fps: float, worst: int = 24) -> dict:
    from perception.detector import Detector
    from perception.pipeline import Pipeline

    ds = load_dataset(dataset)
    det = Detector.from_config(cfg.perception)
    report: dict[str, Any] = {"dataset": str(ds.root), "model": str(det.path)}
    if ds.frames:
        report["frames"], bad = evaluate_frames(det, ds.frames, worst)
        contact_sheet(bad, out / "worst.png")
        report["contact_sheet"] = str(out / "worst.png")
    seqs = {}
    for name, frames in ds.sequences.items():
        if not frames:
            continue
        w, h = frames[0].width, frames[0].height
        pipe = Pipeline(det, cfg.perception, w, h)
        seqs[name] = evaluate_sequence(pipe, frames, fps)
    if seqs:
        vis = sum(s["gate_visible_frames"] for s in seqs.values())
        on = sum((s["on_gate"] or 0) * s["gate_visible_frames"] for s in seqs.values())
        wrong = sum((s["on_wrong_target"] or 0) * s["gate_visible_frames"] for s in seqs.values())
        report["tracking"] = {
            "sequences": len(seqs), "gate_visible_frames": vis,
            "on_gate": round(on / vis, 4) if vis else None,
            "on_wrong_target": round(wrong / vis, 4) if vis else None,
            "switches_to_wrong": sum(s["switches_to_wrong"] for s in seqs.values()),
            "boxes_on_gate_free_frames": sum(s["boxes_on_gate_free_frames"] for s in seqs.values()),
            "per_sequence": seqs,
        }
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    return report


def format_report(r: dict) -> str:
    lines = [f"model {r['model']}", f"dataset {r['dataset']}"]
    f = r.get("frames")
    if f:
        lines.append(f"frames {f['frames']} (gates {f['gates']}, gate-free {f['gate_free_frames']}), "
                     f"IoU {f['iou']}, confidence {f['confidence']}")
        lines.append(f"  recall {f['recall']}  precision {f['precision']}  "
                     f"false boxes per gate-free frame {f['false_boxes_per_gate_free_frame']}  "
                     f"median centre error {f['median_centre_error_px']} px")
        lines.append("  recall by size (width / image width): " + ", ".join(
            f"{k} {v} (n {f['gates_by_size'][k]})" for k, v in f["recall_by_size"].items()))
        lines.append(f"  worst frames: {r['contact_sheet']}")
    t = r.get("tracking")
    if t:
        lines.append(f"tracking {t['sequences']} sequences, gate visible in {t['gate_visible_frames']} frames: "
                     f"on gate {t['on_gate']}, on a wrong target {t['on_wrong_target']}, "
                     f"switches to wrong {t['switches_to_wrong']}, boxes on gate-free frames "
                     f"{t['boxes_on_gate_free_frames']}")
        for name, s in t["per_sequence"].items():
            lines.append(f"  {name}: visible {s['gate_visible_frames']}, on gate {s['on_gate']}, wrong "
                         f"{s['on_wrong_target']}, none {s['no_box']}, switches {s['switches_to_wrong']}, "
                         f"re-acquire median {s['reacquire_s_median']} s max {s['reacquire_s_max']} s")
    return "\n".join(lines)


def _cmd(args: argparse.Namespace) -> int:
    from companion.config import config_from_args
    from perception.detector import DetectorError

    cfg = config_from_args(args)
    try:
        r = run(args.dataset, cfg, Path(args.out), args.fps, args.worst)
    except (DatasetError, DetectorError) as e:
        print(f"companion perception eval: {e}", file=sys.stderr)
        return 2
    print(format_report(r))
    print(f"wrote {Path(args.out) / 'report.json'}")
    return 0


def register(subparsers: Any) -> None:
    from companion.config import add_config_arguments

    grp = subparsers.add_parser("perception", help="perception tools (evaluation on labelled real frames)")
    sub = grp.add_subparsers(dest="perception_command", required=True, metavar="TOOL")
    p = sub.add_parser(
        "eval", help="detector + tracker metrics on a labelled YOLO-layout dataset",
        description=__doc__.split("\n\n")[0] + " Layout and metrics: perception/evaluate.py, docs/perception.md.",
    )
    p.add_argument("dataset", help="YOLO-layout folder: images/, labels/ (empty file = gate-free), sequences/")
    p.add_argument("--out", default="perception-eval", help="folder for report.json and worst.png")
    p.add_argument("--fps", type=float, default=30.0, help="frame rate of the sequences (their time step)")
    p.add_argument("--worst", type=int, default=24, help="frames on the contact sheet")
    add_config_arguments(p)
    p.set_defaults(func=_cmd)
