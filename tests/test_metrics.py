"""Setpoint metrics against series whose answer is known by construction."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.metrics import max_tilt_deg, oscillation, tilt_deg


@settings(max_examples=200, deadline=None)
@given(st.floats(0.8, 6.0), st.floats(1.0, 60.0), st.floats(-30.0, 30.0), st.floats(0, 2 * math.pi))
def test_sine_amplitude_and_frequency(f: float, amp: float, bias: float, phase: float) -> None:
    t = np.arange(0.0, 6.0, 1.0 / 30.0)
    r = bias + 3.0 * t + amp * np.sin(2 * math.pi * f * t + phase)  # a trend must not count as oscillation
    o = oscillation(t, r)
    assert o.frequency_hz == pytest.approx(f, abs=0.3)
    # Hann-windowed peak of a sine between two bins: scalloping loss is at most ~15%.
    assert 0.8 * amp <= o.amplitude_deg <= 1.05 * amp
    # RMS of the derivative of A sin(wt) is A w / sqrt(2) (plus the trend's 3 deg/s).
    expect = math.sqrt((amp * 2 * math.pi * f) ** 2 / 2 + 9.0)
    assert o.rms_rate_dps == pytest.approx(expect, rel=0.1)


def test_steady_bank_is_not_an_oscillation() -> None:
    t = np.linspace(0.0, 3.0, 91)
    o = oscillation(t, np.full_like(t, 25.0))
    assert o.rms_rate_dps == 0.0
    assert o.amplitude_deg < 1e-9


def test_irregular_sampling_and_short_series() -> None:
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.02, 0.045, 150))
    o = oscillation(t, 20.0 * np.sin(2 * math.pi * 1.9 * t))
    assert o.frequency_hz == pytest.approx(1.9, abs=0.3)
    assert o.amplitude_deg > 15.0
    assert math.isnan(oscillation(t[:5], t[:5]).amplitude_deg)


def test_tilt_by_hand() -> None:
    assert tilt_deg(0.0, 0.0) == pytest.approx(0.0)
    assert tilt_deg(30.0, 0.0) == pytest.approx(30.0)
    assert tilt_deg(0.0, -40.0) == pytest.approx(40.0)
    # roll 45, pitch 45: thrust axis (sin p cos r, -sin r, cos p cos r) -> cos(tilt) = 1/2
    assert tilt_deg(45.0, 45.0) == pytest.approx(60.0)
    assert max_tilt_deg(np.array([0.0, 10.0, np.nan]), np.array([0.0, 50.0, 3.0])) == pytest.approx(
        math.degrees(math.acos(math.cos(math.radians(10)) * math.cos(math.radians(50)))))
