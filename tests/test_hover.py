"""Hover-thrust estimator (companion/hover.py) on synthetic data with a known answer."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config import load_config
from companion.controller import PNController
from companion.hover import G, HoverConfig, HoverThrustEstimator, use_hover_thrust
from perception.types import BoundingBox


def _fly(est: HoverThrustEstimator, hover_true: float, n: int, rng: np.random.Generator | None,
         noise: float = 0.0, tau: float = 0.03, dt: float = 1 / 30, u_range=(0.4, 0.9)) -> list[float]:
    """Commands change every frame; the true thrust lags them (exact first-order, sub-stepped)."""
    rng = rng or np.random.default_rng(0)
    u_lag = u = 0.6
    out = []
    for k in range(1, n + 1):
        for _ in range(10):  # the true lag, integrated finely
            u_lag += (u - u_lag) * (1 - math.exp(-dt / 10 / tau))
        a_up = G / hover_true * u_lag + rng.normal(0, noise)
        est.update(k * dt, u, a_up)  # u was the command over the interval ending now
        out.append(est.hover_thrust)
        u = float(rng.uniform(*u_range))
    return out


def test_converges_to_the_true_hover_thrust_from_25_percent_off():
    est = HoverThrustEstimator(0.5, HoverConfig(noise=0.3))
    h = _fly(est, 0.625, 60, np.random.default_rng(1), noise=0.1)
    assert est.ready and h[-1] == pytest.approx(0.625, rel=0.01)
    assert abs(h[9] - 0.625) < 0.02  # within 10 frames (a third of a second) it is most of the way
    e = est.estimate()
    assert e.samples == 59 and 0 < e.std < 0.01  # the first sample only starts the lag state


@settings(max_examples=60, deadline=None)
@given(hover_true=st.floats(0.3, 0.8), offset=st.floats(-0.35, 0.35), tau=st.floats(0.0, 0.1))
def test_noise_free_data_give_the_answer(hover_true, offset, tau):
    hover0 = min(hover_true * (1 + offset), 0.9)
    est = HoverThrustEstimator(hover0, HoverConfig(tau_thrust=tau, max_change=0.6))
    h = _fly(est, hover_true, 40, None, tau=max(tau, 1e-6))
    assert h[-1] == pytest.approx(hover_true, rel=0.005)


def test_saturated_or_free_fall_samples_carry_no_information():
    est = HoverThrustEstimator(0.5)
    for k in range(1, 50):
        assert est.update(k / 30, 1.0, 30.0) is None  # full thrust: the true thrust is capped
    for k in range(50, 100):
        assert est.update(k / 30, 0.6, 0.5) is None  # near free fall (thrown, falling): not a flight sample
    assert est.samples == 0 and est.hover_thrust == 0.5


def test_estimate_stays_within_its_bounds_and_ignores_non_finite_input():
    est = HoverThrustEstimator(0.5, HoverConfig(max_change=0.2))
    _fly(est, 0.9, 80, None)
    assert est.hover_thrust == pytest.approx(0.6)
    est.update(10.0, math.nan, 9.8)
    est.update(10.1, 0.5, math.inf)
    assert est.hover_thrust == pytest.approx(0.6)
    with pytest.raises(ValueError):
        HoverThrustEstimator(0.99)


def test_use_hover_thrust_equals_a_fresh_controller_but_keeps_the_filter():
    cfg = load_config()
    a = PNController.from_config(cfg)
    b = PNController.from_config(cfg).with_hover_thrust(0.62, cfg.airframe.thrust_to_weight)
    q = np.array([1.0, 0.0, 0.0, 0.0])
    box = BoundingBox(330.0, 235.0, 40.0, 40.0, 0.9)
    a.step(0.0, box, q)
    assert a.has_los
    use_hover_thrust(a, 0.62, cfg.airframe.thrust_to_weight)
    assert a.has_los  # the LOS filter survived
    assert a.p == b.p
    b.step(0.0, box, q)
    oa = a.step(1 / 30, BoundingBox(332.0, 236.0, 41.0, 41.0, 0.9), q)
    ob = b.step(1 / 30, BoundingBox(332.0, 236.0, 41.0, 41.0, 0.9), q)
    assert oa.setpoint.thrust == pytest.approx(ob.setpoint.thrust) and oa.f_th == pytest.approx(ob.f_th)


def test_use_hover_thrust_also_moves_the_engagements_pass_and_recovery():
    from companion.engagement import Engagement

    cfg = load_config()
    ctrl = PNController.from_config(cfg)
    eng = Engagement.from_config(cfg, ctrl)
    use_hover_thrust(ctrl, 0.625, cfg.airframe.thrust_to_weight, eng)
    assert eng.params.hover_thrust == 0.625
    assert eng.params.f_max == pytest.approx(ctrl.p.guidance.f_max) and eng.params.f_min == pytest.approx(
        ctrl.p.guidance.f_min)
    assert eng.params.f_max == pytest.approx(G * 1.6)  # 1 / 0.625: full thrust is the limit now
    assert eng._recover_setpoint(np.array([1.0, 0, 0, 0])).thrust == pytest.approx(
        min(1.0, 0.625 * cfg.app.recover_thrust_scale))
