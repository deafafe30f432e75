"""Closing-speed estimator (companion/closing.py) and the controller's use of it and of the accelerometer."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.closing import ClosingParams, ClosingSpeedEstimator
from companion.config import CameraConfig, load_config
from companion.controller import PNController
from companion.sim.camera import GeometricCamera
from perception.los import CameraModel
from perception.types import BoundingBox

MODEL = CameraModel.from_config(CameraConfig())
P = np.array([0.0, 0.0, 10.0])
LEVEL = np.eye(3)  # body FLU = world ENU: looking east
LEVEL_Q = np.array([1.0, 0.0, 0.0, 0.0])


@settings(max_examples=200, deadline=None)
@given(k=st.floats(5.0, 60.0), y=st.floats(-0.35, 0.35), z=st.floats(-0.25, 0.25), r=st.floats(0.3, 2.0),
       yaw=st.floats(-40.0, 40.0))
def test_range_from_the_box_of_a_projected_ring(k, y, z, r, yaw) -> None:
    """Independent: the simulator's exact projection of a ring (range k ring radii, k >= 5); off-centre and
    turned up to 40 deg."""
    d = k * r
    centre = P + d * np.array([1.0, y, z]) / math.sqrt(1 + y * y + z * z)
    n = -np.array([math.cos(math.radians(yaw)), math.sin(math.radians(yaw)), 0.0])
    box = GeometricCamera(MODEL).box_exact(P, LEVEL, centre, n, r)
    est = ClosingSpeedEstimator(ClosingParams(gate_radius=r, v_rel_bar=15.0), MODEL)
    got = est.range_from_box(box) if box is not None else None
    if got is None:  # only a box cut by the image border may give no range
        x0, y0, x1, y1 = box.xyxy
        assert min(x0, y0) <= 1.0 or x1 >= MODEL.width - 1.0 or y1 >= MODEL.height - 1.0
        return
    # A turned ring keeps its diameter vertically here; foreshortening and perspective keep the estimate within
    # a few % (long rather than short: a long range means a high closing speed, the safe side for PN).
    assert d * 0.97 <= got <= d * 1.05


def test_cut_box_gives_no_range() -> None:
    est = ClosingSpeedEstimator(ClosingParams(gate_radius=1.0, v_rel_bar=15.0), MODEL)
    assert est.range_from_box(BoundingBox(20.0, 240.0, 60.0, 420.0)) is not None  # height inside
    assert est.range_from_box(BoundingBox(20.0, 0.0, 60.0, 500.0)) is None  # cut on both axes


def approach(est: ClosingSpeedEstimator, v_close: float, d0: float, seconds: float, rng, imu: bool = False,
             noise: float = 1.0) -> list[float]:
    """A ring straight ahead approached at constant speed; boxes with pixel noise at 30 Hz."""
    out = []
    fx = MODEL.K[0, 0]
    for k in range(int(seconds * 30)):
        t = k / 30
        d = d0 - v_close * t
        size = 2 * fx * est.p.gate_radius / d + rng.normal(0.0, noise)
        est.update(t, BoundingBox(320.0 + rng.normal(0, noise), 240.0, size, size), 0.0 if imu else None)
        out.append(est.speed())
    return out


def test_estimate_starts_at_the_bound_and_lowers_on_evidence() -> None:
    rng = np.random.default_rng(0)
    p = ClosingParams(gate_radius=1.0, v_rel_bar=15.0, margin=1.0, loop_lag=0.0)
    est = ClosingSpeedEstimator(p, MODEL)
    assert est.speed() == 15.0  # no evidence yet: the paper's bound
    speeds = approach(est, 4.4, 25.0, 3.0, rng)
    assert speeds[0] == pytest.approx(15.0, abs=1e-9) or speeds[0] >= 14.0
    assert -est.x[1] == pytest.approx(4.4, abs=0.5)  # the range rate the image shows
    assert 4.4 <= speeds[-1] <= 6.5  # upper confidence value: errs high
    assert all(s <= 15.0 for s in speeds)


def test_imu_sharpens_the_estimate() -> None:
    """With the IMU explaining our own (here: zero) acceleration the process noise is smaller: tighter sigma."""
    p = ClosingParams(gate_radius=1.0, v_rel_bar=15.0, margin=1.0, loop_lag=0.0)
    a, b = ClosingSpeedEstimator(p, MODEL), ClosingSpeedEstimator(p, MODEL)
    approach(a, 5.0, 25.0, 3.0, np.random.default_rng(1), imu=False)
    approach(b, 5.0, 25.0, 3.0, np.random.default_rng(1), imu=True)
    assert b.P[1, 1] < a.P[1, 1]
    assert -b.x[1] == pytest.approx(5.0, abs=0.4)


def test_lag_cap_near_the_gate() -> None:
    """Near the gate the speed in the PN law is capped at range / (lag_margin (loop lag + frame age))."""
    p = ClosingParams(gate_radius=1.0, v_rel_bar=15.0, margin=5.0, loop_lag=0.34, lag_margin=1.0)
    est = ClosingSpeedEstimator(p, MODEL)
    approach(est, 4.4, 25.0, 4.5, np.random.default_rng(2))
    d = est.range
    assert d is not None and 3.0 < d < 7.0
    assert est.speed() == pytest.approx(min(15.0, d / 0.34), rel=1e-9)
    assert est.speed(latency=0.3) == pytest.approx(d / 0.64, rel=1e-9)
    assert est.speed(lambda_dot=0.0) >= p.v_min


def test_fixed_mode_is_the_paper() -> None:
    cfg = load_config(overrides=["guidance.closing_speed=fixed", "guidance.drag_compensation=0"])
    c = PNController.from_config(cfg)
    out = None
    for k in range(10):
        out = c.step(k / 30, BoundingBox(320 + 2 * k, 240, 30, 30), LEVEL_Q, np.array([0.0, 2.0, -9.81]))
    assert out is not None and out.v_rel == 15.0
    assert np.allclose(out.a_n, 2.1 * 15.0 * out.lambda_dot * out.a_n / np.linalg.norm(out.a_n))


def test_sideways_drag_is_compensated_along_the_pn_y_axis_only() -> None:
    """Accelerometer FRD y = -2 m/s^2 (drag pushing left, level vehicle looking north): the demand gains
    +2 m/s^2 to the right (east), nothing vertical, nothing along the LOS."""
    base = load_config(overrides=["guidance.closing_speed=fixed"])
    with_dc = PNController.from_config(base)
    without = PNController.from_config(load_config(overrides=["guidance.closing_speed=fixed",
                                                              "guidance.drag_compensation=0"]))
    acc = np.array([-1.5, -2.0, -9.81])  # FRD: drag back and left; thrust up
    for k in range(5):
        o1 = with_dc.step(k / 30, BoundingBox(320, 240, 30, 30), LEVEL_Q, acc)
        o0 = without.step(k / 30, BoundingBox(320, 240, 30, 30), LEVEL_Q, acc)
    diff = o1.a_n - o0.a_n  # ENU; LOS north = +y
    assert np.allclose(diff, [2.0, 0.0, 0.0], atol=1e-9)


def test_no_accelerometer_no_drag_compensation() -> None:
    c = PNController.from_config(load_config())
    for k in range(5):
        o = c.step(k / 30, BoundingBox(320, 240, 30, 30), LEVEL_Q)
    assert np.allclose(o.a_n, 0.0)


def test_a_box_filling_the_view_ends_the_ranges_until_reset() -> None:
    """A ring whose box reaches ``max_box`` of the image's smaller side fills the view: from then on no box gives a
    range (the background boxes after a crossing are the same size and say "2 m away"); the filter dead-reckons."""
    est = ClosingSpeedEstimator(ClosingParams(gate_radius=1.0, v_rel_bar=15.0, max_box=0.8), MODEL)
    small, big = BoundingBox(320, 240, 100, 100), BoundingBox(320, 240, 0.8 * 480 + 1, 0.8 * 480 + 1)
    assert est.range_from_box(small) is not None and not est.filled
    est.update(0.0, small)
    est.update(0.1, big)
    assert est.filled and est.t_range == 0.0  # the big box gave no range
    assert est.range_from_box(small) is None  # nor does any box after it
    d0, v0 = est.state
    est.update(0.2, small, 0.0)
    assert est.t_range == 0.0 and est.state == pytest.approx((d0 + 0.1 * v0, v0))  # predicted only
    est.reset()
    assert not est.filled and est.range_from_box(small) is not None
    off = ClosingSpeedEstimator(ClosingParams(gate_radius=1.0, v_rel_bar=15.0), MODEL)  # max_box 0: off
    assert off.range_from_box(BoundingBox(320, 240, 470, 470)) is not None and not off.filled
