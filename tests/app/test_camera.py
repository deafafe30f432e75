"""Camera side of the app: a real video file through DeviceCamera, and the synthetic camera's geometry."""

from __future__ import annotations

import asyncio
import itertools
import math

import cv2
import numpy as np
import pytest

from companion.app.camera import CameraFailed, DeviceCamera
from companion.app.synthcam import SyntheticCamera, VehiclePose
from companion.config import load_config
from companion.frames import R_from_euler_ned_deg, quat_wxyz_from_R

pytestmark = pytest.mark.timeout(60)


def test_device_camera_reads_a_video_file_then_reports_its_end(tmp_path):
    path = str(tmp_path / "clip.avi")
    w = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (160, 120))
    for k in range(6):
        w.write(np.full((120, 160, 3), 40 * k, np.uint8))
    w.release()

    async def main() -> list:
        cam = DeviceCamera.open(path)
        frames = []
        try:
            with pytest.raises(CameraFailed, match="stream ended"):
                for _ in range(100):
                    frames.append(await asyncio.wait_for(cam.read(), 10.0))
        finally:
            cam.close()
        return frames

    frames = asyncio.run(main())
    assert 1 <= len(frames) <= 6  # newest-frame source: some may be dropped
    assert [f.index for f in frames] == list(range(1, len(frames) + 1))
    assert all(f.image.shape == (120, 160, 3) for f in frames)
    assert all(b.t > a.t for a, b in itertools.pairwise(frames))


def _pose(p_ned, yaw_deg, t=0.0):
    return VehiclePose(t, np.asarray(p_ned, float), quat_wxyz_from_R(R_from_euler_ned_deg(0.0, 0.0, yaw_deg)))


@pytest.mark.parametrize("yaw", [0.0, 90.0, -135.0])
def test_synthetic_gate_is_placed_ahead_and_boxed_where_the_geometry_says(yaw):
    cfg = load_config([], ["app.synthetic.motion=stationary", "app.synthetic.distance=20", "app.synthetic.radius=1",
                           "app.synthetic.lateral_offset=2", "sim.camera.pixel_noise=0"])
    pose = _pose([3.0, -4.0, -10.0], yaw)
    logged = []
    cam = SyntheticCamera(cfg, lambda: pose, render="geometric",
                          on_gate=lambda k, g, c, r, v: logged.append((k, c, r, v)))
    frame = cam.capture(1.0, pose)
    # Independent geometry: the gate is 20 m ahead along the heading and 2 m to the right, same height.
    psi = math.radians(yaw)
    fwd, right = np.array([math.cos(psi), math.sin(psi), 0.0]), np.array([-math.sin(psi), math.cos(psi), 0.0])
    c_ned = np.array([3.0, -4.0, -10.0]) + 20.0 * fwd + 2.0 * right
    k, c_enu, r, visible = logged[0]
    np.testing.assert_allclose([c_enu[1], c_enu[0], -c_enu[2]], c_ned, atol=1e-9)
    assert k == 1 and r == 1.0 and visible
    # Pinhole: the centre appears 2/20 of fx right of the principal point; the ring spans 2 f r / 20 px.
    fx = 320.0 / math.tan(math.radians(33.5))
    box = frame.box
    assert box.cx == pytest.approx(320.0 + fx * 2.0 / 20.0, abs=0.5)
    assert box.cy == pytest.approx(240.0, abs=0.5)
    assert box.h == pytest.approx(2 * fx * 1.0 / 20.0, rel=0.02)


def test_synthetic_gate_behind_the_camera_gives_no_box():
    cfg = load_config([], ["app.synthetic.motion=stationary", "sim.camera.pixel_noise=0"])
    first = _pose([0.0, 0.0, -10.0], 0.0)
    cam = SyntheticCamera(cfg, lambda: first, render="geometric")
    assert cam.capture(0.0, first).box is not None
    turned = _pose([0.0, 0.0, -10.0], 180.0)  # facing away from the gate
    assert cam.capture(0.1, turned).box is None


def test_rendered_and_geometric_cameras_agree_on_where_the_gate_is():
    """The two synthetic renderings, same pose: the drawn gate's true box = the projected box."""
    ov = ["app.synthetic.motion=stationary", "app.synthetic.distance=15", "app.synthetic.lateral_offset=-1.5",
          "app.synthetic.height_offset=0.5", "sim.camera.pixel_noise=0"]
    cfg = load_config([], ov)
    pose = _pose([1.0, 2.0, -8.0], 30.0)
    geo = SyntheticCamera(cfg, lambda: pose, render="geometric").capture(0.0, pose)
    img = SyntheticCamera(cfg, lambda: pose, render="image").capture(0.0, pose)
    assert img.image.shape == (480, 640, 3) and img.image.dtype == np.uint8 and img.box is None
    g, r = geo.box, img.truth_box
    # The renderer draws the outer rim of a ring with a 0.15 m frame; the geometric camera the 1 m circle.
    assert r.cx == pytest.approx(g.cx, abs=1.5) and r.cy == pytest.approx(g.cy, abs=1.5)
    assert r.w == pytest.approx(g.w, rel=0.03) and r.h == pytest.approx(g.h, rel=0.03)
    # And the image shows the gate there: its colour (BGR 0, 90, 255, unshaded) only inside that box.
    gate_px = np.abs(img.image.astype(int) - [0, 90, 255]).sum(axis=2) < 30
    x0, y0, x1, y1 = (int(v) for v in r.xyxy)
    inside = gate_px[y0:y1 + 1, x0:x1 + 1].sum()
    assert inside > 300 and inside >= 0.99 * gate_px.sum()
