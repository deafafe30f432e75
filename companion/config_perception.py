"""Config section of the perception pipeline (detector, tracker policy, box smoothing, camera source)."""

from __future__ import annotations

import os
import stat
from typing import Literal

from pydantic import Field, model_validator

from companion.configbase import Number, Seconds, Section


class PerceptionConfig(Section):
    # Detector (perception/detector.py)
    model: str = Field(
        "", description="path to a YOLOv8-layout ONNX file, or the file name of a shipped one in perception/models/ "
        "(gate_detector_real.onnx); empty = the shipped model for the frames: gate_detector_real.onnx for a real "
        "camera (app.camera: source, live or replayed), gate_detector.onnx for rendered frames",
    )
    class_name: str = Field("gate", description="class of the target in the model's class list")
    classes: list[str] = Field(
        default_factory=list,
        description="the model's class list; empty = from <model>.json, the ONNX metadata, or [class_name]",
    )
    input_size: int = Field(0, ge=0, le=4096, description="px, square model input; 0 = from the model")
    confidence: Number = Field(0.35, gt=0.0, lt=1.0)
    nms_iou: Number = Field(0.5, gt=0.0, lt=1.0)
    backend: Literal["auto", "cv2", "onnxruntime"] = Field(
        "auto", description="auto = onnxruntime when installed (about 2x faster here), else cv2.dnn"
    )
    threads: int = Field(1, ge=0, le=64, description="inference threads; 0 = library default")
    zoom_below: Number = Field(
        80.0, ge=0.0, le=4096.0,
        description="px; a tracked, candidate or just-lost target smaller than this (larger side) is also looked "
        "for in a crop of the model's input size at full resolution (perception/zoom.py; only when the frame is "
        "larger than the model's input); 0 = off",
    )
    zoom_track_below: Number = Field(
        240.0, ge=0.0, le=4096.0,
        description="px; while tracking, the track's prediction is zoomed on below this (larger side; at least "
        "zoom_below; zoom_below 0 turns every zoom off): at half size the detector boxes a 100-180 px ring together "
        "with background beside it (1.3-2.8x the ring on PX4 SIH merge ramps), at full resolution mostly the ring "
        "alone",
    )
    zoom_scan: bool | Literal["auto"] = Field(
        "auto", description="while searching with nothing to confirm, also run the detector on one full-resolution "
        "tile of the frame a frame, in turn (a gate too small for the whole frame is found there; zoom_below > 0); "
        "auto = on for rendered frames, off for a real camera (its false boxes at full resolution are not measured)",
    )

    # Tracker and policy (perception/tracker.py, perception/pipeline.py)
    tracker: Literal["detect", "nanotrack"] = Field(
        "detect",
        description="detect = detector every frame + association + Kalman box (weight-free); "
        "nanotrack = cv2.TrackerNano between detections (needs the two ONNX files below)",
    )
    nanotrack_backbone: str = Field("", description="NanoTrack backbone ONNX (tracker: nanotrack)")
    nanotrack_neckhead: str = Field("", description="NanoTrack neck/head ONNX (tracker: nanotrack)")
    redetect_every: int = Field(5, ge=1, le=1000, description="frames between detections when a tracker runs")
    redetect_below: Number = Field(0.5, ge=0.0, le=1.0, description="tracker score that forces a detection")
    max_jump: Number = Field(
        0.25, gt=0.0, le=2.0, description="centre jump (fraction of the image diagonal) rejected as a switch"
    )
    max_jump_rate: Number = Field(
        1.5, gt=0.0, le=100.0,
        description="image diagonals per second a box centre may move from the prediction between two frames "
        "(capped by max_jump): 40 px per frame at 30 fps on 640x480, the max_jump cap at 5 fps",
    )
    min_iou: Number = Field(0.05, ge=0.0, le=1.0, description="association: IoU with the prediction, or ...")
    coast_time: Seconds = Field(0.3, ge=0.0, le=10.0, description="s; Kalman prediction kept through misses")
    confirm_frames: int = Field(2, ge=1, le=30, description="consecutive detections that (re)acquire a target")
    acquire_confidence: Number = Field(
        0.5, ge=0.0, le=1.0,
        description="a detection at least this confident acquires on its own frame (1 = always confirm_frames)",
    )
    smoothing: Number = Field(
        0.3, ge=0.0, le=1.0, description="box smoothing 0..1 (0 = raw measurement, 1 = heavy); sets Kalman noise"
    )
    # Consistency rules (perception/tracker.py: plausible, consistent; perception/pipeline.py: challenger)
    max_aspect: Number = Field(
        3.0, ge=1.0, le=100.0,
        description="max(w/h, h/w) of a gate box not cut by the image border (a gate seen 70 deg off-axis: ~2.9)",
    )
    max_growth_rate: Number = Field(
        4.0, gt=0.0, le=100.0,
        description="1/s, box size change rate a measurement may show vs the prediction (approach: speed/distance)",
    )
    switch_frames: int = Field(
        5, ge=2, le=100, description="frames a distinct, better-scoring candidate must persist to take the track"
    )
    min_track_score: Number = Field(
        0.25, ge=0.0, lt=1.0,
        description="track score (confidence averaged over frames, misses count 0) below which no box is output",
    )
    memory_time: Seconds = Field(
        1.0, ge=0.0, le=10.0,
        description="s after a lost track's last measurement during which a new acquisition must be consistent "
        "with it (size and position) or wait; 0 = no memory",
    )
    refuse_time: Seconds = Field(
        1.0, ge=0.0, le=10.0,
        description="s an object the app refused as not the target (companion/verify.py, at acquisition) is not "
        "acquired again, followed while it stays in view; 0 = the app's refusal only resets the tracker",
    )
    derotate: bool = Field(
        True,
        description="move the held boxes by the camera's own rotation between frames (from the attitude at each "
        "frame's capture) before predicting them; frames without an attitude (a video alone) are not moved",
    )
    memory_min_score: Number = Field(
        0.5, ge=0.0, le=1.0,
        description="track score at its last measurement a lost track needs to be remembered (a weak track may "
        "have been on the wrong thing: the gate must not wait for it); 1 = never remember",
    )
    memory_growth_rate: Number = Field(
        1.5, gt=0.0, le=100.0,
        description="1/s, box size change rate a lost target may show while unseen (a gate 8 m away at 12 m/s: "
        "1.5; max_growth_rate's 4 /s holds only just before a pass)",
    )
    memory_reach_rate: Number = Field(
        0.3, ge=0.0, le=10.0,
        description="image diagonals per second the lost target's centre may have moved while unseen (on top of "
        "max_jump)",
    )

    # Camera source (perception/sources.py)
    source: str = Field("0", description="V4L2 index, video file, GStreamer pipeline, rtsp:// URL or 'synthetic'")

    @model_validator(mode="after")
    def _check(self) -> PerceptionConfig:
        if self.tracker == "nanotrack" and not (self.nanotrack_backbone and self.nanotrack_neckhead):
            raise ValueError("tracker: nanotrack needs nanotrack_backbone and nanotrack_neckhead (two ONNX files)")
        for key in ("model", "nanotrack_backbone", "nanotrack_neckhead"):
            kind = _not_a_file(getattr(self, key))
            if kind:
                raise ValueError(f"{key} {getattr(self, key)}: {kind}, not a model file")
        return self


def _not_a_file(path: str) -> str | None:
    """What a model path that exists is when it is not a regular file (None: a file, or not there: the
    detector resolves shipped names and says "not found" itself)."""
    if not path:
        return None
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return None
    for test, what in ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return what
    return None if stat.S_ISREG(mode) else "not a regular file"
