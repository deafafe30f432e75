"""The synthetic camera for PX4 (companion/app/synthcam.py) with the targets and motions of issue 19."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.app.synthcam import SyntheticCamera, VehiclePose
from companion.config import load_config
from companion.frames import R_from_euler_ned_deg, quat_wxyz_from_R

FX = 320.0 / math.tan(math.radians(33.5))


def _pose(p_ned, t=0.0):
    return VehiclePose(t, np.asarray(p_ned, float), quat_wxyz_from_R(R_from_euler_ned_deg(0.0, 0.0, 0.0)))


def test_a_receding_rectangle_on_the_ground() -> None:
    """A 2.5 x 3 m rectangle standing on the ground 20 m ahead (centre 1.5 m up), seen level from 1.5 m: its box
    is 2.5 / 20 x 3 / 20 of the focal length, centred; receding at 9 m/s it is 29 m away a second later."""
    cfg = load_config([], ["app.synthetic.motion=recede", "app.synthetic.distance=20", "sim.camera.pixel_noise=0",
                           "sim.target.shape=rectangle", "sim.target.width=2.5", "sim.target.height=3",
                           "sim.target.on_ground=true", "sim.gates.recede_speed=9"])
    pose = _pose([0.0, 0.0, -1.5])
    cam = SyntheticCamera(cfg, lambda: pose, render="geometric")
    b0 = cam.capture(0.0, pose).box
    assert b0.w == pytest.approx(FX * 2.5 / 20.0, rel=1e-6) and b0.h == pytest.approx(FX * 3.0 / 20.0, rel=1e-6)
    assert (b0.cx, b0.cy) == pytest.approx((320.0, 240.0), abs=1e-6)
    b1 = cam.capture(1.0, pose).box
    assert b1.h == pytest.approx(FX * 3.0 / 29.0, rel=1e-6)


def test_the_renderer_refuses_a_rectangle() -> None:
    cfg = load_config([], ["sim.target.shape=square"])
    pose = _pose([0.0, 0.0, -10.0])
    with pytest.raises(ValueError, match=r"sim\.target\.shape"):
        SyntheticCamera(cfg, lambda: pose, render="image")
