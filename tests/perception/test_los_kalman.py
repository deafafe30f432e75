"""LosKalman (perception/los.py): the constant-velocity Kalman filter on the unit LOS, and its use by the controller."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config import load_config
from companion.controller import PNController
from perception.los import LosKalman, LosKalmanParams
from perception.types import BoundingBox

PARAMS = LosKalmanParams(accel_std=0.5, gate=4.0, reacquire=3, max_dt=0.5)
SIGMA = math.radians(0.3)
LEVEL = np.array([1.0, 0.0, 0.0, 0.0])


def _great_circle(axis: np.ndarray, start: np.ndarray, omega: float):
    """l(t) rotating at omega (rad/s) about the unit axis (start made normal to it): a constant LOS rate."""
    a = start - float(start @ axis) * axis
    a /= np.linalg.norm(a)
    b = np.cross(axis, a)

    def los(t: float) -> tuple[np.ndarray, np.ndarray]:
        c, s = math.cos(omega * t), math.sin(omega * t)
        return c * a + s * b, omega * (-s * a + c * b)  # l and dl/dt

    return los


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


vectors = st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 0.2)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(axis=vectors, start=vectors, omega=st.floats(0.0, 1.0), rate_hz=st.sampled_from([15.0, 30.0, 60.0]),
       seed=st.integers(0, 10_000))
def test_converges_on_a_constant_rate_los(axis, start, omega, rate_hz, seed):
    axis, start = _unit(axis), _unit(start)
    if abs(float(axis @ start)) > 0.95:
        return  # start (almost) on the axis: no well-defined circle
    los = _great_circle(axis, start, omega)
    kf = LosKalman(PARAMS)
    rng = np.random.default_rng(seed)
    errs = []
    for k in range(int(4.0 * rate_hz)):
        t = k / rate_hz
        l_true, rate_true = los(t)
        noisy = _unit(l_true + rng.normal(0.0, SIGMA, 3))
        assert kf.update(t, noisy, SIGMA) or k > 0
        if t > 2.5:
            errs.append((math.acos(min(1.0, float(kf.l @ l_true))), float(np.linalg.norm(kf.rate - rate_true)),
                         math.acos(min(1.0, float(noisy @ l_true)))))
    e = np.array(errs)
    # Converged: the filtered LOS closer to the truth than the measurements, and the rate within 0.15 rad/s on
    # average (differencing two measurements with this noise at 30 Hz: ~0.3 rad/s).
    assert e[:, 0].mean() < e[:, 2].mean() and e[:, 1].mean() < 0.15
    assert abs(float(kf.rate @ kf.l)) < 1e-9 and math.isclose(float(np.linalg.norm(kf.l)), 1.0, rel_tol=1e-12)


def test_noise_free_constant_rate_is_tracked_exactly_enough():
    los = _great_circle(_unit([0.0, 0.0, 1.0]), _unit([1.0, 0.0, 0.0]), 0.8)
    kf = LosKalman(PARAMS)
    for k in range(120):
        kf.update(k / 30, los(k / 30)[0], SIGMA)
    l_true, rate_true = los(119 / 30)
    assert float(np.linalg.norm(kf.rate - rate_true)) < 0.02  # within 2.5 % of 0.8 rad/s
    assert math.degrees(math.acos(min(1.0, float(kf.l @ l_true)))) < 0.1


def test_an_injected_jump_is_rejected_and_the_prediction_kept():
    los = _great_circle(_unit([0.0, 0.0, 1.0]), _unit([1.0, 0.0, 0.0]), 0.5)
    kf = LosKalman(PARAMS)
    for k in range(60):
        assert kf.update(k / 30, los(k / 30)[0], SIGMA)
    t = 60 / 30
    wrong = _unit(los(t)[0] + np.array([0.0, 0.0, 0.15]))  # ~8.5 deg off: a box on something else
    assert not kf.update(t, wrong, SIGMA)
    assert kf.last_nis > PARAMS.gate and kf.rejections == 1
    assert math.degrees(math.acos(min(1.0, float(kf.l @ los(t)[0])))) < 0.1  # the prediction, not the jump
    assert float(np.linalg.norm(kf.rate - los(t)[1])) < 0.02
    assert kf.update(61 / 30, los(61 / 30)[0], SIGMA) and kf.rejections == 0  # the true LOS is taken again


def test_a_persistent_jump_is_a_new_target():
    kf = LosKalman(PARAMS)
    for k in range(30):
        kf.update(k / 30, _unit([1.0, 0.0, 0.0]), SIGMA)
    new = _unit([1.0, 0.3, 0.0])
    assert not kf.update(30 / 30, new, SIGMA)
    assert not kf.update(31 / 30, new, SIGMA)
    assert kf.update(32 / 30, new, SIGMA)  # the third in a row: restart there
    assert np.allclose(kf.l, new) and np.allclose(kf.rate, 0.0) and kf.rejections == 0


def test_a_gap_restarts_the_filter_and_time_must_advance():
    kf = LosKalman(PARAMS)
    kf.update(0.0, _unit([1.0, 0.0, 0.0]), SIGMA)
    kf.update(0.1, _unit([1.0, 0.01, 0.0]), SIGMA)
    assert float(np.linalg.norm(kf.rate)) > 0.0
    far = _unit([0.0, 1.0, 0.0])
    assert kf.update(0.1 + PARAMS.max_dt + 0.01, far, SIGMA)  # long gap: no gating, a fresh start
    assert np.allclose(kf.l, far) and np.allclose(kf.rate, 0.0)
    assert kf.update(0.1 + PARAMS.max_dt + 0.01, _unit([1.0, 0.0, 0.0]), SIGMA)  # same time again: restart too
    with pytest.raises(ValueError):
        LosKalman(LosKalmanParams(accel_std=0.0, gate=4.0))


@settings(max_examples=200, deadline=None, derandomize=True)
@given(steps=st.lists(st.tuples(vectors, st.floats(1e-4, 1.0), st.floats(1e-6, 0.5)), min_size=1, max_size=40))
def test_no_nan_whatever_the_input(steps):
    kf = LosKalman(PARAMS)
    t = 0.0
    for v, dt, sigma in steps:
        t += dt
        kf.update(t, _unit(v), sigma)
        assert np.all(np.isfinite(kf.l)) and np.all(np.isfinite(kf.rate)) and np.all(np.isfinite(kf.P))
        assert math.isclose(float(np.linalg.norm(kf.l)), 1.0, rel_tol=1e-9)
        assert abs(float(kf.rate @ kf.l)) < 1e-9
        assert kf.P[0, 0] > 0.0 and kf.P[1, 1] > 0.0 and np.linalg.det(kf.P) > -1e-18


def test_controller_with_the_kalman_filter_gates_a_wrong_box_and_keeps_flying():
    ctrl = PNController.from_config(load_config([], ["los_filter.kind=kalman", "los_filter.kalman_accel=0.5"]))
    for k in range(30):
        out = ctrl.step(k / 30, BoundingBox(320 + 2 * k, 240, 40, 40), LEVEL)
        assert out.mode == "pn" and out.rejected is None
    lam = out.lambda_dot
    assert lam > 0.0
    out = ctrl.step(30 / 30, BoundingBox(320 + 60 + 35, 240 - 25, 30, 30), LEVEL)  # a box on something else
    assert out.mode == "pn" and out.rejected is not None and out.rejected.startswith("innovation gate")
    assert math.isclose(out.lambda_dot, lam, rel_tol=0.2)  # the prediction carries on
    out = ctrl.step(31 / 30, BoundingBox(320 + 62, 240, 40, 40), LEVEL)
    assert out.rejected is None
    # Low-pass default unchanged: the same box sequence gives no gate at all.
    lp = PNController.from_config(load_config())
    assert lp.p.los_kalman is None
