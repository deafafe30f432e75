"""Rendered camera for the closed loop: true pose + gate -> rendered frame -> real detector/tracker -> box.

Drop-in for ``companion.sim.camera.GeometricCamera``: same ``capture(t, p_enu, R_enu_flu,
centre, normal, radius)`` signature, same frames (world ENU, body FLU attitude), returns the
Pipeline's box (or None) instead of the geometric one. The gate is drawn with its OUTER edge at
``radius`` (what the geometric camera boxes), with a per-run colour, thickness and shape. The
background is a fixed panorama sampled by viewing direction, so it moves consistently with the
vehicle's rotation instead of flickering frame to frame.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

import cv2
import numpy as np

from perception.los import CameraModel
from perception.render import HELDOUT_STYLE, TRAIN_STYLE, Gate, Style, make_background, random_gate_colour
from perception.render import render_gate_frame as _render
from perception.types import BoundingBox

if TYPE_CHECKING:
    from perception.pipeline import Pipeline

_F_FRD_FLU = np.diag([1.0, -1.0, -1.0])  # body FRD <-> FLU (companion.frames.F_FRD_FLU; perception stays standalone)


class Panorama:
    """An equirectangular background (azimuth x elevation) sampled per pixel by viewing direction."""

    def __init__(self, model: CameraModel, rng: np.random.Generator, style: Style, width: int = 2880) -> None:
        self.model = model
        # ~8 px/deg like the camera; clutter scaled to the panorama's area (~13 frames of 640x480).
        k = max(1, round(width * width / 2 / (640 * 480)))
        self.env = make_background(width, width // 2, rng, replace(style, clutter=(style.clutter[0] * k,
                                                                                   style.clutter[1] * k)))
        # Pixel rays (camera frame) on a coarse grid; the direction maps are upsampled per frame.
        self._step = 4
        w, h = model.width, model.height
        us = np.arange(0, w + self._step, self._step, dtype=np.float64)
        vs = np.arange(0, h + self._step, self._step, dtype=np.float64)
        uu, vv = np.meshgrid(us, vs)
        pts = np.stack([uu.ravel(), vv.ravel()], 1).reshape(-1, 1, 2)
        if model.dist.size:
            und = cv2.undistortPoints(pts, model.K, model.dist).reshape(-1, 2)
        else:
            Ki = np.linalg.inv(model.K)
            und = (np.hstack([pts.reshape(-1, 2), np.ones((len(us) * len(vs), 1))]) @ Ki.T)[:, :2]
        rays = np.hstack([und, np.ones((len(und), 1))])
        self._rays = rays / np.linalg.norm(rays, axis=1, keepdims=True)
        self._grid = (len(vs), len(us))

    def view(self, R_world_cam: np.ndarray) -> np.ndarray:
        d = self._rays @ np.asarray(R_world_cam, float).T  # world ENU directions
        az = np.arctan2(d[:, 1], d[:, 0])
        el = np.arcsin(np.clip(d[:, 2], -1.0, 1.0))
        eh, ew = self.env.shape[:2]
        mx = ((az / (2 * math.pi)) % 1.0) * ew
        my = (0.5 - el / math.pi) * (eh - 1)
        gh, gw = self._grid
        w, h = self.model.width, self.model.height
        mx = cv2.resize(mx.reshape(gh, gw).astype(np.float32), (gw * self._step, gh * self._step))[:h, :w]
        my = cv2.resize(my.reshape(gh, gw).astype(np.float32), (gw * self._step, gh * self._step))[:h, :w]
        return cv2.remap(self.env, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)


class RenderedCamera:
    """Renders each frame from the true pose and runs the perception Pipeline on it."""

    def __init__(
        self,
        model: CameraModel,
        pipeline: Pipeline,
        rng: np.random.Generator | None = None,
        style: Style = TRAIN_STYLE,
        shape: str = "ring",
        thickness_frac: float = 0.15,
        colour: tuple[int, int, int] | None = None,
        keep_frames: bool = False,
    ) -> None:
        self.model = model
        self.pipeline = pipeline
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.shape = shape
        self.thickness_frac = float(thickness_frac)
        self.colour = colour if colour is not None else random_gate_colour(self.rng, style)
        # Per-run appearance: lighting fixed over the run, light sensor noise per frame, no JPEG.
        gain = float(self.rng.uniform(0.8, 1.15))
        self.frame_style = replace(style, gain=(gain, gain), blur_px=(0.0, 0.0), noise_sigma=(1.0, 3.0), jpeg_prob=0.0)
        self.panorama = Panorama(model, self.rng, style)
        self._R_flu_cam = _F_FRD_FLU @ model.R_body_cam
        self.keep_frames = keep_frames
        self.drop_prob = 0.0
        self.last_frame: np.ndarray | None = None
        self.last_truth: BoundingBox | None = None

    @classmethod
    def from_config(cls, cfg, seed: int = 0, heldout_style: bool = False, **kw) -> RenderedCamera:
        """From a companion Config: camera model + the configured detector/tracker pipeline."""
        from perception.pipeline import Pipeline

        return cls(CameraModel.from_config(cfg.camera), Pipeline.from_config(cfg), np.random.default_rng(seed),
                   HELDOUT_STYLE if heldout_style else TRAIN_STYLE, **kw)

    @classmethod
    def for_run(cls, cfg, rng: np.random.Generator, drop_prob: float = 0.0, **kw) -> RenderedCamera:
        """One simulated run's camera: fresh pipeline, appearance drawn from ``rng`` (the run's camera stream)."""
        from perception.pipeline import Pipeline

        cam = cls(CameraModel.from_config(cfg.camera), Pipeline.from_config(cfg), rng, **kw)
        cam.drop_prob = float(drop_prob)
        return cam

    def reset(self) -> None:
        self.pipeline.reset()

    def refuse(self) -> None:
        self.pipeline.refuse()

    def acquiring(self, on: bool) -> None:
        self.pipeline.acquiring(on)

    def render(
        self, p_enu: np.ndarray, R_enu_flu: np.ndarray, centre: np.ndarray, normal: np.ndarray, radius: float,
        t: float = 0.0,
    ) -> tuple[np.ndarray, BoundingBox | None]:
        """The frame the camera sees and the ground-truth box of the gate's outer rim."""
        R_world_cam = np.asarray(R_enu_flu, float) @ self._R_flu_cam
        gate = Gate(np.asarray(centre, float), np.asarray(normal, float), float(radius), self.shape,  # type: ignore[arg-type]
                    self.colour, self.thickness_frac * float(radius))
        bg = self.panorama.view(R_world_cam)
        return _render(self.model, R_world_cam, np.asarray(p_enu, float), gate, self.frame_style, self.rng,
                       background=bg, t=t)

    def capture(
        self, t: float, p_enu: np.ndarray, R_enu_flu: np.ndarray, centre: np.ndarray, normal: np.ndarray,
        radius: float, R_world_body: np.ndarray | None = None,
    ) -> BoundingBox | None:
        """``R_world_body``: the attitude the controller is given for this frame (the estimate, not the truth that
        draws it), for the pipeline's rotation compensation (perception/derotate.py)."""
        if self.drop_prob > 0.0 and self.rng.random() < self.drop_prob:
            return None  # a dropped frame never reaches the pipeline
        frame, truth = self.render(p_enu, R_enu_flu, centre, normal, radius, t)
        self.last_truth = truth
        if self.keep_frames:
            self.last_frame = frame
        return self.pipeline.process(frame, t, R_world_body)


def geometric_camera_substitute(cfg, **kw):
    """A callable with GeometricCamera's constructor signature that builds a RenderedCamera.

    ``companion.sim.runner.run_once`` builds ``GeometricCamera(model, pixel_noise, drop_prob, min_box, rng,
    clip)``; this builds the rendered camera from the same arguments (pixel noise and clipping come from
    the real detector instead), so the runner can swap cameras with one line.
    """

    def make(model: CameraModel, pixel_noise: float = 0.0, drop_prob: float = 0.0, min_box: float = 2.0,
             rng: np.random.Generator | None = None, clip: bool = True) -> RenderedCamera:
        from perception.pipeline import Pipeline

        cam = RenderedCamera(model, Pipeline.from_config(cfg), rng if rng is not None else np.random.default_rng(0),
                             **kw)
        cam.drop_prob = float(drop_prob)
        return cam

    return make
