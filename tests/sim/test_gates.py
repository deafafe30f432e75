"""Gate motions against the paper's formulas (section V-A) and their top speeds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.sim.config import GateMotionConfig
from companion.sim.gates import MOTIONS, make_gate, motion_extremes, omega_for_top_speed

CFG = GateMotionConfig()
START = np.array([3.0, 20.0, 12.0])
NORMAL = np.array([0.0, -1.0, 0.0])  # gate faces south: the vehicle starts south of it


def gate(kind, seed=0):
    return make_gate(kind, START, NORMAL, rng=np.random.default_rng(seed), gates_cfg=CFG)


@pytest.mark.parametrize("kind", MOTIONS)
def test_every_motion_starts_at_the_start_position_with_a_fixed_horizontal_normal(kind):
    g = gate(kind, seed=5)
    assert np.allclose(g.position(0.0), START)
    assert np.allclose(g.normal, NORMAL)
    R = g.R_world_motion
    assert np.allclose(R.T @ R, np.eye(3)) and math.isclose(np.linalg.det(R), 1.0)


def test_planar_and_knot_follow_the_paper_formulas():
    # Motion frame for normal -y (south): x_M = n x z = east... computed independently here.
    x_m = np.cross(NORMAL, [0.0, 0.0, 1.0])
    y_m, z_m = NORMAL, np.array([0.0, 0.0, 1.0])
    for kind, d in (("planar", CFG.d_plan), ("knot", CFG.d_knot)):
        g = gate(kind, seed=2)
        w, ph = g.omega, g.phase
        for t in np.linspace(0.0, 7.0, 15):
            u = w * t + ph
            if kind == "planar":
                m = d * np.array([math.cos(u), math.cos(2 * u) / 2, 0.0])
            else:
                m = d * np.array([math.sin(3 * u) * (1 + math.cos(2 * u) / 2), math.sin(3 * u) * math.sin(2 * u),
                                  math.sin(4 * u)])
            expected = g.p0 + m[0] * x_m + m[1] * y_m + m[2] * z_m
            assert np.allclose(g.position(t), expected, atol=1e-12)


@pytest.mark.parametrize("kind", ["planar", "knot"])
def test_velocity_and_acceleration_are_the_derivatives_of_position(kind):
    g = gate(kind, seed=1)
    h = 1e-4
    for t in (0.3, 1.7, 4.2):
        fd_v = (g.position(t + h) - g.position(t - h)) / (2 * h)
        fd_a = (g.position(t + h) - 2 * g.position(t) + g.position(t - h)) / h**2
        assert np.allclose(g.velocity(t), fd_v, atol=1e-6)
        assert np.allclose(g.acceleration(t), fd_a, atol=1e-3)


@pytest.mark.parametrize(("kind", "top"), [("planar", 3.1), ("knot", 1.2)])
def test_omega_gives_the_papers_top_speed(kind, top):
    g = gate(kind)
    period = 2 * math.pi / g.omega
    ts = np.linspace(0.0, period, 20001)
    speeds = [np.linalg.norm(g.velocity(t)) for t in ts]
    assert math.isclose(max(speeds), top, rel_tol=1e-4)
    ext = motion_extremes(kind, CFG.d_plan if kind == "planar" else CFG.d_knot, top)
    accels = [np.linalg.norm(g.acceleration(t)) for t in ts]
    assert math.isclose(max(accels), ext["top_accel"], rel_tol=1e-3)


def test_planar_omega_closed_form():
    # Planar speed d w sqrt(sin^2 u + sin^2 2u) peaks at 1.25 d w (sin^2 u = 3/4 .. by hand: max of
    # s^2 + 4 s^2 c^2 = 5 s^2 - 4 s^4 at s^2 = 5/8 -> 25/16): w = v / (1.25 d).
    assert math.isclose(omega_for_top_speed("planar", 2.0, 3.1), 3.1 / 2.5, rel_tol=1e-6)


@pytest.mark.parametrize(("kind", "speed"), [("linear_slow", 2.5), ("linear_fast", 5.0)])
def test_linear_motions_move_sideways_at_constant_speed(kind, speed):
    signs = set()
    for seed in range(10):
        g = gate(kind, seed)
        v = g.velocity(3.0)
        assert math.isclose(np.linalg.norm(v), speed)
        assert abs(v @ NORMAL) < 1e-12 and abs(v[2]) < 1e-12  # in the gate plane, horizontal
        assert np.allclose(g.position(2.0), START + 2.0 * v)
        signs.add(float(np.sign(v[0])))
    assert signs == {-1.0, 1.0}


def test_start_phase_is_random_and_seeded():
    phases = [gate("planar", s).phase for s in range(5)]
    assert len(set(phases)) == 5
    assert gate("planar", 3).phase == gate("planar", 3).phase


def test_unknown_motion_is_one_clear_error():
    with pytest.raises(ValueError, match="unknown gate motion 'circle'"):
        make_gate("circle", START, NORMAL, rng=np.random.default_rng(0), gates_cfg=CFG)
