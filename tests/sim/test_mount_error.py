"""sim.camera.mount_error: the simulated cameras see through the true mount, the app keeps the configured one."""

from __future__ import annotations

import math

import numpy as np
import pytest

import companion.sim.runner as runner
from companion.app.synthcam import SyntheticCamera, VehiclePose
from companion.config import load_config
from companion.frames import R_from_euler_ned_deg, quat_wxyz_from_R
from companion.sim.camera import true_camera_config

pytestmark = pytest.mark.timeout(60)

FX = 320.0 / math.tan(math.radians(33.5))  # the default camera's focal length, px


def _expected(pitch: float, yaw: float) -> tuple[float, float]:
    """Where a point straight ahead (body x) appears through a camera yawed then pitched up (intrinsic Z, Y):
    camera forward = (cos y cos p, sin y cos p, -sin p), right = (-sin y, cos y, 0), down = (cos y sin p,
    sin y sin p, cos p) in body FRD, so body x has camera coordinates (-sin y, cos y sin p, cos y cos p)."""
    y, p = math.radians(yaw), math.radians(pitch)
    return 320.0 - FX * math.tan(y) / math.cos(p), 240.0 + FX * math.tan(p)


def _pose() -> VehiclePose:
    return VehiclePose(0.0, np.array([0.0, 0.0, -10.0]), quat_wxyz_from_R(R_from_euler_ned_deg(0.0, 0.0, 0.0)))


@pytest.mark.parametrize(("pitch", "yaw"), [(5.0, 0.0), (0.0, 3.0), (-5.0, -3.0)])
def test_a_gate_straight_ahead_renders_where_the_true_mount_puts_it(pitch, yaw):
    ov = ["app.synthetic.motion=stationary", "app.synthetic.distance=20", "sim.camera.pixel_noise=0",
          f"sim.camera.mount_error.pitch={pitch}", f"sim.camera.mount_error.yaw={yaw}"]
    cfg = load_config([], ov)
    assert cfg.camera.mount.pitch == 0.0 and cfg.camera.mount.yaw == 0.0  # the app's belief is unchanged
    u, v = _expected(pitch, yaw)
    pose = _pose()
    geo = SyntheticCamera(cfg, lambda: pose, render="geometric").capture(0.0, pose).box
    assert geo.cx == pytest.approx(u, abs=0.3) and geo.cy == pytest.approx(v, abs=0.3)
    if pitch == 5.0:
        assert geo.cy - 240.0 == pytest.approx(42.3, abs=0.2)  # the "42 px lower"
    # The drawn frame (the synthetic camera's rendered mode for PX4) puts the ring there too.
    img = SyntheticCamera(cfg, lambda: pose, render="image").capture(0.0, pose).truth_box
    assert img.cx == pytest.approx(u, abs=1.5) and img.cy == pytest.approx(v, abs=1.5)


def test_the_error_adds_to_a_configured_mount():
    cfg = load_config([], ["camera.mount.pitch=10", "sim.camera.mount_error.pitch=-4",
                           "sim.camera.mount_error.roll=2"])
    true = true_camera_config(cfg).mount
    assert (true.roll, true.pitch, true.yaw) == (2.0, 6.0, 0.0)
    plain = load_config([], [])
    assert true_camera_config(plain) is plain.camera  # no error: the configured camera itself
    with pytest.raises(ValueError, match=r"sim\.camera\.mount_error"):
        true_camera_config(load_config([], ["camera.mount.pitch=-60", "sim.camera.mount_error.pitch=-40"]))


def test_the_in_process_runner_builds_its_camera_through_the_true_mount(monkeypatch):
    """Both in-process cameras (geometric and rendered) get their model from the same line of run_once."""
    seen = []

    class Stop(Exception):
        pass

    def fake_camera(model, *a, **k):
        seen.append(model)
        raise Stop

    monkeypatch.setattr(runner, "GeometricCamera", fake_camera)
    cfg = load_config([], ["sim.camera.mount_error.pitch=5"])
    with pytest.raises(Stop):
        runner.run_once(cfg, runner.RunSpec("stationary", 0))
    expected = true_camera_config(cfg).R_body_cam
    np.testing.assert_allclose(seen[0].R_body_cam, expected, atol=1e-12)
    assert not np.allclose(expected, cfg.camera.R_body_cam, atol=1e-3)
    # Optical axis 5 deg above body x (FRD: z negative).
    assert math.degrees(math.asin(-expected[2, 2])) == pytest.approx(5.0, abs=1e-9)
