#!/usr/bin/env python3
"""Train the shipped gate detector on rendered frames and export it as a YOLOv8-layout ONNX file.

Dev-only: needs CPU PyTorch (``pip install torch==2.13.0``), never a runtime dependency.
Reproducible from ``--seed`` and ``--steps`` (rendering, init, batch order and the learning-rate
schedule all follow from them); ``--minutes`` instead times the first steps and fixes the step
count from the budget (printed, and recorded in the JSON, for a rerun with ``--steps``).

    .venv/bin/python tools/train_detector.py --minutes 30 --seed 1
    .venv/bin/python tools/train_detector.py --eval-only      # re-measure the shipped model (prints only)
    .venv/bin/python tools/train_detector.py --world real --init-onnx perception/models/gate_detector.onnx \
        --steps 3000 --threads 2 --out DIR                     # real-world frames (perception.realworld)
    .venv/bin/python tools/train_detector.py --finetune DATASET --steps 1500   # your labelled frames

``--finetune DATASET`` (YOLO layout: DATASET/images/*.jpg|png, DATASET/labels/*.txt, class 0 = gate, an
empty label file = a gate-free frame) starts from the shipped model (or ``--init-onnx``/``--resume``) and
mixes your frames (half of each batch, flipped and colour-jittered) with rendered real-world frames so the
detector keeps what it knew. It writes ./finetuned-detector/gate_detector.onnx (``--out`` to change);
check it with ``companion perception eval`` on frames you did NOT train on, then configure it
(``perception.model: finetuned-detector/gate_detector.onnx``).

Output (``--out``, default perception/models/): gate_detector.onnx (opset 17, input
``images`` 1x3x320x320 BGR->RGB /255 letterboxed, output [1, 4+nc, N] = cx, cy, w, h in input
pixels + class scores) and gate_detector.json (classes, input size, seed, steps, metrics).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from perception.detector import letterbox  # noqa: E402  (the detector's own: train and inference agree)
from perception.realworld import real_scene  # noqa: E402
from perception.render import HELDOUT_STYLE, TRAIN_STYLE, PinholeCamera, random_scene  # noqa: E402

INPUT = 320
STRIDES = (8, 16, 32)
PROBE = 40  # steps timed to turn --minutes into a step count
# Box sizes (max side, input px) each level is responsible for; overlapping so borderline sizes get both.
LEVEL_RANGES = ((0.0, 56.0), (36.0, 140.0), (100.0, 1e9))


def build_model(nc: int = 1):
    import torch
    from torch import nn

    def conv(ci, co, k=3, s=1):
        return nn.Sequential(nn.Conv2d(ci, co, k, s, k // 2, bias=False), nn.BatchNorm2d(co), nn.SiLU())

    class Block(nn.Module):  # residual bottleneck
        def __init__(self, c):
            super().__init__()
            self.a, self.b = conv(c, c // 2, 1), conv(c // 2, c, 3)

        def forward(self, x):
            return x + self.b(self.a(x))

    class Net(nn.Module):
        def __init__(self):
            super().__init__()
            self.nc = nc
            # Sized for ~175 M MACs at 320x320: the 3x3 convs at stride 4-8 dominate, so fusion is 1x1.
            self.stem = nn.Sequential(conv(3, 16, 3, 2), conv(16, 32, 3, 2))  # /4
            self.p3 = nn.Sequential(conv(32, 48, 3, 2), Block(48))  # /8
            self.p4 = nn.Sequential(conv(48, 64, 3, 2), Block(64), Block(64))  # /16
            self.p5 = nn.Sequential(conv(64, 96, 3, 2), Block(96), conv(96, 96, 3))  # /32
            self.up = nn.Upsample(scale_factor=2, mode="nearest")
            self.f4 = conv(96 + 64, 64, 1)
            self.f3 = conv(64 + 48, 48, 1)
            self.d4 = conv(48, 64, 3, 2)
            self.n4 = conv(64 + 64, 64, 1)
            self.d5 = conv(64, 96, 3, 2)
            self.n5 = conv(96 + 96, 96, 1)
            self.heads = nn.ModuleList(
                nn.Sequential(conv(c, h, 3), nn.Conv2d(h, 4 + nc, 1)) for c, h in ((48, 32), (64, 64), (96, 96))
            )
            for h in self.heads:  # prior: few cells hold an object
                nn.init.constant_(h[-1].bias[4:], -4.0)
                nn.init.zeros_(h[-1].bias[:4])

        def raw(self, x):
            x = self.stem(x)
            c3 = self.p3(x)
            c4 = self.p4(c3)
            c5 = self.p5(c4)
            t4 = self.f4(torch.cat([self.up(c5), c4], 1))
            o3 = self.f3(torch.cat([self.up(t4), c3], 1))
            o4 = self.n4(torch.cat([self.d4(o3), t4], 1))
            o5 = self.n5(torch.cat([self.d5(o4), c5], 1))
            return [h(o) for h, o in zip(self.heads, (o3, o4, o5), strict=True)]

        def decode(self, outs):
            """Raw head maps -> (B, 4+nc, N): cx, cy, w, h in input pixels, then class probabilities."""
            res = []
            for o, s in zip(outs, STRIDES, strict=True):
                b, _, gh, gw = o.shape
                gy, gx = torch.meshgrid(torch.arange(gh, dtype=o.dtype), torch.arange(gw, dtype=o.dtype), indexing="ij")
                cx = (torch.sigmoid(o[:, 0]) * 2 - 0.5 + gx) * s
                cy = (torch.sigmoid(o[:, 1]) * 2 - 0.5 + gy) * s
                w = torch.exp(o[:, 2].clamp(-6, 6)) * s * 2
                h = torch.exp(o[:, 3].clamp(-6, 6)) * s * 2
                cls = torch.sigmoid(o[:, 4:])
                res.append(torch.cat([torch.stack([cx, cy, w, h], 1), cls], 1).reshape(b, 4 + self.nc, -1))
            return torch.cat(res, 2)

        def forward(self, x):
            return self.decode(self.raw(x))

    return Net()


def targets_for(boxes_xyxy: list[np.ndarray], n_anchor: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-anchor assignment. Returns (B, N) positive mask and (B, N, 4) target xyxy."""
    b = len(boxes_xyxy)
    pos = np.zeros((b, n_anchor), bool)
    tgt = np.zeros((b, n_anchor, 4), np.float32)
    for i, boxes in enumerate(boxes_xyxy):
        for x0, y0, x1, y1 in boxes:
            cx, cy, side = (x0 + x1) / 2, (y0 + y1) / 2, max(x1 - x0, y1 - y0)
            off = 0
            for s, (lo, hi) in zip(STRIDES, LEVEL_RANGES, strict=True):
                g = INPUT // s
                if lo <= side < hi:
                    gx, gy = int(cx // s), int(cy // s)
                    rad = 1 if side / s > 3 else 0  # big boxes: 3x3 cells around the centre
                    for yy in range(max(gy - rad, 0), min(gy + rad + 1, g)):
                        for xx in range(max(gx - rad, 0), min(gx + rad + 1, g)):
                            # only cells whose centre lies inside the box and near its centre
                            ccx, ccy = (xx + 0.5) * s, (yy + 0.5) * s
                            if (x0 <= ccx <= x1 and y0 <= ccy <= y1) or (xx == gx and yy == gy):
                                k = off + yy * g + xx
                                pos[i, k] = True
                                tgt[i, k] = (x0, y0, x1, y1)
                off += g * g
    return pos, tgt


def giou(a, b):
    import torch

    ix0, iy0 = torch.max(a[:, 0], b[:, 0]), torch.max(a[:, 1], b[:, 1])
    ix1, iy1 = torch.min(a[:, 2], b[:, 2]), torch.min(a[:, 3], b[:, 3])
    inter = (ix1 - ix0).clamp(0) * (iy1 - iy0).clamp(0)
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    union = area_a + area_b - inter + 1e-6
    iou = inter / union
    cx0, cy0 = torch.min(a[:, 0], b[:, 0]), torch.min(a[:, 1], b[:, 1])
    cx1, cy1 = torch.max(a[:, 2], b[:, 2]), torch.max(a[:, 3], b[:, 3])
    carea = (cx1 - cx0) * (cy1 - cy0) + 1e-6
    return iou - (carea - union) / carea, iou


def sample(rng: np.random.Generator, cam: PinholeCamera, world: str = "render",
           real_fraction: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """One letterboxed training frame and its boxes (K, 4) xyxy in input pixels."""
    if world == "real" or (world == "mixed" and rng.random() < real_fraction):
        img, xyxy = real_scene(rng)
    else:
        img, box = random_scene(rng, cam, TRAIN_STYLE)
        xyxy = np.array([box.xyxy], np.float32) if box is not None else np.zeros((0, 4), np.float32)
    return _letterbox_boxes(img, xyxy)


def _letterbox_boxes(img: np.ndarray, xyxy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    lb, s, dx, dy = letterbox(img, (INPUT, INPUT))
    boxes = np.asarray(xyxy, np.float32).reshape(-1, 4) * s + np.array([dx, dy, dx, dy], np.float32)
    return lb, boxes


def load_yolo_frames(dataset: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """A YOLO-layout folder (images/, labels/) as letterboxed frames with boxes; the user's fine-tune data."""
    from perception.evaluate import load_dataset

    out = []
    for item in load_dataset(dataset).frames:
        img = cv2.imread(str(item.image), cv2.IMREAD_COLOR)
        if img is None:
            continue
        out.append(_letterbox_boxes(img, item.boxes))
    if not out:
        raise SystemExit(f"train_detector: --finetune {dataset}: no readable labelled frames")
    return out


def load_onnx_weights(model, path: Path) -> None:
    """Start from an exported model: its Conv+BN were fused on export, so the BN layers become identity."""
    import onnx
    import torch
    from onnx import numpy_helper

    graph = onnx.load(str(path)).graph
    inits = {i.name: numpy_helper.to_array(i).copy() for i in graph.initializer}
    nodes = [nd for nd in graph.node if nd.op_type == "Conv"]
    # The exporter writes the convs in execution order: record that order from a forward pass.
    order, names = [], {m: k for k, m in model.named_modules()}
    hooks = [m.register_forward_hook(lambda mod, i, o: order.append(mod))
             for m in model.modules() if isinstance(m, torch.nn.Conv2d)]
    model.eval()
    with torch.no_grad():
        model(torch.zeros(1, 3, INPUT, INPUT))
    for h in hooks:
        h.remove()
    if len(order) != len(nodes):
        raise SystemExit(f"train_detector: --init-onnx {path}: {len(nodes)} convs, the model has {len(order)}")
    mods = dict(model.named_modules())
    n = 0
    with torch.no_grad():
        for conv, node in zip(order, nodes, strict=True):
            w = torch.from_numpy(inits[node.input[1]])
            if tuple(w.shape) != tuple(conv.weight.shape):
                raise SystemExit(f"train_detector: --init-onnx {path}: layer {names[conv]} shape {tuple(w.shape)}")
            conv.weight.copy_(w)
            bias = torch.from_numpy(inits[node.input[2]])
            if conv.bias is not None:
                conv.bias.copy_(bias)
            else:
                parent, idx = names[conv].rsplit(".", 1)
                bn = mods[f"{parent}.{int(idx) + 1}"]
                bn.weight.fill_(1.0)
                bn.bias.copy_(bias)
                bn.running_mean.zero_()
                bn.running_var.fill_(1.0 - bn.eps)
            n += 1
    model.train()
    print(f"initialised {n} conv layers from {path}", flush=True)


def train(args: argparse.Namespace) -> None:
    import torch

    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)  # 1 by default: 2 shared cores on the dev machine
    rng = np.random.default_rng(args.seed)
    cam = PinholeCamera.default()
    model = build_model()
    if args.resume:  # continue a run (e.g. a second budget); record it in the JSON
        model.load_state_dict(torch.load(args.resume))
    elif args.init_onnx:
        load_onnx_weights(model, args.init_onnx)
    if args.init_onnx or args.freeze_bn:
        # The exported model had its BN folded into the convs: keep the (identity) BN statistics frozen so the
        # warm start is the exported function; batch statistics would change it from the first step.
        for mod in model.modules():
            if isinstance(mod, torch.nn.BatchNorm2d):
                mod.eval()
    user = load_yolo_frames(args.finetune) if args.finetune else []
    if user:
        print(f"fine-tune: {len(user)} frames from {args.finetune}", flush=True)
    n_params = sum(p.numel() for p in model.parameters())
    print(f"params {n_params}", flush=True)
    n_anchor = sum((INPUT // s) ** 2 for s in STRIDES)
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=5e-4)
    # Replay pool: rendering is the bottleneck, so each rendered frame is seen a few times (with flips).
    pool = [sample(rng, cam, args.world, args.real_fraction) for _ in range(args.pool)]
    t0 = time.monotonic()
    # The schedule is in steps, so a run is reproducible from (--seed, --steps). With only --minutes, the
    # step count is fixed from the speed of the first PROBE steps and printed/recorded for reruns.
    total = args.steps
    step = 0
    ema_loss = None
    while True:
        elapsed = time.monotonic() - t0
        if not total and step == PROBE:
            total = max(PROBE + 1, int(args.minutes * 60.0 / (elapsed / PROBE)))
            print(f"budget {args.minutes} min -> {total} steps (rerun with --steps {total})", flush=True)
        if (total and step >= total) or (args.stop_at and step >= args.stop_at):
            break
        frac = step / total if total else 0.0
        lr = args.lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(frac, 1.0))))
        for g in opt.param_groups:
            g["lr"] = lr
        for _ in range(args.fresh):
            pool[int(rng.integers(len(pool)))] = sample(rng, cam, args.world, args.real_fraction)
        idx = rng.integers(len(pool), size=args.batch)
        imgs, boxes = [], []
        for j, k in enumerate(idx):
            im, bx = user[int(rng.integers(len(user)))] if user and j % 2 == 0 else pool[int(k)]
            if rng.random() < 0.5:  # horizontal flip
                im = im[:, ::-1]
                bx = bx.copy()
                bx[:, [0, 2]] = INPUT - bx[:, [2, 0]]
            if rng.random() < 0.5:
                # Desaturate towards grey (no new hues): shape cues over colour, so gate colours never
                # seen in training (the held-out style) are still gates.
                a = rng.uniform(0.0, 1.0)
                grey = cv2.cvtColor(cv2.cvtColor(np.ascontiguousarray(im), cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR)
                im = cv2.addWeighted(np.ascontiguousarray(im), a, grey, 1.0 - a, 0.0)
            if args.hue and rng.random() < 0.5:
                # Rotate hues (YOLO's hsv_h augmentation, full circle): a gate of any colour is a gate.
                hsv = cv2.cvtColor(np.ascontiguousarray(im), cv2.COLOR_BGR2HSV)
                hsv[..., 0] = ((hsv[..., 0].astype(np.int16) + int(rng.integers(180))) % 180).astype(np.uint8)
                im = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)
            imgs.append(im)
            boxes.append(bx)
        x = torch.from_numpy(np.stack(imgs)[..., ::-1].copy()).permute(0, 3, 1, 2).float() / 255.0
        pos, tgt = targets_for(boxes, n_anchor)
        pos_t, tgt_t = torch.from_numpy(pos), torch.from_numpy(tgt)
        out = model(x)  # (B, 5, N)
        cls = out[:, 4].clamp(1e-6, 1 - 1e-6)
        npos = max(int(pos.sum()), 1)
        cls_target = torch.zeros_like(cls)
        box_loss = torch.zeros(())
        if pos.any():
            pb = out[:, :4].permute(0, 2, 1)[pos_t]
            pxy = torch.stack([pb[:, 0] - pb[:, 2] / 2, pb[:, 1] - pb[:, 3] / 2,
                               pb[:, 0] + pb[:, 2] / 2, pb[:, 1] + pb[:, 3] / 2], 1)
            g, iou = giou(pxy, tgt_t[pos_t])
            box_loss = (1 - g).mean()
            # IoU-aware class target: the score ranks boxes by quality, which NMS then keeps.
            cls_target[pos_t] = iou.detach().clamp(0.3, 1.0)
        bce = torch.nn.functional.binary_cross_entropy(cls, cls_target, reduction="none")
        # focal-style down-weighting of the many easy negatives
        wgt = (cls_target - cls).abs().detach() ** 1.5
        cls_loss = (bce * wgt).sum() / npos
        loss = cls_loss + 5.0 * box_loss
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
        opt.step()
        ema_loss = float(loss.detach()) if ema_loss is None else 0.98 * ema_loss + 0.02 * float(loss.detach())
        step += 1
        if step % 50 == 0:
            print(f"step {step} t {elapsed / 60:.1f} min lr {lr:.2e} loss {ema_loss:.3f} "
                  f"(cls {float(cls_loss.detach()):.3f} box {float(box_loss.detach()):.3f})", flush=True)
        if step % args.checkpoint_every == 0:
            torch.save(model.state_dict(), args.out / "gate_detector.pt")
    torch.save(model.state_dict(), args.out / "gate_detector.pt")
    write_model(model, args, total or step, step, round((time.monotonic() - t0) / 60, 1))


def write_model(model, args: argparse.Namespace, total: int, step: int, minutes: float | None) -> None:
    """ONNX + JSON metadata (everything needed to reproduce: seed, schedule length, stop step)."""
    import torch

    export(model, args.out / "gate_detector.onnx")
    meta = {
        "classes": ["gate"],
        "input_size": [INPUT, INPUT],
        "input": "RGB float 0..1, NCHW, letterboxed with pad value 114",
        "output": "[1, 4 + nc, N]: cx, cy, w, h (input pixels), class probabilities",
        "training": {
            "command": f"tools/train_detector.py --seed {args.seed} --steps {total} --lr {args.lr}"
                       + f" --threads {args.threads}" + (" --hue" if args.hue else "")
                       + (f" --resume {args.resume}" if args.resume else "")
                       + (f" --world {args.world}" if args.world != "render" else "")
                       + (f" --real-fraction {args.real_fraction}" if args.world == "mixed" else "")
                       + (f" --init-onnx {args.init_onnx}" if args.init_onnx else "")
                       + (" --freeze-bn" if args.freeze_bn else "")
                       + (f" --finetune {args.finetune}" if args.finetune else "")
                       + (f" --stop-at {step}" if step < total else ""),
            "world": args.world, "real_fraction": args.real_fraction if args.world == "mixed" else None,
            "finetune": str(args.finetune) if args.finetune else None,
            "init_onnx": str(args.init_onnx) if args.init_onnx else None,
            "augment": "horizontal flip, desaturation towards grey (p 0.5)"
                       + (", hue rotation (p 0.5)" if args.hue else ""),
            "seed": args.seed, "schedule_steps": total, "steps": step, "minutes": minutes,
            "batch": args.batch, "pool": args.pool, "fresh": args.fresh, "lr": args.lr,
            "params": sum(p.numel() for p in model.parameters()),
            "resumed_from": str(args.resume) if args.resume else None, "style": TRAIN_STYLE.name,
            "torch": torch.__version__,
        },
    }
    (args.out / "gate_detector.json").write_text(json.dumps(meta, indent=2) + "\n")
    print(f"exported after {step} of {total} steps", flush=True)


def export(model, path: Path) -> None:
    import torch

    model.eval()
    dummy = torch.zeros(1, 3, INPUT, INPUT)
    torch.onnx.export(model, (dummy,), str(path), opset_version=17, dynamo=False,
                      input_names=["images"], output_names=["output0"])
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)", flush=True)


def evaluate(model_path: Path, n: int, seed: int, style, backend: str = "cv2") -> dict:
    """Recall / precision at IoU 0.5 of the real Detector (perception.detector) on rendered frames."""
    from perception.detector import Detector
    from perception.tracker import iou

    det = Detector(model_path, "gate", backend=backend)
    rng = np.random.default_rng(seed)
    cam = PinholeCamera.default()
    tp = fp = n_gt = 0
    by_size = {"small": [0, 0], "medium": [0, 0], "large": [0, 0]}  # [hits, total] by box max side (px)
    centre_err = []
    for _ in range(n):
        img, gt = random_scene(rng, cam, style)
        dets = det.detect(img)
        matched = False
        for d in dets:
            if gt is not None and not matched and iou(d, gt) >= 0.5:
                tp += 1
                matched = True
                centre_err.append(math.hypot(d.cx - gt.cx, d.cy - gt.cy))
            else:
                fp += 1
        if gt is not None:
            n_gt += 1
            side = max(gt.w, gt.h)
            key = "small" if side < 64 else "medium" if side < 192 else "large"
            by_size[key][1] += 1
            by_size[key][0] += int(matched)
    return {
        "frames": n,
        "seed": seed,
        "style": style.name,
        "gates": n_gt,
        "recall": round(tp / max(n_gt, 1), 4),
        "precision": round(tp / max(tp + fp, 1), 4),
        "recall_by_size": {k: round(h / t, 4) if t else None for k, (h, t) in by_size.items()},
        "median_centre_error_px": round(float(np.median(centre_err)), 2) if centre_err else None,
        "confidence": det.conf,
        "iou_threshold": 0.5,
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--minutes", type=float, default=30.0, help="wall-clock training budget")
    p.add_argument("--steps", type=int, default=0, help="exact number of steps (overrides --minutes)")
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--pool", type=int, default=600, help="rendered frames kept for reuse")
    p.add_argument("--fresh", type=int, default=3, help="new frames rendered per step")
    p.add_argument("--lr", type=float, default=3e-3)
    p.add_argument("--out", type=Path, default=None,
                   help="output folder (default perception/models/, with --finetune ./finetuned-detector/)")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (results depend on it)")
    p.add_argument("--hue", action="store_true", help="hue-rotation augmentation (stage 2 of the shipped model)")
    p.add_argument("--eval-frames", type=int, default=400)
    p.add_argument("--checkpoint-every", type=int, default=100, help="steps between saves of DIR/gate_detector.pt")
    p.add_argument("--eval-only", action="store_true")
    p.add_argument("--resume", type=Path, default=None, help="start from this state dict (.pt)")
    p.add_argument("--world", choices=("render", "real", "mixed"), default="render",
                   help="training frames: perception.render (the stage-1/2 model), perception.realworld, or mixed")
    p.add_argument("--real-fraction", type=float, default=0.5, help="--world mixed: share of realworld frames")
    p.add_argument("--init-onnx", type=Path, default=None,
                   help="start from this exported model (.onnx); its BN layers are folded, so they stay frozen")
    p.add_argument("--freeze-bn", action="store_true",
                   help="keep BN statistics frozen (for --resume of a run that started from --init-onnx)")
    p.add_argument("--finetune", type=Path, default=None,
                   help="YOLO-layout DATASET of your own labelled frames: half of each batch (see above)")
    p.add_argument("--stop-at", type=int, default=0, help="stop after this many steps of the --steps schedule")
    p.add_argument("--export-checkpoint", type=Path, default=None,
                   help="export this .pt (from a run given by --seed/--steps/--stop-at) instead of training")
    args = p.parse_args()
    out_given = args.out is not None
    if args.out is None:  # a fine-tune never overwrites the shipped model by default
        args.out = Path("finetuned-detector") if args.finetune else ROOT / "perception" / "models"
    args.out.mkdir(parents=True, exist_ok=True)
    if args.finetune and not (args.resume or args.init_onnx):
        args.init_onnx = ROOT / "perception" / "models" / "gate_detector.onnx"  # start from the shipped model
    if args.finetune and args.world == "render":
        args.world = "mixed"  # the user's frames + real-world and rendered frames, so nothing is forgotten
    if args.export_checkpoint:  # a checkpoint of a run (--seed, --steps, --stop-at say which): export only
        import torch

        model = build_model()
        model.load_state_dict(torch.load(args.export_checkpoint))
        write_model(model, args, args.steps, args.stop_at or args.steps, None)
    elif not args.eval_only:
        train(args)
    onnx_path = args.out / "gate_detector.onnx"
    meta_path = args.out / "gate_detector.json"
    meta = json.loads(meta_path.read_text())
    # Held-out seeds are far from any training draw; the held-out style never appears in training.
    meta["metrics"] = {
        "heldout_frames": evaluate(onnx_path, args.eval_frames, 10_000_019, TRAIN_STYLE),
        "heldout_style": evaluate(onnx_path, args.eval_frames, 20_000_033, HELDOUT_STYLE),
    }
    if not (args.eval_only and not out_given):  # a re-measurement never rewrites the shipped record
        meta_path.write_text(json.dumps(meta, indent=2) + "\n")
    print(json.dumps(meta["metrics"], indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
