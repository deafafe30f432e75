"""Camera side of the data path: a frame source and the perception stage that turns a frame into a box.

The flight loop only sees ``CameraSource.read() -> Frame`` and ``Perception.process(frame) -> box``,
for a real camera (``DeviceCamera`` over perception/sources.py + the detector pipeline) and for the
synthetic camera (companion/app/synthcam.py) alike.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from companion.frames import R_from_quat_wxyz
from perception.plausibility import FrameChecker, FrameFault
from perception.types import BoundingBox


@dataclass(frozen=True)
class Frame:
    """One camera frame. ``image`` for real/rendered frames; ``box`` is set only by the geometric camera."""

    index: int
    t: float  # capture time, s, on the app's monotonic clock
    image: np.ndarray | None = None
    box: BoundingBox | None = None
    truth_box: BoundingBox | None = None  # synthetic images: where the gate really is (scoring only)


class CameraSource(Protocol):
    async def read(self) -> Frame: ...

    def close(self) -> None: ...


class Perception(Protocol):
    def process(self, frame: Frame, attitude: np.ndarray | None = None) -> BoundingBox | None:
        """``attitude``: PX4's attitude at the frame's capture (NED/FRD quaternion wxyz), the one the core rotates
        the box with; None where there is none."""
        ...


class GeometricPerception:
    """The geometric camera's frames already carry the box (the projection is the detector)."""

    def process(self, frame: Frame, attitude: np.ndarray | None = None) -> BoundingBox | None:
        return frame.box


class PipelinePerception:
    """Real perception: detector + tracker + smoothing on the frame's image."""

    def __init__(self, pipeline: Any) -> None:
        self.pipeline = pipeline

    def process(self, frame: Frame, attitude: np.ndarray | None = None) -> BoundingBox | None:
        if frame.image is None:
            return None
        # The pipeline moves its track by the camera's own rotation (perception/derotate.py).
        return self.pipeline.process(frame.image, frame.t, None if attitude is None else R_from_quat_wxyz(attitude))

    def reset(self) -> None:
        """Forget the track (a gate was passed: the next one is a new target, not a jump)."""
        self.pipeline.reset()

    def refuse(self) -> None:
        """Look past the object held (the app refused it as not the target)."""
        self.pipeline.refuse()

    def acquiring(self, on: bool) -> None:
        """The app is acquiring: weigh other candidates at full resolution (perception/pipeline.py)."""
        self.pipeline.acquiring(on)


class CameraFailed(RuntimeError):
    """The camera ended or reported an error (one line: which source, what)."""


class DeviceCamera:
    """A real camera (V4L2, file, GStreamer, RTSP) through perception/sources.py: newest frame only."""

    def __init__(self, source: Any) -> None:
        self.source = source
        self.index = 0

    @classmethod
    def open(cls, spec: str) -> DeviceCamera:
        from perception.sources import open_source

        return cls(open_source(spec, realtime=True))

    async def read(self) -> Frame:
        loop = asyncio.get_running_loop()
        while True:
            # A stalled camera keeps us here: the app's watchdog acts, this loop just keeps waiting.
            got = await loop.run_in_executor(None, self.source.read, 0.5)
            if got is not None:
                t, image = got
                self.index += 1
                return Frame(self.index, t, image)
            if self.source.ended:
                raise CameraFailed(f"camera {self.source.name}: {self.source.error or 'stream ended'}")

    def close(self) -> None:
        self.source.close()


class CheckedCamera:
    """Any camera source, every frame checked (perception/plausibility.py) before anyone sees it.

    An implausible frame (wrong size or type, a timestamp that repeats, goes back, runs ahead or is
    stale, the same image over and over) raises CameraFailed: the flight ends in its named safe
    state (CAMERA_FAILED) instead of flying on it.
    """

    def __init__(self, inner: CameraSource, checker: FrameChecker,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.inner = inner
        self.checker = checker
        self.clock = clock

    @classmethod
    def from_config(cls, inner: CameraSource, cfg: Any) -> CheckedCamera:
        return cls(inner, FrameChecker(cfg.camera.width, cfg.camera.height, cfg.safety.camera_frozen_timeout))

    async def read(self) -> Frame:
        frame = await self.inner.read()
        try:
            self.checker.check(frame.t, frame.image, self.clock())
        except FrameFault as e:
            raise CameraFailed(str(e)) from None
        return frame

    def close(self) -> None:
        self.inner.close()

    def __getattr__(self, name: str) -> Any:  # the wrapped source's own attributes (render, faults, ...)
        return getattr(self.inner, name)
