"""Hover thrust that matches the vehicle: drag along the thrust axis removed (companion/hover.py
thrust_specific_force), a heavier vehicle as one simulator setting (sim.quad.mass_scale), the estimate on by
default and unbiased in process."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import companion.core as core
from companion.config import load_config
from companion.hover import G, HoverConfig, thrust_specific_force
from companion.sim import runner
from companion.sim.dynamics import QuadParams, Quadrotor, QuadState


def test_a_horizontal_drag_is_removed_from_the_thrust_axis():
    R = Rotation.from_euler("ZYX", [40, -25, 20], degrees=True).as_matrix()  # body FRD -> NED, tilted 32 deg
    thrust = 11.0  # m/s^2 along -z body
    drag_ned = np.array([-2.0, 1.2, 0.0])  # horizontal airspeed: horizontal drag
    f = np.array([0.0, 0.0, -thrust]) + R.T @ drag_ned  # what the accelerometer reads
    assert thrust_specific_force(f, R) == pytest.approx(thrust, abs=1e-12)
    raw = thrust_specific_force(f, R, HoverConfig(drag_correction=False))
    assert raw == pytest.approx(-f[2]) and abs(raw - thrust) > 0.3  # the drag's share along the thrust axis
    tilted = Rotation.from_euler("ZYX", [0, -65, 0], degrees=True).as_matrix()
    assert math.isnan(thrust_specific_force(f, tilted))  # beyond max_tilt: no sample
    assert HoverConfig().estimate  # on by default


def test_mass_scale_is_a_heavier_vehicle_with_the_same_motors():
    p = QuadParams.from_config(load_config([], ["sim.quad.mass_scale=1.25"]))
    assert (p.mass, p.hover_thrust, p.thrust_to_weight) == pytest.approx((2.5, 0.625, 1.6))
    assert p.f_max == pytest.approx(G * 2.0 / 1.25)  # the same largest thrust in newtons over 1.25 x the mass
    # Physically: the true hover thrust holds it, the configured one sinks it.
    for u, sinks in ((0.625, False), (0.5, True)):
        quad = Quadrotor(p, QuadState(p=np.array([0.0, 0.0, 20.0]), f_th=G, on_ground=False))
        for _ in range(100):
            s = quad.step(0.01, np.array([0.0, 0.0, 0.0, 1.0]), u)
        assert bool(s.v[2] < -1.0) is sinks and bool(abs(s.v[2]) < 0.05) is not sinks
    explicit = QuadParams.from_config(load_config([], ["sim.quad.mass_scale=1.25", "sim.quad.hover_thrust=0.6"]))
    assert explicit.hover_thrust == 0.6 and explicit.thrust_to_weight == pytest.approx(1.6)
    with pytest.raises(ValueError, match=r"sim\.quad\.mass_scale 2"):
        QuadParams.from_config(load_config([], ["sim.quad.mass_scale=2"]))


def _final_estimates(monkeypatch, overrides):
    finals: list[float] = []
    orig = core.FlightCore._hover_update

    def spy(self, imu, thrust, a_up):
        e = orig(self, imu, thrust, a_up)
        if e is not None:
            self._last_estimate = e.hover_thrust
        return e

    monkeypatch.setattr(core.FlightCore, "_hover_update", spy)
    made = []
    real_from_config = core.FlightCore.from_config

    def from_config(*a, **k):
        c = real_from_config(*a, **k)
        made.append(c)
        return c

    monkeypatch.setattr(core.FlightCore, "from_config", from_config)
    cfg = load_config([], overrides)
    for seed in range(3):
        for motion in ("stationary", "planar"):
            made.clear()
            runner.run_once(cfg, runner.RunSpec(motion, seed))
            finals.append(made[0]._last_estimate)
    return np.array(finals)


def test_in_process_the_estimate_finds_a_heavier_vehicle_without_the_drag_bias(monkeypatch):
    """A vehicle 25 % heavier than configured (true hover thrust 0.625), flown at ~15 m/s: the estimate with the
    drag removed lands on it; the accelerometer's -z alone reads ~3 % high (the drag along the tilted thrust axis)."""
    fixed = _final_estimates(monkeypatch, ["sim.quad.mass_scale=1.25"])
    assert np.all(np.abs(fixed - 0.625) < 0.008), fixed
    raw = _final_estimates(monkeypatch, ["sim.quad.mass_scale=1.25", "hover.drag_correction=false"])
    assert raw.mean() > 0.635 and raw.mean() - 0.625 > 3 * abs(fixed.mean() - 0.625)
