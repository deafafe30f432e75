"""Object detector for YOLOv8/YOLO11-layout ONNX models, run with cv2.dnn (default) or onnxruntime.

Layout: one input ``1x3xHxW`` (RGB, 0..1, letterboxed with grey 114), one output ``[1, 4+nc, N]``
with rows cx, cy, w, h in input pixels followed by nc class scores (what ``yolo export
format=onnx`` and tools/train_detector.py produce). The class list comes from, in order: the
``classes`` argument, a JSON file next to the model (``{"classes": [...]}``), the ``names``
metadata that Ultralytics writes into the ONNX file, or ``[class_name]`` for a one-class model.

The model is validated on load (file exists, parses, input and output shapes, class list length,
class name present); any problem raises ``DetectorError`` with one line naming the file.
"""

from __future__ import annotations

import ast
import json
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from perception.plausibility import plausible_candidates
from perception.types import BoundingBox

MODELS_DIR = Path(__file__).resolve().parent / "models"
SHIPPED_MODEL = MODELS_DIR / "gate_detector.onnx"
# Trained on real-world photos; on real flythrough video it began no engagement on clutter where the default
# model began them on lit cabinets and walls (docs/verification.md): the default for real camera frames.
SHIPPED_REAL_MODEL = MODELS_DIR / "gate_detector_real.onnx"
PAD_VALUE = 114


def model_path(pc, real_frames: bool = False) -> Path:  # pc: companion.config_perception.PerceptionConfig
    """The ONNX file a config names: ``perception.model`` (a path, or the bare file name of a shipped model), or
    when it is empty the shipped model for the frames: real-world for a real camera, default for rendered ones."""
    if not pc.model:
        return SHIPPED_REAL_MODEL if real_frames else SHIPPED_MODEL
    path = Path(pc.model)
    if not path.exists() and path.name == str(pc.model) and (MODELS_DIR / path.name).is_file():
        path = MODELS_DIR / path.name  # a bare file name of a shipped model, e.g. gate_detector_real.onnx
    return path


class DetectorError(ValueError):
    """A model that cannot be used, as one line: file and what is wrong."""


# --------------------------------------------------------------------------- ONNX header (no onnx dependency)


def _varint(buf: bytes, i: int) -> tuple[int, int]:
    shift = result = 0
    while True:
        if i >= len(buf):
            raise ValueError("truncated varint")
        b = buf[i]
        i += 1
        result |= (b & 0x7F) << shift
        if not b & 0x80:
            return result, i
        shift += 7
        if shift > 63:
            raise ValueError("bad varint")


def _fields(buf: bytes) -> list[tuple[int, int, object]]:
    """Top-level protobuf fields of a message: (number, wire type, int | bytes)."""
    out = []
    i = 0
    while i < len(buf):
        key, i = _varint(buf, i)
        num, wt = key >> 3, key & 7
        if wt == 0:
            v, i = _varint(buf, i)
        elif wt == 1:
            v, i = buf[i:i + 8], i + 8
        elif wt == 2:
            n, i = _varint(buf, i)
            if i + n > len(buf):
                raise ValueError("truncated field")
            v, i = buf[i:i + n], i + n
        elif wt == 5:
            v, i = buf[i:i + 4], i + 4
        else:
            raise ValueError(f"unsupported wire type {wt}")
        out.append((num, wt, v))
    return out


@dataclass(frozen=True)
class OnnxHeader:
    inputs: list[tuple[str, list[int | str]]]  # graph inputs that are not initializers: name, dims
    outputs: list[tuple[str, list[int | str]]]
    metadata: dict[str, str]


def _value_info(buf: bytes) -> tuple[str, list[int | str]]:
    name, dims = "", []
    for num, _, v in _fields(buf):
        if num == 1:
            name = bytes(v).decode("utf-8", "replace")
        elif num == 2:  # TypeProto
            for n2, _, v2 in _fields(v):
                if n2 == 1:  # tensor_type
                    for n3, _, v3 in _fields(v2):
                        if n3 == 2:  # shape
                            for n4, _, v4 in _fields(v3):
                                if n4 == 1:  # dim
                                    d: int | str = "?"
                                    for n5, _, v5 in _fields(v4):
                                        if n5 == 1:
                                            d = int(v5)
                                        elif n5 == 2:
                                            d = bytes(v5).decode("utf-8", "replace")
                                    dims.append(d)
    return name, dims


def read_onnx_header(path: Path) -> OnnxHeader:
    """Graph inputs/outputs and metadata of an ONNX file (ModelProto fields 7 and 14)."""
    model = _fields(path.read_bytes())
    graphs = [v for num, wt, v in model if num == 7 and wt == 2]
    if not graphs:
        raise ValueError("no graph in the file")
    init_names: set[str] = set()
    inputs, outputs = [], []
    for num, wt, v in _fields(graphs[0]):
        if wt != 2:
            continue
        if num == 5:  # initializer (TensorProto), name = field 8
            for n2, _, v2 in _fields(v):
                if n2 == 8:
                    init_names.add(bytes(v2).decode("utf-8", "replace"))
        elif num == 11:
            inputs.append(_value_info(v))
        elif num == 12:
            outputs.append(_value_info(v))
    meta = {}
    for num, wt, v in model:
        if num == 14 and wt == 2:
            kv = {n: bytes(x).decode("utf-8", "replace") for n, _, x in _fields(v)}
            meta[kv.get(1, "")] = kv.get(2, "")
    return OnnxHeader([i for i in inputs if i[0] not in init_names], outputs, meta)


# --------------------------------------------------------------------------- detector


def letterbox(img: np.ndarray, size_hw: tuple[int, int]) -> tuple[np.ndarray, float, int, int]:
    """Scale to fit ``size_hw`` keeping the aspect ratio, pad centred with grey 114. Returns img, scale, dx, dy."""
    h, w = img.shape[:2]
    H, W = size_hw
    s = min(W / w, H / h)
    nw, nh = round(w * s), round(h * s)
    dx, dy = (W - nw) // 2, (H - nh) // 2
    out = np.full((H, W, 3), PAD_VALUE, np.uint8)
    out[dy:dy + nh, dx:dx + nw] = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA)
    return out, s, dx, dy


def _class_list(path: Path, header: OnnxHeader, classes: list[str] | None, class_name: str) -> list[str] | None:
    if classes:
        return list(classes)
    side = path.with_suffix(".json")
    if side.is_file():
        try:
            meta = json.loads(side.read_text())
        except (OSError, ValueError) as e:
            raise DetectorError(f"{side}: unreadable model metadata ({e})") from None
        if isinstance(meta, dict) and isinstance(meta.get("classes"), list):
            return [str(c) for c in meta["classes"]]
    names = header.metadata.get("names")
    if names:  # Ultralytics: "{0: 'person', 1: 'bicycle', ...}"
        try:
            parsed = ast.literal_eval(names)
            if isinstance(parsed, dict):
                return [str(parsed[k]) for k in sorted(parsed)]
        except (ValueError, SyntaxError):
            pass
    return None


class Detector:
    """``detect(image_bgr) -> list[BoundingBox]`` of one class, best first, in image pixels."""

    def __init__(
        self,
        path: str | Path,
        class_name: str = "gate",
        input_size: int | tuple[int, int] | None = None,
        conf: float = 0.35,
        nms_iou: float = 0.5,
        backend: str = "cv2",
        classes: list[str] | None = None,
        threads: int = 0,
    ) -> None:
        self.path = Path(path)
        self.conf = float(conf)
        self.nms_iou = float(nms_iou)
        p = self.path
        if backend not in ("auto", "cv2", "onnxruntime"):
            raise DetectorError(f"{p}: backend must be 'auto', 'cv2' or 'onnxruntime', got {backend!r}")
        if backend == "auto":  # onnxruntime when installed: about twice as fast as cv2.dnn here
            try:
                import onnxruntime  # noqa: F401

                backend = "onnxruntime"
            except ImportError:
                backend = "cv2"
        self.backend = backend
        if not p.is_file():
            raise DetectorError(f"{p}: model file not found")
        try:
            header = read_onnx_header(p)
        except (ValueError, OSError, IndexError) as e:
            raise DetectorError(f"{p}: not an ONNX model ({e})") from None
        if len(header.inputs) != 1:
            raise DetectorError(f"{p}: expected one image input, the model has {len(header.inputs)}")
        in_name, dims = header.inputs[0]
        if len(dims) != 4 or dims[1] != 3 or (isinstance(dims[0], int) and dims[0] != 1):
            raise DetectorError(f"{p}: input {in_name!r} is {dims}, expected 1x3xHxW (an image model)")
        if input_size is not None:
            hw = (input_size, input_size) if isinstance(input_size, int) else tuple(input_size)
        elif isinstance(dims[2], int) and isinstance(dims[3], int) and dims[2] > 0 and dims[3] > 0:
            hw = (dims[2], dims[3])
        elif "imgsz" in header.metadata:
            hw = tuple(ast.literal_eval(header.metadata["imgsz"]))
        else:
            hw = (640, 640)
        for d, want in zip(dims[2:], hw, strict=True):
            if isinstance(d, int) and d > 0 and d != want:
                raise DetectorError(f"{p}: input is {dims[2]}x{dims[3]}, configured input size is {hw[0]}x{hw[1]}")
        self.input_hw: tuple[int, int] = (int(hw[0]), int(hw[1]))
        self.input_name = in_name
        if len(header.outputs) < 1:
            raise DetectorError(f"{p}: model has no output")
        self.classes = _class_list(p, header, classes, class_name)
        # Load and run once on a blank image: a model that does not run or has the wrong output is refused now.
        try:
            if backend == "cv2":
                self._net = cv2.dnn.readNetFromONNX(str(p))
                if threads > 0:
                    cv2.setNumThreads(threads)
            else:
                import onnxruntime as ort

                so = ort.SessionOptions()
                if threads > 0:
                    so.intra_op_num_threads = threads
                    so.inter_op_num_threads = 1
                self._sess = ort.InferenceSession(str(p), so, providers=["CPUExecutionProvider"])
            out = self._infer(np.zeros((1, 3, *self.input_hw), np.float32))
        except ImportError:
            raise DetectorError(f"{p}: backend 'onnxruntime' requested but onnxruntime is not installed") from None
        except Exception as e:  # cv2.error / onnxruntime exceptions: no common base class
            first = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
            raise DetectorError(f"{p}: model does not load or run with {backend} ({first[:200]})") from None
        if out.ndim != 3 or out.shape[0] != 1 or out.shape[1] < 5:
            raise DetectorError(f"{p}: output is {list(out.shape)}, expected YOLOv8 layout [1, 4+nc, N]")
        nc = out.shape[1] - 4
        if out.shape[2] < out.shape[1]:
            raise DetectorError(
                f"{p}: output is {list(out.shape)}, looks transposed; expected YOLOv8 layout [1, 4+nc, N]"
            )
        if self.classes is None:
            if nc != 1:
                raise DetectorError(f"{p}: model has {nc} classes but no class list (set perception.classes)")
            self.classes = [class_name]
        if len(self.classes) != nc:
            raise DetectorError(
                f"{p}: output has {nc} class scores but the class list has {len(self.classes)} names"
            )
        if class_name not in self.classes:
            raise DetectorError(f"{p}: class {class_name!r} not in the model's classes {self.classes}")
        self.class_name = class_name
        self.class_index = self.classes.index(class_name)
        self.nc = nc
        self.last_ms = 0.0

    @classmethod
    def from_config(cls, pc, real_frames: bool = False) -> Detector:  # pc: config_perception.PerceptionConfig
        """``real_frames``: the frames come from a real camera (live or recorded), where an unset
        ``perception.model`` means the real-world model; rendered frames keep the default one."""
        path = model_path(pc, real_frames)
        return cls(
            path, pc.class_name, pc.input_size or None, pc.confidence, pc.nms_iou, pc.backend,
            list(pc.classes) or None, pc.threads,
        )

    def _infer(self, blob: np.ndarray) -> np.ndarray:
        if self.backend == "cv2":
            self._net.setInput(blob)
            return np.asarray(self._net.forward())
        return self._sess.run(None, {self.input_name: blob})[0]

    def detect(self, image: np.ndarray, t: float = 0.0) -> list[BoundingBox]:
        """Boxes of the configured class (confidence >= conf, after NMS), best first."""
        t0 = time.perf_counter()
        if image.ndim != 3 or image.shape[2] != 3:
            raise ValueError(f"detector: expected an HxWx3 BGR image, got shape {image.shape}")
        lb, s, dx, dy = letterbox(image, self.input_hw)
        blob = cv2.dnn.blobFromImage(lb, 1.0 / 255.0, swapRB=True)
        out = self._infer(blob)[0]  # (4 + nc, N)
        scores = out[4:]
        mine = scores[self.class_index]
        # Class filter: the anchor's best class must be ours (a "car" anchor with some gate score is a car).
        keep = mine >= self.conf
        if self.nc > 1:
            keep &= scores.argmax(0) == self.class_index
        if not keep.any():
            self.last_ms = (time.perf_counter() - t0) * 1e3
            return []
        # Finite, in-range, sane-sized candidates only, at most MAX_CANDIDATES of them into NMS.
        b, conf = plausible_candidates(out[:4, keep].T, mine[keep], self.input_hw)
        x0 = (b[:, 0] - b[:, 2] / 2 - dx) / s
        y0 = (b[:, 1] - b[:, 3] / 2 - dy) / s
        w = b[:, 2] / s
        h = b[:, 3] / s
        idx = cv2.dnn.NMSBoxes(
            np.stack([x0, y0, w, h], 1).tolist(), conf.tolist(), self.conf, self.nms_iou
        )
        H, W = image.shape[:2]
        res = []
        for i in np.asarray(idx, dtype=int).reshape(-1):
            # clip to the image: a gate partly out of view is still a gate
            bx = BoundingBox.from_xyxy(
                max(0.0, float(x0[i])), max(0.0, float(y0[i])), min(float(W), float(x0[i] + w[i])),
                min(float(H), float(y0[i] + h[i])), float(conf[i]), t,
            )
            if bx.w > 1 and bx.h > 1:
                res.append(bx)
        res.sort(key=lambda bb: -bb.confidence)
        self.last_ms = (time.perf_counter() - t0) * 1e3
        return res
