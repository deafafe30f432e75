"""The controller object: its inputs (no position, no velocity), its state, and its handling of bad frames."""

from __future__ import annotations

import inspect
import math
import typing

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from companion import frames, metrics
from companion.config import Config, load_config
from companion.controller import ControlOutput, PNController
from perception.types import BoundingBox

LEVEL = np.array([1.0, 0.0, 0.0, 0.0])


@pytest.fixture
def ctrl() -> PNController:
    return PNController.from_config(load_config())


def test_step_accepts_no_position_or_velocity() -> None:
    sig = inspect.signature(PNController.step)
    # Box, attitude estimate, optionally the accelerometer (specific force) and the current time: nothing else.
    assert list(sig.parameters) == ["self", "t", "box", "q_wxyz_ned_frd", "accel_frd", "t_now"]
    hints = typing.get_type_hints(PNController.step)
    assert hints["box"] == BoundingBox | None
    assert hints["accel_frd"] == np.ndarray | None and hints["t_now"] == float | None
    forbidden = ("pos", "vel", "gps", "ekf", "odom", "truth", "state")
    for name in list(sig.parameters) + [f for f in BoundingBox.__dataclass_fields__]:
        assert not any(w in name.lower() for w in forbidden), name
    c = PNController.from_config(load_config())
    with pytest.raises(TypeError):
        c.step(0.0, None, LEVEL, position=np.zeros(3))  # type: ignore[call-arg]


def test_hover_before_any_los_then_pn(ctrl) -> None:
    yawed = frames.quat_wxyz_from_R(frames.R_from_euler_ned_deg(0, 0, 40.0))
    out = ctrl.step(0.0, None, yawed)
    assert out.mode == "hover" and out.los_ned is None
    assert out.setpoint.yaw_deg == pytest.approx(40.0)
    assert out.setpoint.thrust == pytest.approx(0.5)
    out = ctrl.step(1 / 30, BoundingBox(320, 240, 30, 30), yawed)
    assert out.mode == "pn" and out.rejected is None
    # The gate dead ahead of a vehicle yawed 40 deg: LOS along the nose, setpoint yaw 40, nose down gamma_bar.
    assert np.allclose(out.los_ned, [math.cos(math.radians(40)), math.sin(math.radians(40)), 0.0])
    assert out.setpoint.yaw_deg == pytest.approx(40.0)
    assert out.setpoint.pitch_deg == pytest.approx(-21.05)


def test_garbage_boxes_are_rejected_and_the_setpoint_stays_finite(ctrl) -> None:
    ctrl.step(0.0, BoundingBox(320, 240, 30, 30), LEVEL)
    bad = [BoundingBox(math.nan, 240, 30, 30), BoundingBox(320, math.inf, 30, 30), BoundingBox(320, 240, -5, 30),
           BoundingBox(5000, 240, 30, 30), BoundingBox(320, 240, 30, 30, confidence=math.nan)]
    for k, box in enumerate(bad, start=1):
        out = ctrl.step(k / 30, box, LEVEL)
        assert out.mode == "coast" and out.rejected and "invalid box" in out.rejected
        sp = out.setpoint
        assert all(math.isfinite(x) for x in (sp.roll_deg, sp.pitch_deg, sp.yaw_deg, sp.thrust))
    assert ctrl.step(10 / 30, None, LEVEL).rejected == "no box"


def test_time_must_advance(ctrl) -> None:
    ctrl.step(1.0, BoundingBox(320, 240, 30, 30), LEVEL)
    assert ctrl.step(1.0, BoundingBox(320, 240, 30, 30), LEVEL).rejected == "frame time not after the previous one"
    assert ctrl.step(0.5, BoundingBox(320, 240, 30, 30), LEVEL).mode == "coast"
    assert ctrl.step(math.nan, BoundingBox(320, 240, 30, 30), LEVEL).rejected == "non-finite frame time"


def test_los_jump_rejected_then_reacquired(ctrl) -> None:
    for k in range(5):
        ctrl.step(k / 30, BoundingBox(320, 240, 30, 30), LEVEL)
    # The tracker switches to something 150 px away (~17 deg in one frame: ~9 rad/s > max_rate 3 rad/s).
    outs = [ctrl.step((5 + k) / 30, BoundingBox(470, 240, 30, 30), LEVEL) for k in range(4)]
    assert [o.rejected is not None and "LOS jump" in o.rejected for o in outs[:2]] == [True, True]
    assert outs[0].mode == "coast"
    # It persisted for three frames: accepted as a re-acquisition, the filter restarts there (no rate spike).
    assert outs[2].rejected is None and outs[2].mode == "pn" and outs[2].lambda_dot == 0.0
    assert outs[3].lambda_dot < 0.5


def test_vehicle_rotation_is_not_los_rate(ctrl) -> None:
    """A fixed target seen from a rotating vehicle: the box moves, the inertial LOS must not."""
    fx = ctrl.camera.K[0, 0]
    target = np.array([1.0, 0.0, 0.0])  # NED: due north, level
    rates = []
    for k in range(30):
        yaw = 10.0 * math.sin(k / 5)  # the vehicle yaws back and forth by +-10 deg
        R = frames.R_from_euler_ned_deg(0.0, 0.0, yaw)
        d = R.T @ target  # target direction in the body
        box = BoundingBox(320 + fx * d[1] / d[0], 240 + fx * d[2] / d[0], 30, 30)
        rates.append(ctrl.step(k / 30, box, frames.quat_wxyz_from_R(R)).lambda_dot)
    assert max(rates) < 1e-9


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), cx=st.floats(0, 640), cy=st.floats(0, 480))
def test_any_attitude_and_box_gives_a_finite_setpoint_within_limits(seed, cx, cy) -> None:
    cfg = Config()
    c = PNController.from_config(cfg)
    rot = Rotation.random(2, random_state=seed)
    outs: list[ControlOutput] = []
    for k, r in enumerate(rot):
        x, y, z, w = r.as_quat()
        outs.append(c.step(k / 30, BoundingBox(cx + k, cy, 20, 20), np.array([w, x, y, z])))
    for o in outs:
        sp = o.setpoint
        assert all(math.isfinite(v) for v in (sp.roll_deg, sp.pitch_deg, sp.yaw_deg, sp.thrust))
        assert cfg.airframe.thrust_min <= sp.thrust <= 1.0
        # The flight envelope holds whatever the LOS: tilt of the thrust axis, measured from the Euler angles.
        assert float(metrics.tilt_deg(sp.roll_deg, sp.pitch_deg)) <= cfg.airframe.max_tilt + 1e-6
        if o.los_ned is not None:
            # The commanded optical axis stays within gamma_bar of the LOS, unless the LOS is steeper than the
            # tilt envelope lets the optical axis follow (then it is exactly as far off as the envelope forces).
            ang = math.degrees(math.acos(min(1.0, float(sp.R_ned_frd[:, 0] @ o.los_ned))))
            elevation = math.degrees(math.asin(min(1.0, abs(float(o.los_ned[2])))))
            assert ang <= max(cfg.guidance.gamma_bar, elevation - cfg.airframe.max_tilt) + 1e-6


def test_hover_thrust_from_the_autopilot(ctrl) -> None:
    c2 = ctrl.with_hover_thrust(0.62, 2.0)
    out = c2.step(0.0, None, LEVEL)
    assert out.setpoint.thrust == pytest.approx(0.62)
    out = c2.step(1 / 30, BoundingBox(320, 240, 30, 30), LEVEL)
    assert out.setpoint.thrust == pytest.approx(0.62 / math.cos(math.radians(21.05)))
    with pytest.raises(ValueError):
        ctrl.with_hover_thrust(0.0, 2.0)
