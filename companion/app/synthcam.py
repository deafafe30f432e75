"""Synthetic camera: what the onboard camera would see, from the vehicle pose that arrives over MAVLink.

SENSOR SIMULATION ONLY. The pose read here (position from LOCAL_POSITION_NED, attitude from
PX4's estimate) is used to *draw the picture* of virtual gates, as the paper's hardware runs
did with "simulated gate visuals". It never reaches the controller: the controller sees only
the box that perception extracts from the frame, exactly as with a real camera.

Two renderings, one interface (``CameraSource.read() -> Frame``, ``Perception.process(frame)``):
* ``image``: BGR frames from perception/render.py go through the real detector pipeline;
* ``geometric``: the gate rim projected to a pixel box (companion/sim/camera.py), cheaper, with
  the simulator's pixel noise and drops; its "perception" just reads that box out of the frame.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.app.camera import Frame, GeometricPerception, Perception, PipelinePerception
from companion.frames import F_FRD_FLU, R_enu_flu_from_ned_frd, R_from_quat_wxyz, ned_to_enu
from companion.sim.camera import GeometricCamera, true_camera_config
from companion.sim.gates import GateMotion, make_gate
from perception.los import CameraModel
from perception.types import BoundingBox

if TYPE_CHECKING:
    from companion.config import Config


SENSOR_NOISE = 1.5  # grey levels (std) on rendered frames; the detector trained with 0..8


@dataclass(frozen=True)
class VehiclePose:
    """Pose for sensor simulation: position NED (m) and attitude NED/FRD quaternion (wxyz)."""

    t: float
    p_ned: np.ndarray
    q_wxyz: np.ndarray


class FaultInjector:
    """Test switch (app.synthetic.fault): corrupts perception output from ``after`` s past the first frame."""

    def __init__(self, kind: str, after: float, width: int) -> None:
        self.kind = kind
        self.after = after
        self.width = width
        self.t0: float | None = None
        self.jumped = 0

    def active(self, t: float) -> bool:
        if self.kind == "none":
            return False
        if self.t0 is None:
            self.t0 = t
        return t - self.t0 >= self.after

    def apply(self, t: float, box: BoundingBox | None) -> BoundingBox | None:
        if not self.active(t):
            return box
        if self.kind == "nan_box":  # a broken detector: NaN, negative size, centre off the image, in turn
            self.jumped += 1
            return (BoundingBox(math.nan, math.nan, math.nan, math.nan, 1.0, t),
                    BoundingBox(320.0, 240.0, -40.0, 30.0, 1.0, t),
                    BoundingBox(5000.0, -80.0, 40.0, 30.0, 1.0, t))[self.jumped % 3]
        if self.kind == "lose_target":
            return None
        if self.kind == "block":  # a detector call that never returns, on the event loop's thread
            import time

            time.sleep(3600)
        if self.kind == "exception":
            raise RuntimeError("injected perception failure (app.synthetic.fault=exception)")
        if self.kind == "los_jump" and box is not None and self.jumped < 2:
            # Two frames of a box on the far side of the image (a tracker switching targets), then back.
            self.jumped += 1
            return BoundingBox(self.width - box.cx if abs(self.width / 2 - box.cx) > 150 else
                               (box.cx + 250) % self.width, box.cy, box.w, box.h, box.confidence, t)
        return box


class InjectedPerception:
    def __init__(self, inner: Perception, faults: FaultInjector) -> None:
        self.inner = inner
        self.faults = faults

    def process(self, frame: Frame, attitude: np.ndarray | None = None) -> BoundingBox | None:
        return self.faults.apply(frame.t, self.inner.process(frame, attitude))

    def reset(self) -> None:
        reset = getattr(self.inner, "reset", None)
        if reset is not None:
            reset()

    def refuse(self) -> None:
        refuse = getattr(self.inner, "refuse", None)
        if refuse is not None:
            refuse()

    def acquiring(self, on: bool) -> None:
        acquiring = getattr(self.inner, "acquiring", None)
        if acquiring is not None:
            acquiring(on)


class SyntheticScene:
    """Virtual gates in world ENU, anchored at the vehicle pose of the first frame."""

    def __init__(self, cfg: Config, first: VehiclePose, rng: np.random.Generator) -> None:
        sc = cfg.app.synthetic
        p_enu = ned_to_enu(first.p_ned)
        R_ned_frd = R_from_quat_wxyz(first.q_wxyz)
        fwd_ned = R_ned_frd[:, 0].copy()
        fwd_ned[2] = 0.0
        if np.linalg.norm(fwd_ned) < 1e-6:
            fwd_ned = np.array([1.0, 0.0, 0.0])
        fwd = ned_to_enu(fwd_ned / np.linalg.norm(fwd_ned))
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        tgt = cfg.sim.target
        self.size = tgt.size(sc.radius)  # (width, height) m; a ring's width is its diameter
        self.radius = 0.5 * self.size[0] if tgt.width is not None else sc.radius
        self.gates: list[GateMotion] = []
        for k in range(sc.count):
            centre = p_enu + fwd * sc.distance * (k + 1) + right * sc.lateral_offset + [0, 0, sc.height_offset]
            if tgt.on_ground:  # standing on the ground (ENU z = 0 is the take-off point's ground)
                centre[2] = 0.5 * self.size[1]
            # The normal points back at the vehicle's start side (the sim's convention).
            self.gates.append(make_gate(sc.motion, centre, -fwd, rng=rng, gates_cfg=cfg.sim.gates))

    def positions(self, t: float) -> list[np.ndarray]:
        return [g.position(t) for g in self.gates]


class SyntheticRenderer:
    """The synthetic camera's picture of a gate from a pose: perception/render.py through the camera as it truly sits
    on the body (``sim.camera.mount_error``), a world-fixed background, a sensor's noise. The synthetic camera draws
    every frame with it; ``companion log rerun --rerender`` draws a flight's frames again with it from the log."""

    def __init__(self, cfg: Config, rng: np.random.Generator) -> None:
        from perception.render import TRAIN_STYLE, PinholeCamera
        from perception.simcamera import Panorama

        self.cfg = cfg
        true_cam = true_camera_config(cfg)
        self.model = CameraModel.from_config(true_cam)
        self.camera = PinholeCamera.from_config(true_cam)
        self.rng = rng
        # The background is fixed in the world, as the in-process rendered camera's: its clutter moves in the image
        # as the vehicle turns. An image-fixed background (before) turned a false detection into a box that stayed
        # put however the vehicle rotated, a phantom PN chased into the ground (PX4 Table I, x500, stationary gate).
        self.panorama = Panorama(self.model, np.random.default_rng(cfg.sim.seed), TRAIN_STYLE)
        self._noise: list[np.ndarray] | None = None
        self._noise_k = 0

    def draw(self, t: float, p_enu: np.ndarray, R_enu_flu: np.ndarray,
             gate: tuple[np.ndarray, np.ndarray, float] | None) -> tuple[np.ndarray, BoundingBox | None]:
        """The BGR frame seen at ``t`` from ``p_enu`` with attitude ``R_enu_flu`` (body FLU -> ENU) of ``gate``
        (centre ENU, normal ENU, radius m; None: the background only), and the gate's true box (None: not in view)."""
        from perception.render import Gate, render_gate_frame

        R_enu_cam = R_enu_flu @ F_FRD_FLU @ self.model.R_body_cam
        g = None if gate is None else Gate(gate[0], gate[1], gate[2])
        image, truth = render_gate_frame(self.camera, R_enu_cam, p_enu, g, style=None, rng=self.rng,
                                         background=self.panorama.view(R_enu_cam), t=t)
        return self._sensor_noise(image), truth

    def _sensor_noise(self, image: np.ndarray) -> np.ndarray:
        """A real sensor's frames are never identical, even of a static view; a clean render of a hovering
        vehicle's view is. Without noise an empty view would look like a frozen camera to
        perception/plausibility.py. A few seeded noise frames in turn: cheap, deterministic."""
        import cv2

        if self._noise is None or self._noise[0].shape != image.shape:
            rng = np.random.default_rng(self.cfg.sim.seed + 2)
            self._noise = [rng.normal(0.0, SENSOR_NOISE, image.shape).round().astype(np.int16) for _ in range(4)]
        self._noise_k = (self._noise_k + 1) % len(self._noise)
        return cv2.add(image, self._noise[self._noise_k], dtype=cv2.CV_8U)


class SyntheticCamera:
    """Paced at the camera rate; each frame renders the scene from the newest pose."""

    def __init__(
        self,
        cfg: Config,
        pose: Callable[[], VehiclePose | None],
        render: str | None = None,
        clock: Callable[[], float] = time.monotonic,
        on_gate: Callable[[int, GateMotion, np.ndarray, float, bool], None] | None = None,
    ) -> None:
        self.cfg = cfg
        self.pose = pose
        self.render = render or cfg.app.synthetic.render
        self.clock = clock
        self.on_gate = on_gate
        self.period = 1.0 / cfg.camera.rate
        # The camera as it truly sits on the body (sim.camera.mount_error); the app perceives with cfg.camera.
        self.model = CameraModel.from_config(true_camera_config(cfg))
        self.rng = np.random.default_rng(cfg.sim.seed)
        simcam = cfg.sim.camera
        self.geo = GeometricCamera(self.model, simcam.pixel_noise, simcam.drop_prob, simcam.min_box,
                                   np.random.default_rng(cfg.sim.seed + 1))
        if cfg.sim.target.shape != "ring":
            if self.render != "geometric":
                raise ValueError(f"synthetic camera: sim.target.shape {cfg.sim.target.shape!r} needs "
                                 "app.synthetic.render: geometric (the renderer draws rings)")
            self.geo.use_rectangle(*cfg.sim.target.size(cfg.app.synthetic.radius))
        self.scene: SyntheticScene | None = None
        self.t_scene0 = 0.0
        self.index = 0
        self._next: float | None = None
        self._last_pose_t = -math.inf
        # Built here, not at the first frame: its background takes ~0.4 s. It draws from self.rng, which the scene's
        # gates also draw from (the same stream as before it was a class of its own).
        self.renderer = SyntheticRenderer(cfg, self.rng) if self.render == "image" else None
        self.faults = FaultInjector(cfg.app.synthetic.fault, cfg.app.synthetic.fault_after, self.model.width)
        self.closed = False
        self._last: Frame | None = None

    def perception(self, pipeline: Any | None = None) -> Perception:
        inner: Perception = GeometricPerception() if self.render == "geometric" else PipelinePerception(pipeline)
        return InjectedPerception(inner, self.faults)

    async def read(self) -> Frame:
        now = self.clock()
        if self._next is None:
            self._next = now
        if self._next > now:
            await asyncio.sleep(self._next - now)
        # Newest frame only: after a slow consumer, skip the missed ticks (a real camera drops them).
        self._next = max(self._next + self.period, self.clock())
        t = self.clock()
        if self.cfg.app.synthetic.fault == "stall" and self.faults.active(t):
            await asyncio.Event().wait()  # a camera driver that hangs: no frame ever again
        if self.cfg.app.synthetic.fault == "freeze" and self._last is not None and self.faults.active(t):
            # A driver that re-sends its last buffer: the same picture, a fresh index and timestamp.
            self.index += 1
            return Frame(self.index, t, self._last.image, self._last.box, self._last.truth_box)
        pose = self.pose()
        while pose is None:  # no pose yet (telemetry just started): wait a tick
            await asyncio.sleep(self.period)
            pose = self.pose()
        if pose.t > self._last_pose_t:
            # Capture time = the pose's own time (up to a sample period old), so the controller's
            # attitude-at-capture lookup finds the attitude that drew the frame.
            self._last_pose_t = pose.t
            t = min(t, pose.t)
        # A stale pose (telemetry stopped, e.g. link lost) is drawn at the current time: the camera keeps
        # running, and the attitude lookup past the newest sample returns that same sample.
        if self.render == "image":
            frame = await asyncio.get_running_loop().run_in_executor(None, self.capture, t, pose)
        else:
            frame = self.capture(t, pose)
        self._last = frame
        return frame

    def capture(self, t: float, pose: VehiclePose) -> Frame:
        if self.scene is None:
            self.scene = SyntheticScene(self.cfg, pose, self.rng)
            self.t_scene0 = t
        ts = t - self.t_scene0
        p_enu = ned_to_enu(pose.p_ned)
        R_enu_flu = R_enu_flu_from_ned_frd(R_from_quat_wxyz(pose.q_wxyz))
        self.index += 1
        best: tuple[float, GateMotion, np.ndarray] | None = None
        for g in self.scene.gates:
            c = g.position(ts)
            depth = float((c - p_enu) @ R_enu_flu[:, 0])
            if depth > 0.0 and (best is None or depth < best[0]):
                best = (depth, g, c)
        box = truth = None
        image = None
        if self.render == "geometric":
            if best is not None:
                box = self.geo.capture(t, p_enu, R_enu_flu, best[2], best[1].normal, self.scene.radius)
        else:
            assert self.renderer is not None
            radius = self.scene.radius if self.scene else 1.0
            image, truth = self.renderer.draw(t, p_enu, R_enu_flu,
                                              None if best is None else (best[2], best[1].normal, radius))
        if self.on_gate is not None:
            # Every gate, every frame (scoring needs each one's plane crossing); visible = the one drawn.
            for k, g in enumerate(self.scene.gates, 1):
                in_view = best is not None and g is best[1] and (box is not None or image is not None)
                self.on_gate(k, g, g.position(ts), self.scene.radius, in_view)
        return Frame(self.index, t, image, box, truth)

    def close(self) -> None:
        self.closed = True
