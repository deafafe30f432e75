"""Tiny hand-built ONNX models in the YOLOv8 layout (and wrong layouts), written by the tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper


def constant_yolo_model(path: Path, out: np.ndarray, in_shape: tuple[int, ...] = (1, 3, 64, 64),
                        metadata: dict[str, str] | None = None) -> Path:
    """A model whose output is the constant ``out`` (+ 0 x mean of the input), so decoding can be checked."""
    x = helper.make_tensor_value_info("images", TensorProto.FLOAT, list(in_shape))
    y = helper.make_tensor_value_info("output0", TensorProto.FLOAT, list(out.shape))
    const = numpy_helper.from_array(out.astype(np.float32), "C")
    zero = numpy_helper.from_array(np.zeros((1,), np.float32), "Z")
    nodes = [
        helper.make_node("ReduceMean", ["images"], ["m"], keepdims=0),
        helper.make_node("Mul", ["m", "Z"], ["m0"]),
        helper.make_node("Add", ["C", "m0"], ["output0"]),
    ]
    graph = helper.make_graph(nodes, "constant_yolo", [x], [y], [const, zero])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    for k, v in (metadata or {}).items():
        e = model.metadata_props.add()
        e.key, e.value = k, v
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path
