"""Config section of the perception pipeline (detector, tracker, camera source)."""

from __future__ import annotations

from pydantic import Field

from companion.configbase import Number, Section


class PerceptionConfig(Section):
    model: str = Field("", description="path to a YOLOv8-layout ONNX file; empty = the shipped gate detector")
    class_name: str = Field("gate", description="class of the target in the model's class list")
    confidence: Number = Field(0.35, gt=0.0, lt=1.0)
    nms_iou: Number = Field(0.5, gt=0.0, lt=1.0)
