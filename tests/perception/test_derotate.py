"""The pipeline's track follows the camera's own rotation (perception/derotate.py).

Logged on real PX4 (SIH, 2026-12-07 table, run060): the first setpoint of the engagement pitched the hovering
vehicle from 0 to -33 deg in 0.25 s; the level gate 25 m ahead (40 px) moved from image row 371 to 80 in that time,
up to 70 px between frames. The pipeline's track coasted on row 354-371 with decaying confidence while the
detector found the gate at rows 228 and 78, and the app rotated the stale row with the new attitude into a LOS
22 deg below the gate's. Below, the same motion with the camera of config/vehicles/sih.yaml: the projections of a
world-fixed gate, computed by cv2.projectPoints, are the detections.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from companion.config import load_config
from companion.config_perception import PerceptionConfig
from perception.derotate import Derotation
from perception.los import CameraModel
from perception.pipeline import Pipeline
from perception.types import BoundingBox
from tests.perception.test_tracker_pipeline import ScriptedDetector

FRAME = np.zeros((480, 640, 3), np.uint8)
DT = 1 / 30
GATE_NED = np.array([25.0, 0.0, 0.0])  # level, 25 m ahead of a vehicle at the origin


def _camera(dist: tuple[float, ...] = ()) -> CameraModel:
    cam = load_config(["config/vehicles/sih.yaml"]).camera
    return CameraModel(np.asarray(cam.K, float), np.asarray(dist, float), np.asarray(cam.R_body_cam, float),
                       cam.width, cam.height)


def _R(pitch_deg: float, yaw_deg: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    """Body FRD -> world NED."""
    return Rotation.from_euler("ZYX", [yaw_deg, pitch_deg, roll_deg], degrees=True).as_matrix()


def _pixel(model: CameraModel, R_ned_frd: np.ndarray, p_ned: np.ndarray) -> tuple[float, float] | None:
    """Independent projection: cv2.projectPoints of the world point with the camera's pose."""
    R_cam_ned = (R_ned_frd @ model.R_body_cam).T
    if (R_cam_ned @ p_ned)[2] <= 0.0:
        return None
    rvec, _ = cv2.Rodrigues(R_cam_ned)
    dist = model.dist if model.dist.size else np.zeros(5)
    img, _ = cv2.projectPoints(p_ned.reshape(1, 1, 3), rvec, np.zeros(3), model.K, dist)
    return float(img[0, 0, 0]), float(img[0, 0, 1])


@pytest.mark.parametrize("dist", [(), (-0.28, 0.07, 0.0, 0.0, 0.0)], ids=["pinhole", "barrel"])
def test_a_pixel_moves_where_the_rotation_takes_its_world_point(dist) -> None:
    model = _camera(dist)
    d = Derotation(model)
    rng = np.random.default_rng(3)
    for _ in range(40):
        a = rng.uniform(-40, 40, 3)
        R0, R1 = _R(*a), _R(*(a + rng.uniform(-12, 12, 3)))
        p = R0 @ model.R_body_cam @ np.array([rng.uniform(-0.4, 0.4), rng.uniform(-0.3, 0.3), 1.0]) * 20.0
        px0, px1 = _pixel(model, R0, p), _pixel(model, R1, p)
        assert d.step(R0, DT) is None  # no earlier frame (after a reset, below)
        M = d.step(R1, DT)
        d.reset()
        assert M is not None and px0 is not None and px1 is not None
        moved = d.move(M, *px0)
        assert moved is not None
        assert math.hypot(moved[0] - px1[0], moved[1] - px1[1]) < 0.05


def test_no_attitude_no_rotation_or_an_estimator_jump_moves_nothing() -> None:
    d = Derotation(_camera())
    assert d.step(None, DT) is None and d.step(_R(-5), DT) is None  # the first attitude: nothing to compare with
    assert d.step(_R(-5), DT) is None  # the same attitude
    assert d.step(None, DT) is None and d.step(_R(-30), DT) is None  # an attitude gap: no rotation is invented
    assert d.step(_R(-30, yaw_deg=49.0), DT) is not None  # 49 deg in a frame: 1470 deg/s, still a rotation
    assert d.step(_R(-30, yaw_deg=100.0), DT) is None  # 51 deg more in a frame: a yaw reset, not the camera
    assert d.step(_R(-30, yaw_deg=151.0), 2 * DT) is not None  # 51 deg in two frame periods


def _pitch_profile() -> list[float]:
    """Hover for 10 frames, then pitch down at 150 deg/s to -36 deg (the first setpoint), then hold."""
    return [0.0] * 10 + [max(-36.0, -150.0 * DT * k) for k in range(1, 25)]


def _flight(model: CameraModel, with_attitude: bool) -> list[tuple[BoundingBox | None, tuple[float, float] | None]]:
    pitches = _pitch_profile()
    truth = [_pixel(model, _R(p), GATE_NED) for p in pitches]
    # Found on every other frame once the motion starts, as the logged detector found the moving 40 px ring.
    script = [[BoundingBox(px[0], px[1], 40.0, 40.0, 0.6)] if px is not None and 20 < px[1] < 460 and (
        k < 10 or k % 2 == 0) else [] for k, px in enumerate(truth)]
    pipe = Pipeline(ScriptedDetector(script), PerceptionConfig(), 640, 480, camera=model)  # type: ignore[arg-type]
    out = [pipe.process(FRAME, k * DT, _R(p) if with_attitude else None) for k, p in enumerate(pitches)]
    return list(zip(out, truth, strict=True))


def test_the_track_follows_the_gate_while_the_vehicle_pitches_down() -> None:
    model = _camera()
    rows = _flight(model, with_attitude=True)
    shown = [(b, px) for b, px in rows[5:] if px is not None and 20 < px[1] < 460]
    assert len(shown) >= 12
    # Every frame with the gate in view: a box on it (the gate moves up to ~45 px a frame here, 90 px between
    # detections).
    for b, px in shown:
        assert b is not None and math.hypot(b.cx - px[0], b.cy - px[1]) < 6.0, (b, px)


def test_without_the_attitude_the_track_is_left_behind() -> None:
    """The failure the rotation fixes: the same detections without attitudes leave the track on a stale pixel
    (a box far from the gate) or without a box while the gate is in view."""
    model = _camera()
    rows = _flight(model, with_attitude=False)
    shown = [(b, px) for b, px in rows[5:] if px is not None and 20 < px[1] < 460]
    stale = [b for b, px in shown if b is not None and math.hypot(b.cx - px[0], b.cy - px[1]) > 30.0]
    assert len(stale) >= 3  # boxes the app would rotate into a wrong LOS (up to 159 px behind here)
