"""Rendered frames: geometry against closed-form projections and the sim's geometric camera."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from perception.render import (
    HELDOUT_STYLE,
    TRAIN_STYLE,
    Gate,
    PinholeCamera,
    gate_box,
    look_at,
    random_gate_colour,
    random_scene,
    render_gate_frame,
)

CAM = PinholeCamera.default()
F = 320.0 / math.tan(math.radians(33.5))
R_FWD = look_at(np.zeros(3), np.array([1.0, 0.0, 0.0]))  # camera looks along world x (ENU east)


def test_look_at_is_a_rotation_with_image_y_down() -> None:
    assert np.allclose(R_FWD.T @ R_FWD, np.eye(3)) and np.linalg.det(R_FWD) == pytest.approx(1.0)
    assert np.allclose(R_FWD[:, 2], [1, 0, 0]) and np.allclose(R_FWD[:, 1], [0, 0, -1])


def test_fronto_parallel_ring_box_is_the_circle() -> None:
    """A ring facing the camera on the axis projects to a circle of radius f r / d about the principal point."""
    d, r = 12.0, 1.3
    gate = Gate(np.array([d, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]), r, "ring", (0, 0, 255), 0.2)
    img, box = render_gate_frame(CAM, R_FWD, np.zeros(3), gate, style=None)
    assert box is not None
    rad = F * r / d
    assert (box.cx, box.cy) == pytest.approx((320.0, 240.0), abs=1e-6)
    # the 72-gon touches the circle at 0/90 deg, so the extents are exact
    assert (box.w, box.h) == pytest.approx((2 * rad, 2 * rad), abs=1e-6)
    # Pixels: the middle of the frame band is the gate colour, the centre is the plain background.
    mid = F * (r - 0.1) / d
    assert tuple(img[240, round(320 + mid)]) == (0, 0, 255)
    assert tuple(img[round(240 - mid), 320]) == (0, 0, 255)
    assert tuple(img[240, 320]) == (128, 128, 128)


def test_square_gate_and_offset_box_match_pinhole() -> None:
    d, r = 10.0, 1.0
    c = np.array([d, -2.0, 1.0])  # 2 m right (ENU -y), 1 m up
    gate = Gate(c, np.array([1.0, 0.0, 0.0]), r, "square", (255, 0, 0), 0.2)
    _img, box = render_gate_frame(CAM, R_FWD, np.zeros(3), gate, style=None)
    assert box is not None
    u = 320 + F * 2.0 / d
    v = 240 - F * 1.0 / d
    assert (box.cx, box.cy) == pytest.approx((u, v), abs=1e-6)
    assert (box.w, box.h) == pytest.approx((2 * F * r / d, 2 * F * r / d), abs=1e-6)


def test_gate_behind_or_out_of_view_gives_no_box() -> None:
    gate = Gate(np.array([-5.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]), 1.0)
    img, box = render_gate_frame(CAM, R_FWD, np.zeros(3), gate, style=None)
    assert box is None and (img == 128).all()
    side = Gate(np.array([5.0, 30.0, 0.0]), np.array([1.0, 0.0, 0.0]), 1.0)
    assert render_gate_frame(CAM, R_FWD, np.zeros(3), side, style=None)[1] is None


def test_gate_being_passed_is_clipped_not_broken() -> None:
    """Camera inside the gate plane region: part of the ring is behind the camera; box clipped to the image."""
    gate = Gate(np.array([0.3, 0.0, 0.0]), np.array([0.5, 0.86, 0.0]), 1.5, "ring", (0, 255, 0), 0.3)
    img, box = render_gate_frame(CAM, R_FWD, np.zeros(3), gate, style=None)
    assert box is not None
    x0, y0, x1, y1 = box.xyxy
    assert 0 <= x0 < x1 <= 640 and 0 <= y0 < y1 <= 480
    green = (img[..., 1] == 255) & (img[..., 0] == 0)
    assert green.any()
    ys, xs = np.nonzero(green)
    # every drawn gate pixel lies inside the box (1 px of anti-aliasing slack)
    assert xs.min() >= x0 - 1 and xs.max() <= x1 + 1 and ys.min() >= y0 - 1 and ys.max() <= y1 + 1
    # ... and the box is tight around them
    assert xs.min() <= x0 + 2 and xs.max() >= x1 - 2 and ys.min() <= y0 + 2 and ys.max() >= y1 - 2
    # Half the ring is behind the camera: it is not drawn mirrored into the image.
    assert box.cx > 320


def test_box_agrees_with_the_sims_geometric_camera() -> None:
    """The closed loop swaps GeometricCamera for RenderedCamera: their boxes of the rim must agree."""
    from companion.config import load_config
    from companion.sim.camera import GeometricCamera
    from perception.los import CameraModel
    from perception.simcamera import RenderedCamera

    model = CameraModel.from_config(load_config().camera)
    geo = GeometricCamera(model, clip=True)  # a detector boxes the visible extent
    ren = RenderedCamera(model, pipeline=None, rng=np.random.default_rng(1))  # render() only: no pipeline needed
    rng = np.random.default_rng(11)
    compared = 0
    for _ in range(60):
        p = np.array([0.0, 0.0, 5.0])
        R = Rotation.from_euler("ZYX", rng.uniform(-0.3, 0.3, 3)).as_matrix()
        c = np.array([rng.uniform(4, 30), rng.uniform(-6, 6), 5 + rng.uniform(-3, 3)])
        n = np.array([1.0, rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3)])
        n /= np.linalg.norm(n)
        r = float(rng.uniform(0.5, 2.0))
        a = geo.box_exact(p, R, c, n, r)
        _img, b = ren.render(p, R, c, n, r)
        if a is None or GeometricCamera(model).box_exact(p, R, c, n, r) is None:
            continue  # centre out of view: the partial ring is compared in tests/sim/test_geometric_camera.py
        assert b is not None
        assert np.abs(np.subtract(a.xyxy, b.xyxy)).max() < 1.0
        compared += 1
    assert compared >= 30


def test_styles_are_reproducible_and_disjoint() -> None:
    a = random_scene(np.random.default_rng(5), CAM, TRAIN_STYLE)
    b = random_scene(np.random.default_rng(5), CAM, TRAIN_STYLE)
    assert np.array_equal(a[0], b[0]) and a[1] == b[1]
    c = random_scene(np.random.default_rng(6), CAM, TRAIN_STYLE)
    assert not np.array_equal(a[0], c[0])
    import colorsys

    rng = np.random.default_rng(0)
    for style in (TRAIN_STYLE, HELDOUT_STYLE):
        for _ in range(200):
            bgr = random_gate_colour(rng, style)
            h = colorsys.rgb_to_hsv(bgr[2] / 255, bgr[1] / 255, bgr[0] / 255)[0] * 360
            in_style = any(lo - 1 <= h <= hi + 1 for lo, hi in style.hue_ranges)
            assert in_style, (style.name, h)
    assert not set(TRAIN_STYLE.backgrounds) & set(HELDOUT_STYLE.backgrounds)


def test_gate_box_matches_render_box() -> None:
    gate = Gate(np.array([8.0, 1.0, 0.5]), np.array([1.0, 0.3, 0.1]), 0.8)
    _img, box = render_gate_frame(CAM, R_FWD, np.zeros(3), gate, TRAIN_STYLE, np.random.default_rng(0), t=2.5)
    assert box == gate_box(CAM, R_FWD, np.zeros(3), gate, t=2.5) and box.t == 2.5
