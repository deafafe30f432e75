"""The camera and perception a flight uses, from its config (``fly`` and shadow mode alike).

A device camera through the detector pipeline, or the synthetic camera drawn from the vehicle's pose
(geometric box, or rendered frames through the detector), its virtual gates logged and handed to the
gate judge. Also ``detector_available``: whether the configured detector loads (``companion check``,
``companion sim``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from companion.app.outcome import GateJudge
    from companion.config import Config
    from companion.flightlog import FlightLog
    from companion.vehicle import TruthSource


def build_camera(cfg: Config, link: Any, log: Any, judge: Any = None,
                 truth: TruthSource | None = None) -> tuple[Any, Any, bool]:
    """(camera source, perception, run perception in a thread) for the configured camera; the synthetic
    camera draws from ``truth``'s pose and its gates go to the log and to ``judge``
    (companion/app/outcome.py, ground truth).

    Every source is wrapped in CheckedCamera: each frame is checked for plausibility (size, type,
    timestamps, frozen content) before perception sees it.
    """
    from companion.app.camera import CheckedCamera

    cam, perception, in_thread = _build_camera(cfg, link, log, judge, truth)
    return CheckedCamera.from_config(cam, cfg), perception, in_thread


def _build_camera(cfg: Config, link: Any, log: Any, judge: Any = None,
                  truth: TruthSource | None = None) -> tuple[Any, Any, bool]:
    from companion.app.synthcam import SyntheticCamera, VehiclePose

    if cfg.app.camera == "synthetic":
        if truth is None:
            raise ValueError("the synthetic camera draws from a truth source (open_truth or LinkPositionTruth)")

        def pose() -> VehiclePose | None:
            # Sensor simulation only: the pose draws the picture; the controller never sees it.
            att = link.attitude
            if truth.latest() is None or att is None:
                return None
            # Stamped with the attitude sample's time: the frame is "captured" at the instant whose
            # attitude drew it, so the controller's attitude-at-capture lookup sees the same attitude.
            # PX4 SIH's truth: its true pose at that instant; the link's: its newest position, PX4's attitude.
            true = truth.at(att.t_rx)
            if true is None:
                return None
            return VehiclePose(att.t_rx, true.position_ned, true.q_wxyz)

        cam = SyntheticCamera(cfg, pose, on_gate=gate_logger(log, judge))
        if cam.render == "geometric":
            return cam, cam.perception(), False
        from perception.pipeline import Pipeline

        return cam, cam.perception(Pipeline.from_config(cfg)), True
    from companion.app.camera import DeviceCamera, PipelinePerception
    from perception.pipeline import Pipeline

    pipe = Pipeline.from_config(cfg, real_frames=True)
    return DeviceCamera.open(cfg.perception.source), PipelinePerception(pipe), True


def gate_logger(log: FlightLog, judge: GateJudge | None = None,
                clock: Callable[[], float] = time.monotonic) -> Callable[[int, Any, np.ndarray, float, bool], None]:
    """Callback for the synthetic camera: log each virtual gate (scene ENU -> NED), and hand it to the
    judge (on the monotonic clock of the link's truth samples). Scoring only."""
    from companion.frames import enu_to_ned

    def on_gate(k: int, gate: Any, c_enu: np.ndarray, radius: float, visible: bool) -> None:
        c, n = enu_to_ned(c_enu), enu_to_ned(gate.normal)
        log.write("gate", k=k, gate_n=c[0], gate_e=c[1], gate_d=c[2], normal_n=n[0], normal_e=n[1],
                  normal_d=n[2], radius=radius, visible=visible)
        if judge is not None:
            judge.gate(clock(), k, c, n, radius)

    return on_gate


def real_frames(cfg: Config) -> bool:
    """The detector sees a real camera's frames (app.camera: source), not rendered ones."""
    return cfg.app.camera == "source" and str(cfg.perception.source).strip() != "synthetic"


def detector_available(cfg: Config) -> str | None:
    """None when the configured detector loads, else the one-line reason it does not."""
    try:
        from perception.detector import Detector

        Detector.from_config(cfg.perception, real_frames=real_frames(cfg))
        return None
    except Exception as e:  # a missing or broken model file
        return f"{type(e).__name__}: {e}"
