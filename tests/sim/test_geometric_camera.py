"""Geometric camera against hand-computed projections."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from companion.config import CameraConfig
from companion.sim.camera import GeometricCamera, rim_points
from perception.los import CameraModel

MODEL = CameraModel.from_config(CameraConfig())  # 640 x 480, fx = fy = 320 / tan(33.5 deg)
FX = 320.0 / math.tan(math.radians(33.5))
P = np.array([0.0, 0.0, 10.0])  # vehicle
LEVEL = np.eye(3)  # body FLU = world ENU: looking east
FACING = np.array([-1.0, 0.0, 0.0])  # gate normal, towards the vehicle


def cam(**kw) -> GeometricCamera:
    return GeometricCamera(MODEL, **kw)


def test_fronto_parallel_gate_straight_ahead():
    d, r = 20.0, 1.0
    box = cam().box_exact(P, LEVEL, P + np.array([d, 0, 0]), FACING, r)
    assert box is not None
    assert math.isclose(FX, 483.4, rel_tol=1e-3)
    assert math.isclose(box.cx, 320.0, abs_tol=1e-9) and math.isclose(box.cy, 240.0, abs_tol=1e-9)
    assert math.isclose(box.w, 2 * FX * r / d, rel_tol=1e-9)
    assert math.isclose(box.h, 2 * FX * r / d, rel_tol=1e-9)


def test_offset_gate_left_and_up_moves_the_box_left_and_up():
    # ENU: north (+y) is left of an east-looking camera, up is up: u = cx - fx y / x, v = cy - fy z / x.
    box = cam().box_exact(P, LEVEL, P + np.array([25.0, 2.0, -1.5]), FACING, 0.5)
    assert math.isclose(box.cx, 320.0 - FX * 2.0 / 25.0, rel_tol=1e-9)
    assert math.isclose(box.cy, 240.0 + FX * 1.5 / 25.0, rel_tol=1e-9)


def test_pitched_nose_down_sees_a_level_gate_above_the_centre():
    theta = math.radians(15.0)
    R = Rotation.from_euler("y", theta).as_matrix()  # FLU: +y rotation pitches the nose down
    box = cam().box_exact(P, R, P + np.array([30.0, 0, 0]), FACING, 1.0)
    assert math.isclose(box.cy, 240.0 - FX * math.tan(theta), rel_tol=1e-9)
    assert math.isclose(box.cx, 320.0, abs_tol=1e-9)


def test_yawed_vehicle_sees_the_gate_off_centre():
    psi = math.radians(10.0)
    R = Rotation.from_euler("z", psi).as_matrix()  # nose turned left (north of east)
    box = cam().box_exact(P, R, P + np.array([30.0, 0, 0]), FACING, 1.0)
    assert math.isclose(box.cx, 320.0 + FX * math.tan(psi), rel_tol=1e-9)


def test_field_of_view_check():
    c = cam()
    assert c.box_exact(P, LEVEL, P + np.array([-10.0, 0, 0]), FACING, 1.0) is None  # behind
    # 40 deg to the side: outside the 33.5 deg half angle of view.
    side = 20.0 * np.array([math.cos(math.radians(40)), math.sin(math.radians(40)), 0.0])
    assert c.box_exact(P, LEVEL, P + side, FACING, 1.0) is None
    inside = 20.0 * np.array([math.cos(math.radians(30)), math.sin(math.radians(30)), 0.0])
    assert c.box_exact(P, LEVEL, P + inside, FACING, 1.0) is not None
    # Too small to detect: 1 m ring at 1 km is < 2 px.
    assert c.box_exact(P, LEVEL, P + np.array([1000.0, 0, 0]), FACING, 1.0) is None


def test_closed_form_extent_matches_densely_sampled_rim_for_oblique_views():
    rng = np.random.default_rng(7)
    c = cam()
    for _ in range(200):
        R = Rotation.from_euler("zyx", rng.uniform(-15, 15, 3), degrees=True).as_matrix()
        centre = P + np.array([rng.uniform(4, 30), rng.uniform(-3, 3), rng.uniform(-2, 2)])
        normal = np.array([-1.0, rng.uniform(-1, 1), rng.uniform(-0.3, 0.3)])
        box = c.box_exact(P, R, centre, normal, 1.0)
        if box is None:
            continue
        # Independent: 4000 rim points through cv2.projectPoints.
        nrm = normal / np.linalg.norm(normal)
        u = np.cross(nrm, [0, 0, 1.0])
        u /= np.linalg.norm(u)
        w = np.cross(nrm, u)
        ang = np.linspace(0, 2 * np.pi, 4000, endpoint=False)
        rim = centre + np.outer(np.cos(ang), u) + np.outer(np.sin(ang), w)
        R_cam_world = (R @ np.diag([1.0, -1.0, -1.0]) @ MODEL.R_body_cam).T
        pc = (rim - P) @ R_cam_world.T
        px, _ = cv2.projectPoints(pc.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), MODEL.K, np.zeros(5))
        px = px.reshape(-1, 2)
        if px[:, 0].min() < 0 or px[:, 0].max() > 640 or px[:, 1].min() < 0 or px[:, 1].max() > 480:
            continue
        assert math.isclose(box.w, np.ptp(px[:, 0]), rel_tol=1e-4, abs_tol=1e-3)
        assert math.isclose(box.h, np.ptp(px[:, 1]), rel_tol=1e-4, abs_tol=1e-3)


def test_clipped_box_of_a_ring_cut_by_the_border():
    # 2 m ring at 5 m, 1.5 m left: the left edge is cut at u = 0.
    centre = P + np.array([5.0, 1.5, 0.0])
    paper = cam().box_exact(P, LEVEL, centre, FACING, 2.0)
    clipped = cam(clip=True).box_exact(P, LEVEL, centre, FACING, 2.0)
    u_right = 320.0 - FX * (1.5 - 2.0) / 5.0
    assert math.isclose(clipped.xyxy[0], 0.0, abs_tol=1e-9)
    assert math.isclose(clipped.xyxy[2], u_right, rel_tol=1e-9)
    assert math.isclose(paper.cx, 320.0 - FX * 1.5 / 5.0, rel_tol=1e-9)  # centre unbiased
    assert clipped.cx > paper.cx  # the detector-like box is biased towards the visible part


def test_distorted_camera_uses_opencv_projection():
    cfg = CameraConfig(distortion=[-0.2, 0.05, 0.0, 0.0, 0.0])
    model = CameraModel.from_config(cfg)
    centre = P + np.array([10.0, 2.0, 1.0])
    box = GeometricCamera(model).box_exact(P, LEVEL, centre, FACING, 0.5)
    pc = np.array([[-2.0, -1.0, 10.0]])  # camera frame: x right (= -north), y down (= -up), z forward
    px, _ = cv2.projectPoints(pc.reshape(1, 1, 3), np.zeros(3), np.zeros(3), model.K, model.dist)
    assert np.allclose([box.cx, box.cy], px.reshape(2), atol=1e-9)


def test_drops_and_pixel_noise_statistics():
    centre = P + np.array([20.0, 0, 0])
    assert all(cam(drop_prob=1.0).capture(0.0, P, LEVEL, centre, FACING, 1.0) is None for _ in range(20))
    c = cam(pixel_noise=2.0, rng=np.random.default_rng(1), drop_prob=0.25)
    boxes = [c.capture(0.0, P, LEVEL, centre, FACING, 1.0) for _ in range(4000)]
    got = [b for b in boxes if b is not None]
    assert 0.22 < 1 - len(got) / len(boxes) < 0.28
    cx = np.array([b.cx for b in got])
    assert abs(cx.mean() - 320.0) < 0.15 and 1.9 < cx.std() < 2.1


def test_capture_is_reproducible_for_a_seed():
    a = cam(pixel_noise=1.0, rng=np.random.default_rng(3)).capture(1.0, P, LEVEL, P + np.array([20, 0, 0]), FACING, 1.0)
    b = cam(pixel_noise=1.0, rng=np.random.default_rng(3)).capture(1.0, P, LEVEL, P + np.array([20, 0, 0]), FACING, 1.0)
    assert a == b and a.t == 1.0


@pytest.mark.parametrize("normal", [[-1.0, 0, 0], [0.3, -1.0, 0.2], [0.0, 0.0, 1.0]])
def test_rim_points_lie_on_the_circle(normal):
    c = np.array([1.0, 2.0, 3.0])
    pts = rim_points(c, np.array(normal), 1.5)
    n = np.array(normal) / np.linalg.norm(normal)
    assert np.allclose(np.linalg.norm(pts - c, axis=1), 1.5)
    assert np.allclose((pts - c) @ n, 0.0)


def _dense_visible_extent(R: np.ndarray, centre: np.ndarray, normal: np.ndarray, radius: float):
    """Independent: 20000 rim points through cv2.projectPoints, the extent of those in the image."""
    nrm = normal / np.linalg.norm(normal)
    u = np.cross(nrm, [0, 0, 1.0])
    u /= np.linalg.norm(u)
    w = np.cross(nrm, u)
    ang = np.linspace(0, 2 * np.pi, 20000, endpoint=False)
    rim = centre + radius * (np.outer(np.cos(ang), u) + np.outer(np.sin(ang), w))
    R_cam_world = (R @ np.diag([1.0, -1.0, -1.0]) @ MODEL.R_body_cam).T
    pc = (rim - P) @ R_cam_world.T
    pc = pc[pc[:, 2] > 1e-3]
    if len(pc) == 0:
        return None
    px, _ = cv2.projectPoints(pc.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), MODEL.K, np.zeros(5))
    px = px.reshape(-1, 2)
    px = px[(px[:, 0] >= 0) & (px[:, 0] <= 640) & (px[:, 1] >= 0) & (px[:, 1] <= 480)]
    if len(px) == 0:
        return None
    return px[:, 0].min(), px[:, 1].min(), px[:, 0].max(), px[:, 1].max()


def test_detector_like_box_is_the_visible_part_of_a_partial_ring():
    """clip=True: the box of a ring cut by the border (even with its centre out of view) is the extent of
    the arcs inside the image, not the whole ring's extent clipped."""
    rng = np.random.default_rng(3)
    det, paper = cam(clip=True), cam()
    n_partial = n_centre_out = 0
    for _ in range(300):
        R = Rotation.from_euler("zyx", rng.uniform(-20, 20, 3), degrees=True).as_matrix()
        centre = P + np.array([rng.uniform(1.5, 12), rng.uniform(-6, 6), rng.uniform(-4, 4)])
        normal = np.array([-1.0, rng.uniform(-0.6, 0.6), rng.uniform(-0.3, 0.3)])
        expect = _dense_visible_extent(R, centre, normal, 1.0)
        box = det.box_exact(P, R, centre, normal, 1.0)
        if expect is None or expect[2] - expect[0] < 2.0 or expect[3] - expect[1] < 2.0:
            assert box is None or min(box.w, box.h) < 3.0
            continue
        assert box is not None
        assert np.abs(np.subtract(box.xyxy, expect)).max() < 0.5
        whole = not (expect[0] > 0.01 and expect[2] < 639.99 and expect[1] > 0.01 and expect[3] < 479.99)
        n_partial += whole
        n_centre_out += paper.box_exact(P, R, centre, normal, 1.0) is None
    assert n_partial >= 50 and n_centre_out >= 20  # both cases were exercised


def test_looking_through_the_ring_sees_no_ring_and_close_arcs_fill_the_image():
    # 0.5 m before a 2 m ring, centred: the whole ring is outside the 67 deg field of view.
    assert cam(clip=True).box_exact(P, LEVEL, P + np.array([0.5, 0, 0]), FACING, 2.0) is None
    # 2 m before a 1 m ring centred 0.6 m up: its top arc is above the image (cut at v = 0), its lowest point
    # 0.4 m below the camera, its sides at +-1 m (the widest points, at the centre's height, are in view).
    box = cam(clip=True).box_exact(P, LEVEL, P + np.array([2.0, 0.0, 0.6]), FACING, 1.0)
    assert box is not None and box.xyxy[1] == pytest.approx(0.0, abs=1e-9)
    assert box.xyxy[3] == pytest.approx(240.0 + FX * 0.4 / 2.0, rel=1e-9)
    assert box.w == pytest.approx(2 * FX * 1.0 / 2.0, rel=1e-3)
