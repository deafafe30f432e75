"""Quadrotor dynamics (eq:meth_quadrotor_dynamics): hover, held tilt, drag-limited speed, ground."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from companion.sim.dynamics import G, QuadParams, Quadrotor, QuadState

LEVEL = np.array([0.0, 0.0, 0.0, 1.0])


def airborne(v=(0.0, 0.0, 0.0), q=LEVEL, f_th=G) -> QuadState:
    return QuadState(p=np.array([0.0, 0.0, 10.0]), v=np.array(v, float), q=np.array(q, float),
                     f_th=f_th, on_ground=False)


def test_hover_thrust_holds_altitude():
    params = QuadParams(hover_thrust=0.42)
    quad = Quadrotor(params, airborne(f_th=G))
    for _ in range(5 * 240):
        s = quad.step(1 / 240, LEVEL, 0.42)
    assert abs(s.p[2] - 10.0) < 1e-6
    assert np.linalg.norm(s.v) < 1e-9
    # Accelerometer at hover reads +g along body z.
    assert np.allclose(quad.specific_force_body(), [0.0, 0.0, G], atol=1e-9)


def test_more_thrust_climbs_at_the_expected_rate():
    params = QuadParams(drag_lin=0.0, drag_quad=0.0, tau_thrust=1e-4)
    quad = Quadrotor(params, airborne())
    s = quad.step(1.0, LEVEL, 0.6)
    a_expected = 0.6 * G / 0.5 - G
    assert math.isclose(s.v[2], a_expected * 1.0, rel_tol=1e-3)
    # Capped at thrust_to_weight * g whatever the command.
    quad = Quadrotor(params, airborne())
    s = quad.step(1.0, LEVEL, 1.0)
    assert math.isclose(s.v[2], (params.thrust_to_weight - 1) * G, rel_tol=1e-3)


def test_held_tilt_gives_expected_acceleration():
    """Pitched nose-down by 20 deg (FLU: +y rotation) with thrust g/cos: a_x = g tan(20 deg), no climb."""
    tilt = math.radians(20.0)
    q_cmd = Rotation.from_euler("y", tilt).as_quat()
    params = QuadParams(drag_lin=0.0, drag_quad=0.0)
    thrust = params.hover_thrust / math.cos(tilt)
    quad = Quadrotor(params, airborne())
    quad.step(2.0, q_cmd, thrust)  # settle attitude and thrust lag
    v0 = quad.state.v.copy()
    s = quad.step(1.0, q_cmd, thrust)
    a = s.v - v0
    assert math.isclose(a[0], G * math.tan(tilt), rel_tol=1e-3)
    assert abs(a[2]) < 1e-3 and abs(a[1]) < 1e-6
    # Attitude converged to the command.
    assert Rotation.from_quat(s.q).inv() * Rotation.from_quat(q_cmd) is not None
    assert (Rotation.from_quat(s.q).inv() * Rotation.from_quat(q_cmd)).magnitude() < 1e-4


def test_drag_limits_top_speed_to_the_balance_of_tilt_and_drag():
    tilt = math.radians(21.05)  # the paper's gamma_bar: the tilt the tuned controller flies at
    q_cmd = Rotation.from_euler("y", tilt).as_quat()
    params = QuadParams()
    thrust = params.hover_thrust / math.cos(tilt)
    quad = Quadrotor(params, airborne())
    for _ in range(120):
        s = quad.step(1.0, q_cmd, thrust)
    # Independent: horizontal thrust g tan(45) = (drag_lin v + drag_quad v^2) / m.
    c, b, a = -G * math.tan(tilt) * params.mass, params.drag_lin, params.drag_quad
    v_top = (-b + math.sqrt(b * b - 4 * a * c)) / (2 * a)
    assert 20.0 < v_top < 26.0
    assert math.isclose(s.v[0], v_top, rel_tol=2e-3)
    assert s.p[2] > 10.0 - 1.0  # altitude roughly kept (drag has no vertical part at level flight)


def test_wind_drifts_a_hovering_vehicle_to_the_wind_speed():
    quad = Quadrotor(QuadParams(), airborne())
    for _ in range(400):  # time constant ~ m / drag_lin = 40 s
        s = quad.step(1.0, LEVEL, 0.5, wind_enu=np.array([3.0, 0.0, 0.0]))
    assert math.isclose(s.v[0], 3.0, rel_tol=1e-3)


def test_rests_on_ground_and_flags_a_fast_touchdown():
    quad = Quadrotor(QuadParams())
    s = quad.step(1.0, LEVEL, 0.3)  # less than hover: stays put
    assert s.on_ground and s.p[2] == 0.0 and not s.ground_contact
    quad = Quadrotor(QuadParams(), airborne())
    for _ in range(200):
        s = quad.step(0.02, LEVEL, 0.0)
        if s.on_ground:
            break
    assert s.on_ground and s.p[2] == 0.0 and s.ground_contact


def test_rate_limit_bounds_the_body_rate():
    params = QuadParams(max_rate=math.radians(100.0))
    quad = Quadrotor(params, airborne())
    big = Rotation.from_euler("x", 170, degrees=True).as_quat()
    peak = 0.0
    for _ in range(100):
        s = quad.step(0.005, big, 0.5)
        peak = max(peak, float(np.max(np.abs(s.omega))))
    assert peak <= params.max_rate + 1e-9
    assert peak > 0.9 * params.max_rate


def test_command_delay_holds_the_previous_setpoint_for_exactly_the_delay():
    """cmd_delay: a setpoint reaches the attitude loop cmd_delay after it was given (PX4 SIH's transport lag)."""
    roll = Rotation.from_euler("x", 20.0, degrees=True).as_quat()
    delayed = Quadrotor(QuadParams(cmd_delay=0.1), airborne())
    prompt = Quadrotor(QuadParams(), airborne())
    delayed.step(1 / 200, LEVEL, 0.5)  # the setpoint held before: level
    delayed.step(1 / 200, roll, 0.5 / math.cos(math.radians(20.0)))
    for _ in range(18):  # up to 0.1 s after the roll command: still level
        s = delayed.step(1 / 200, roll, 0.5 / math.cos(math.radians(20.0)))
        assert np.allclose(s.omega, 0.0) and np.allclose(s.q, LEVEL)
    # From then on it follows the command as the undelayed vehicle did 0.1 s earlier.
    ref = [prompt.step(1 / 200, roll, 0.5 / math.cos(math.radians(20.0))).q.copy() for _ in range(40)]
    got = [delayed.step(1 / 200, roll, 0.5 / math.cos(math.radians(20.0))).q.copy() for _ in range(40)]
    assert np.allclose(got[-20:], ref[-21:-1], atol=2e-3)
    assert Rotation.from_quat(got[-1]).as_euler("xyz", degrees=True)[0] > 5.0
