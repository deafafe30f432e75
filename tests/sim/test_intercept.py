"""The intercept of issue 19 in the in-process simulator: rectangular and ground targets, the recede and sinusoid
motions, and a pull-up that clears a receding truck (the paper's end-to-end experiment)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import CameraConfig, Config
from companion.evaluation.intercept import truck_overrides, wilson
from companion.sim.camera import GeometricCamera
from companion.sim.config import GateMotionConfig
from companion.sim.gates import make_gate
from companion.sim.runner import RunSpec, run_once, with_overrides
from companion.sim.scoring import distance_to_rect, predicted_miss, rect_basis
from perception.los import CameraModel

MODEL = CameraModel.from_config(CameraConfig())
FX = 320.0 / math.tan(math.radians(33.5))
P = np.array([0.0, 0.0, 10.0])
FACING = np.array([-1.0, 0.0, 0.0])


def test_rectangle_box_is_the_rectangles_not_a_rings() -> None:
    """A 2.5 m wide, 3 m high target 20 m ahead, head-on: a 2.5 / 20 x 3 / 20 box (times the focal length)."""
    cam = GeometricCamera(MODEL)
    cam.use_rectangle(2.5, 3.0)
    box = cam.box_exact(P, np.eye(3), P + np.array([20.0, 0.0, 0.0]), FACING, 1.25)
    assert box is not None
    assert box.w == pytest.approx(FX * 2.5 / 20.0, rel=1e-6)
    assert box.h == pytest.approx(FX * 3.0 / 20.0, rel=1e-6)
    assert (box.cx, box.cy) == pytest.approx((320.0, 240.0))
    # Clipped (detector-like) and seen from 1.5 m below its centre at 3 m: the top edge is in the image.
    cam.clip = True
    near = cam.box_exact(P, np.eye(3), P + np.array([3.0, 0.0, 1.5]), FACING, 1.25)
    assert near is not None
    assert near.xyxy[1] == pytest.approx(240.0 - FX * 3.0 / 3.0, abs=1e-6) or near.xyxy[1] <= 0.0
    assert near.xyxy[3] == pytest.approx(240.0, abs=1e-6)  # the bottom edge is at the camera's height


def test_recede_and_sinusoid_motions() -> None:
    rng = np.random.default_rng(1)
    gc = GateMotionConfig(recede_speed=9.0, sinusoid_amplitude=3.0 / math.pi, sinusoid_frequency=0.5)
    g = make_gate("recede", np.array([40.0, 0.0, 1.5]), FACING, rng=rng, gates_cfg=gc)
    assert g.position(2.0) == pytest.approx([58.0, 0.0, 1.5])  # away from the vehicle (at the origin side)
    s = make_gate("sinusoid", np.array([20.0, 0.0, 10.0]), FACING, rng=rng, gates_cfg=gc)
    assert s.position(0.0) == pytest.approx([20.0, 0.0, 10.0])
    ts = np.linspace(0.0, 2.0, 2001)
    pos = np.array([s.position(t) for t in ts])
    speed = np.linalg.norm(np.diff(pos, axis=0), axis=1) / np.diff(ts)
    assert speed.max() == pytest.approx(3.0, rel=1e-3)  # 2 pi f A
    assert np.ptp(pos[:, 0]) == 0.0 and np.ptp(pos[:, 2]) == 0.0  # lateral only (north for an east-facing gate)
    fd = (s.position(0.7 + 1e-6) - s.position(0.7 - 1e-6)) / 2e-6
    assert s.velocity(0.7) == pytest.approx(fd, abs=1e-6)


def test_scoring_geometry() -> None:
    b = rect_basis(FACING)
    c = np.array([10.0, 0.0, 1.5])
    assert distance_to_rect(np.array([10.0, 0.0, 4.0]), c, b, 1.25, 1.5) == pytest.approx(1.0)  # 1 m over the top
    assert distance_to_rect(np.array([8.0, 0.0, 1.5]), c, b, 1.25, 1.5) == pytest.approx(2.0)  # 2 m in front
    miss = predicted_miss(np.array([0.0, 0.3, 1.9]), np.array([20.0, 0.0, 0.0]), c, np.array([9.0, 0, 0]), FACING)
    assert miss == pytest.approx(0.5)
    lo, hi = wilson(95, 100)
    assert (lo, hi) == pytest.approx((0.8882, 0.9785), abs=1e-4)


def _truck(seed: int, ground: bool) -> dict:
    cfg = with_overrides(Config(), truck_overrides(speed=9.0, distance=40.0, ground=ground))
    return run_once(cfg, RunSpec("recede", seed=seed)).as_dict([1.0])


@pytest.mark.parametrize("ground", [False, True])
def test_pull_up_clears_a_receding_truck(ground: bool) -> None:
    """Issue 19: a 2.5 x 3 m target receding at 9 m/s from 40 m, on_close=pull_up: reached (predicted miss from the
    last velocity before the pull-up <= 0.9 m) and cleared by >= 1 m, without a floor trip on the ground. On the
    code before it, the pull-up fired at a time-to-contact of 0.25 s and cleared none (0 of 60)."""
    for seed in range(3):
        r = _truck(seed, ground)
        assert r["pullup_pulled_up"], r
        assert r["engagement_end"] == "HANDBACK", r  # OK (no floor trip, no abort)
        assert r["end_reason"] != "ground"
        assert r["pullup_predicted_miss_m"] <= 0.9, r
        assert r["pullup_clearance_m"] >= 1.0, r
        if ground:  # on the ground: the target's bottom is at z = 0, so the vehicle really went down to it
            assert r["altitude_m"] >= 4.0
