"""Guidance math against independent computations: geometry by hand, scipy Rotation, numeric optimisation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from companion import guidance, metrics
from companion.frames import F_FRD_FLU, P_NED_ENU
from companion.guidance import G, GuidanceParams, g_W

finite = st.floats(-1.0, 1.0, allow_nan=False)


@st.composite
def unit_vectors(draw, vertical_bias: bool = True) -> np.ndarray:
    """Unit vectors, with extra weight on the nasty ones: exactly or nearly vertical, axis-aligned."""
    kind = draw(st.sampled_from(["random", "random", "random", "vertical", "near_vertical", "axis"]))
    if kind == "vertical" and vertical_bias:
        return np.array([0.0, 0.0, draw(st.sampled_from([1.0, -1.0]))])
    if kind == "near_vertical" and vertical_bias:
        eps = draw(st.floats(1e-15, 1e-6))
        az = draw(st.floats(0, 2 * math.pi))
        v = np.array([eps * math.cos(az), eps * math.sin(az), draw(st.sampled_from([1.0, -1.0]))])
        return v / np.linalg.norm(v)
    if kind == "axis":
        v = np.zeros(3)
        v[draw(st.integers(0, 2))] = draw(st.sampled_from([1.0, -1.0]))
        return v
    v = np.array([draw(finite), draw(finite), draw(finite)])
    assume(np.linalg.norm(v) > 1e-3)
    return v / np.linalg.norm(v)


@st.composite
def params(draw, gamma_deg=(2.0, 60.0), tilt_deg=(15.0, 85.0)) -> GuidanceParams:
    hover = draw(st.floats(0.2, 0.8))
    tw = draw(st.floats(1.2, 4.0))
    thrust_min = draw(st.one_of(st.just(0.01), st.floats(0.01, min(0.3, hover * 0.9))))
    return GuidanceParams(
        k_pn=draw(st.floats(0.3, 3.0)),
        v_rel_bar=draw(st.floats(1.0, 40.0)),
        gamma_bar=math.radians(draw(st.floats(*gamma_deg))),
        f_max=G * min(tw, 1.0 / hover),
        f_min=G * thrust_min / hover,
        fov=draw(st.sampled_from(["exact", "paper"])),
        max_tilt=math.radians(draw(st.floats(*tilt_deg))),
    )


@st.composite
def demands(draw, l: np.ndarray, max_mag: float = 200.0, min_mag: float = 0.0) -> np.ndarray:  # noqa: E741
    """A PN-like demand: any vector normal to l, magnitude up to max_mag (zero included unless min_mag > 0)."""
    v = np.array([draw(finite), draw(finite), draw(finite)])
    v = v - (v @ l) * l
    n = np.linalg.norm(v)
    if min_mag > 0.0:
        mag = draw(st.floats(min_mag, max_mag))
    else:
        mag = draw(st.one_of(st.just(0.0), st.floats(0.0, max_mag), st.floats(0.0, 5.0)))
    return v / n * mag if n > 1e-6 else np.zeros(3)


def achieved_acc(R_W_B: np.ndarray, f_th: float) -> np.ndarray:
    """Acceleration of the paper's model without drag: thrust along body z plus gravity."""
    return f_th * R_W_B[:, 2] + g_W


def angle(a: np.ndarray, b: np.ndarray) -> float:
    return math.atan2(np.linalg.norm(np.cross(a, b)), float(a @ b))


def tilt(R_W_B: np.ndarray) -> float:
    """Angle of the thrust axis (body z) from world vertical, rad."""
    return angle(R_W_B[:, 2], np.array([0.0, 0.0, 1.0]))


def feasible_at_zero_demand(l: np.ndarray, p: GuidanceParams, n: int = 4001) -> bool:  # noqa: E741
    """Brute force: is there a thrust along the LOS t_x that, with zero normal acceleration, keeps the FOV bound,
    the tilt bound and the thrust limits? Computed from world vectors, not from the solver's formulas."""
    R_pn = guidance.pn_frame(l)
    y, z = R_pn[:, 1], R_pn[:, 2]
    t_y, t_z = -float(y @ g_W), -float(z @ g_W)  # thrust normal to the LOS that cancels gravity there
    if t_z < p.f_min:
        return False
    for t_x in np.linspace(-p.f_max, p.f_max, n):
        t = t_x * l + t_y * y + t_z * z
        f = float(np.linalg.norm(t))
        if not (p.f_min <= f <= p.f_max) or angle(t, np.array([0.0, 0.0, 1.0])) > p.max_tilt:
            continue
        # Body x: in the plane of the thrust and the LOS, normal to the thrust (roll about the LOS only).
        x = l - (l @ t) / f**2 * t
        fov = angle(x, l) if p.fov == "exact" else math.acos(min(1.0, t_z / f))
        if fov <= p.gamma_bar:
            return True
    return False


# --- properties over thousands of random cases -------------------------------------------------


@settings(max_examples=3000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_solver_invariants(data) -> None:
    p = data.draw(params())
    l = data.draw(unit_vectors())  # noqa: E741
    a_n = data.draw(demands(l))
    sol = guidance.solve(l, a_n, p)
    R = sol.R_W_B

    # No NaN/inf anywhere, and a proper rotation.
    assert all(math.isfinite(x) for x in (sol.f_th, sol.phi, sol.theta, sol.demand_scale))
    assert np.all(np.isfinite(R))
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-9) and np.linalg.det(R) == pytest.approx(1.0, abs=1e-9)
    # Thrust in its limits, and the thrust axis within the tilt envelope, always (fallback included).
    assert p.f_min - 1e-9 <= sol.f_th <= p.f_max + 1e-9
    assert tilt(R) <= p.max_tilt + 1e-9
    # The real angle between the commanded optical axis (body x) and the LOS stays within gamma_bar, unless
    # no attitude can keep it within the tilt envelope (then it is as small as the envelope allows).
    if not sol.fallback:
        assert angle(R[:, 0], l) <= p.gamma_bar + 1e-9
    else:
        assert sol.demand_scale == 0.0 and sol.theta == 0.0
        if abs(l[2]) < 1.0 - 1e-9:  # a vertical LOS has no PN frame to compute the brute force in
            assert not feasible_at_zero_demand(l, p, n=401)
    assert 0.0 <= sol.demand_scale <= 1.0
    acc = achieved_acc(R, sol.f_th)
    acc_normal = acc - (acc @ l) * l
    if not sol.fallback:
        # The honoured fraction of the demand is met exactly normal to the LOS, and the rest goes forward.
        assert np.allclose(acc_normal, sol.demand_scale * a_n, atol=1e-9 * (1 + np.linalg.norm(a_n)))
        if tilt(R) < p.max_tilt - 1e-7:  # f sin(phi) cos(theta) >= 0 unless the envelope holds the vehicle back
            assert float(acc @ l) >= float(g_W @ l) - 1e-9
    if sol.demand_scale == 1.0 and not sol.fallback:
        assert np.allclose(acc_normal, a_n, atol=1e-9)


@settings(max_examples=2000, deadline=None)
@given(data=st.data())
def test_setpoint_is_the_same_attitude_and_thrust(data) -> None:
    p = data.draw(params())
    l = data.draw(unit_vectors())  # noqa: E741
    sol = guidance.solve(l, data.draw(demands(l)), p)
    hover = data.draw(st.floats(0.2, 0.8))
    thrust_min = data.draw(st.floats(0.01, 0.2))
    sp = guidance.to_setpoint(sol.R_W_B, sol.f_th, hover, thrust_min)
    # Independent: scipy's Euler angles of the NED/FRD rotation, rebuilt by hand from the ENU/FLU one.
    R_ned = P_NED_ENU @ sol.R_W_B @ F_FRD_FLU
    rot = Rotation.from_matrix(R_ned)
    R_back = Rotation.from_euler("ZYX", [sp.yaw_deg, sp.pitch_deg, sp.roll_deg], degrees=True).as_matrix()
    assert np.allclose(R_back, R_ned, atol=1e-6)  # Euler angles lose precision near gimbal lock
    q = sp.q_wxyz()
    assert np.allclose(Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix(), rot.as_matrix(), atol=1e-9)
    assert thrust_min <= sp.thrust <= 1.0
    assert sp.thrust == pytest.approx(min(1.0, max(thrust_min, hover * sol.f_th / G)))
    assert all(math.isfinite(x) for x in (sp.roll_deg, sp.pitch_deg, sp.yaw_deg, sp.thrust))


@settings(max_examples=2000, deadline=None)
@given(l_prev=unit_vectors(), axis=unit_vectors(vertical_bias=False), alpha=st.floats(1e-6, 3.0),
       dt=st.floats(1e-3, 1.0))
def test_los_rate_against_a_known_rotation(l_prev, axis, alpha, dt) -> None:
    k = axis - (axis @ l_prev) * l_prev  # rotation axis normal to l_prev: the LOS turns by exactly alpha
    assume(np.linalg.norm(k) > 1e-3)
    k /= np.linalg.norm(k)
    l = Rotation.from_rotvec(alpha * k).apply(l_prev)  # noqa: E741
    r = guidance.los_rate(l, l_prev, dt)
    assert r.lambda_dot == pytest.approx(alpha / dt, rel=1e-7)
    # k_l = l x l_prev is the rotation axis reversed, scaled by sin(alpha).
    assert np.allclose(r.k_l, -math.sin(alpha) * k, atol=1e-9)
    # n: unit, normal to l, pointing where the LOS is turning (derivative of the rotation at alpha).
    assert np.linalg.norm(r.n) == pytest.approx(1.0)
    assert abs(r.n @ l) < 1e-9
    assert np.allclose(r.n, np.cross(k, l), atol=1e-9)


def test_los_rate_degenerate_inputs_are_zero_not_nan() -> None:
    l = np.array([1.0, 0.0, 0.0])  # noqa: E741
    for prev, dt in ((None, 1 / 30), (l, 1 / 30), (l, 0.0), (np.array([0.0, 1.0, 0.0]), 0.0),
                     (np.array([0.0, 1.0, 0.0]), float("nan"))):
        r = guidance.los_rate(l, prev, dt)
        assert r.lambda_dot == 0.0 and np.all(r.n == 0.0)
    assert np.all(guidance.pn_demand(0.0, np.zeros(3), 2.1, 15.0) == 0.0)


@settings(max_examples=2000, deadline=None)
@given(l=unit_vectors())
def test_pn_frame(l) -> None:  # noqa: E741
    R = guidance.pn_frame(l)
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.linalg.det(R) == pytest.approx(1.0)
    assert np.allclose(R[:, 0], l)
    horizontal = math.hypot(l[0], l[1]) > 1e-9
    if horizontal:
        # eq:meth_rotation_pn_world: y = e_z x l normalised, z = l x y; gravity has no PN y component.
        y = np.cross([0, 0, 1.0], l)
        assert np.allclose(R[:, 1], y / np.linalg.norm(y))
        assert abs(R[:, 1] @ g_W) < 1e-12
        assert R[2, 2] >= 0.0  # PN z points up (away from gravity)


def test_pn_frame_vertical_los_uses_reference() -> None:
    down = np.array([0.0, 0.0, -1.0])
    R = guidance.pn_frame(down, y_ref=np.array([1.0, 0.0, 0.0]))
    assert np.allclose(R[:, 1], [1.0, 0.0, 0.0])
    R2 = guidance.pn_frame(down, y_ref=down)
    assert np.allclose(R2.T @ R2, np.eye(3))


# --- the closed form against a numerical optimisation of eq:meth_optimization_problem_simplified --------


def fov_margin(phi: float, theta: float, p: GuidanceParams) -> float:
    """>= 0 inside the field-of-view set Q_fov. Exact: the real angle between the optical axis
    R_y(phi) R_x(theta) e_x and the LOS e_x, computed from the rotation; paper: cos(phi) cos(theta)."""
    if p.fov == "paper":
        return math.cos(phi) * math.cos(theta) - math.cos(p.gamma_bar)
    axis = Rotation.from_euler("YX", [phi, theta]).apply([1.0, 0.0, 0.0])  # intrinsic: R_y(phi) R_x(theta)
    return float(axis[0]) - math.cos(p.gamma_bar)


def tilt_margin(phi: float, theta: float, up_pn: np.ndarray, p: GuidanceParams) -> float:
    """>= 0 when the thrust axis R_y(phi) R_x(theta) e_z is within max_tilt of world up (given in the PN frame)."""
    axis = Rotation.from_euler("YX", [phi, theta]).apply([0.0, 0.0, 1.0])
    return float(axis @ up_pn) - math.cos(p.max_tilt)


def numeric_optimum(a_y: float, a_z: float, g_z: float, p: GuidanceParams,
                    up_pn: np.ndarray) -> tuple[float, float, float, float]:
    """maximise f sin(phi) cos(theta) s.t. [n_y a_n, n_z a_n] = [-f sin theta, f cos phi cos theta + g_z],
    0 <= f <= f_max, orientation in Q_fov and within the tilt bound — solved by SLSQP from several starts."""
    cons = [
        {"type": "eq", "fun": lambda x: a_y + x[0] * math.sin(x[2])},
        {"type": "eq", "fun": lambda x: a_z - (x[0] * math.cos(x[1]) * math.cos(x[2]) + g_z)},
        {"type": "ineq", "fun": lambda x: fov_margin(x[1], x[2], p)},
        {"type": "ineq", "fun": lambda x: tilt_margin(x[1], x[2], up_pn, p)},
    ]
    best = None
    for f0 in (0.3, 0.6, 0.95):
        for phi0 in (0.1, 0.5 * p.gamma_bar, 0.9 * p.gamma_bar):
            res = minimize(
                lambda x: -x[0] * math.sin(x[1]) * math.cos(x[2]),
                x0=[f0 * p.f_max, phi0, 0.0],
                bounds=[(0.0, p.f_max), (-math.pi / 2, math.pi / 2), (-math.pi / 2, math.pi / 2)],
                constraints=cons, method="SLSQP", options={"ftol": 1e-13, "maxiter": 500},
            )
            ok = (res.success and all(abs(c["fun"](res.x)) < 1e-7 for c in cons[:2])
                  and all(c["fun"](res.x) > -1e-9 for c in cons[2:]))
            if ok and (best is None or res.fun < best.fun):
                best = res
    assert best is not None, "the numerical optimiser found no feasible point"
    f, phi, theta = best.x
    return -best.fun, f, phi, theta


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(data=st.data())
def test_closed_form_matches_numeric_optimisation(data) -> None:
    p = data.draw(params())
    l = data.draw(unit_vectors(vertical_bias=False))  # noqa: E741
    assume(abs(l[2]) < 0.9)
    a_n = data.draw(demands(l, max_mag=15.0))
    sol = guidance.solve(l, a_n, p)
    assume(sol.demand_scale == 1.0 and not sol.fallback)  # the paper's problem is posed for feasible demands
    R_pn = guidance.pn_frame(l)
    a_y, a_z, g_z = float(R_pn[:, 1] @ a_n), float(R_pn[:, 2] @ a_n), float(R_pn[:, 2] @ g_W)
    obj_closed = sol.f_th * math.sin(sol.phi) * math.cos(sol.theta)
    obj_num, f_num, _, _ = numeric_optimum(a_y, a_z, g_z, p, R_pn.T @ np.array([0.0, 0.0, 1.0]))
    assert obj_closed == pytest.approx(obj_num, abs=1e-5 * (1 + abs(obj_num)))
    assert obj_closed >= obj_num - 1e-6  # the closed form is never worse than the optimiser
    # The optimiser may return an off-optimal f only where the objective is flat in it.
    assert sol.f_th == pytest.approx(f_num, abs=1e-3 * p.f_max) or abs(obj_closed - obj_num) < 1e-7


@settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(data=st.data())
def test_saturation_scale_is_the_largest_feasible(data) -> None:
    """When the demand is scaled down, slightly more of it is infeasible: no feasible thrust/attitude exists.

    Checked numerically: the optimiser is asked to meet (s + 2%) of the demand within the FOV bound and the
    thrust limits, and must fail.
    """
    p = data.draw(params())
    l = data.draw(unit_vectors(vertical_bias=False))  # noqa: E741
    assume(abs(l[2]) < 0.9)
    a_n = data.draw(demands(l, max_mag=60.0, min_mag=3.0))
    sol = guidance.solve(l, a_n, p)
    assume(not sol.fallback and 0.05 < sol.demand_scale < 0.95)
    R_pn = guidance.pn_frame(l)
    s = sol.demand_scale * 1.02
    a_y, a_z, g_z = s * float(R_pn[:, 1] @ a_n), s * float(R_pn[:, 2] @ a_n), float(R_pn[:, 2] @ g_W)
    # Feasibility as a least-violation problem over (f, phi, theta).

    up_pn = R_pn.T @ np.array([0.0, 0.0, 1.0])

    def violation(x):
        f, phi, theta = x
        eq = (a_y + f * math.sin(theta)) ** 2 + (a_z - f * math.cos(phi) * math.cos(theta) - g_z) ** 2
        # (a) of the solver: the thrust floor on the component normal to the LOS in the PN x-z plane.
        floor = max(0.0, p.f_min - f * math.cos(phi) * math.cos(theta))
        return eq + max(0.0, -fov_margin(phi, theta, p)) ** 2 + max(0.0, -tilt_margin(phi, theta, up_pn, p)) ** 2 \
            + floor**2

    best = min(
        minimize(violation, [f0 * p.f_max, phi0, th0], method="L-BFGS-B",
                 bounds=[(p.f_min, p.f_max), (-math.pi / 2, math.pi / 2), (-math.pi / 2, math.pi / 2)]).fun
        for f0 in (0.3, 0.9) for phi0 in (0.0, 0.3) for th0 in (-0.3, 0.3)
    )
    assert best > 1e-10


# --- known geometries, computed by hand ----------------------------------------------------------------


@pytest.fixture(params=["exact", "paper"])
def x500(request) -> GuidanceParams:
    return GuidanceParams(k_pn=2.1, v_rel_bar=15.0, gamma_bar=math.radians(21.05), f_max=2 * G, f_min=0.2 * G,
                          fov=request.param)


def test_gate_straight_ahead_level(x500) -> None:
    # LOS north and level, no LOS rate: pitch down by exactly gamma_bar, thrust G / cos(gamma_bar).
    l = np.array([0.0, 1.0, 0.0])  # noqa: E741 (ENU: north)
    sol = guidance.solve(l, np.zeros(3), x500)
    sp = guidance.to_setpoint(sol.R_W_B, sol.f_th, 0.5, 0.1)
    assert sp.roll_deg == pytest.approx(0.0, abs=1e-9)
    assert sp.pitch_deg == pytest.approx(-21.05)
    assert sp.yaw_deg == pytest.approx(0.0, abs=1e-9)
    assert sol.f_th == pytest.approx(G / math.cos(math.radians(21.05)))
    assert sp.thrust == pytest.approx(0.5 / math.cos(math.radians(21.05)))


def test_gate_ten_degrees_left(x500) -> None:
    az = math.radians(10.0)  # 10 deg left of north = towards west
    l = np.array([-math.sin(az), math.cos(az), 0.0])  # noqa: E741
    sp = guidance.to_setpoint(guidance.solve(l, np.zeros(3), x500).R_W_B, 10.0, 0.5, 0.1)
    assert sp.yaw_deg == pytest.approx(-10.0)  # NED yaw: left is negative
    assert sp.pitch_deg == pytest.approx(-21.05)
    assert sp.roll_deg == pytest.approx(0.0, abs=1e-9)


def test_gate_above(x500) -> None:
    el = math.radians(20.0)
    l = np.array([0.0, math.cos(el), math.sin(el)])  # noqa: E741 (north, 20 deg up)
    sol = guidance.solve(l, np.zeros(3), x500)
    sp = guidance.to_setpoint(sol.R_W_B, sol.f_th, 0.5, 0.1)
    # Body x lies gamma_bar below the LOS in its vertical plane; gravity normal to the LOS is G cos(el).
    assert sp.pitch_deg == pytest.approx(20.0 - 21.05)
    assert sol.f_th == pytest.approx(G * math.cos(el) / math.cos(math.radians(21.05)))
    assert sp.yaw_deg == pytest.approx(0.0, abs=1e-9)


def test_gate_moving_right_rolls_right(x500) -> None:
    l_prev = np.array([0.0, 1.0, 0.0])
    l = Rotation.from_rotvec([0, 0, -0.01]).apply(l_prev)  # noqa: E741 (LOS turns clockwise = right)
    r = guidance.los_rate(l, l_prev, 1 / 30)
    a_n = guidance.pn_demand(r.lambda_dot, r.n, x500.k_pn, x500.v_rel_bar)
    assert a_n[0] > 0  # east = right of north
    sp = guidance.to_setpoint(guidance.solve(l, a_n, x500).R_W_B, 10.0, 0.5, 0.1)
    assert sp.roll_deg > 5.0  # FRD roll positive = right wing down


def test_large_downward_demand_saturates_with_positive_thrust(x500) -> None:
    l = np.array([0.0, 1.0, 0.0])  # noqa: E741
    sol = guidance.solve(l, np.array([0.0, 0.0, -50.0]), x500)  # asks for 5 g downwards
    assert 0.0 <= sol.demand_scale < 1.0 and not sol.fallback
    assert sol.f_th >= x500.f_min
    acc = achieved_acc(sol.R_W_B, sol.f_th)
    assert acc[2] < -G * 0.5  # it does accelerate down, as far as it can


def test_vertical_los_falls_back_without_nan(x500) -> None:
    """Gate straight below / above: no attitude keeps it in view within the tilt envelope. The envelope wins:
    tilt exactly max_tilt towards the LOS, optical axis 90 deg - max_tilt off it, thrust for level flight."""
    for l in (np.array([0.0, 0.0, -1.0]), np.array([0.0, 0.0, 1.0])):  # noqa: E741
        sol = guidance.solve(l, np.zeros(3), x500)
        assert sol.fallback and sol.demand_scale == 0.0
        assert np.all(np.isfinite(sol.R_W_B))
        assert tilt(sol.R_W_B) == pytest.approx(x500.max_tilt)
        assert angle(sol.R_W_B[:, 0], l) == pytest.approx(math.pi / 2 - x500.max_tilt)
        assert sol.f_th == pytest.approx(G / math.cos(x500.max_tilt))
        assert achieved_acc(sol.R_W_B, sol.f_th)[2] == pytest.approx(0.0, abs=1e-9)  # holds altitude


def test_exact_fov_regression_tiny_thrust_floor() -> None:
    """The case from the issue: t_z was driven to ~1e-8, theta to 90 deg, and phi came from rounding, so the
    optical axis ended 48.8 deg off the LOS with gamma_bar 21.05 deg."""
    p = GuidanceParams(k_pn=2.1, v_rel_bar=15.0, gamma_bar=math.radians(21.05), f_max=19.62, f_min=0.5,
                       fov="exact")
    l = np.array([0.5619, -0.68914, 0.457553])  # noqa: E741
    l = l / np.linalg.norm(l)  # noqa: E741
    a_n = np.array([14.629774, -27.276636, -59.048729])
    sol = guidance.solve(l, a_n, p)
    assert np.all(np.isfinite(sol.R_W_B)) and not sol.fallback
    assert angle(sol.R_W_B[:, 0], l) <= p.gamma_bar + 1e-12
    assert tilt(sol.R_W_B) <= p.max_tilt + 1e-12
    assert abs(sol.theta) < math.radians(80.0)
    assert p.f_min <= sol.f_th <= p.f_max
    sp = guidance.to_setpoint(sol.R_W_B, sol.f_th, 0.5, 0.025)
    assert float(metrics.tilt_deg(sp.roll_deg, sp.pitch_deg)) <= math.degrees(p.max_tilt) + 1e-9


def test_no_knife_edge_for_a_large_downward_sideways_demand() -> None:
    """The issue's example: l = [1, 0, 0], a_n = [0, 10, -30] used to give roll -90 deg at thrust 0.167.
    Now the roll stays within the tilt envelope and the achieved normal acceleration keeps the demand's
    direction (the demand is scaled, not bent)."""
    for fov in ("exact", "paper"):
        p = GuidanceParams(2.1, 15.0, math.radians(21.05), 2 * G, 0.2 * G, fov, max_tilt=math.radians(50.0))
        l, a_n = np.array([1.0, 0.0, 0.0]), np.array([0.0, 10.0, -30.0])  # noqa: E741
        sol = guidance.solve(l, a_n, p)
        sp = guidance.to_setpoint(sol.R_W_B, sol.f_th, 0.5, 0.1)
        assert abs(sp.roll_deg) <= 50.0 + 1e-9 and float(metrics.tilt_deg(sp.roll_deg, sp.pitch_deg)) <= 50.0 + 1e-9
        assert 0.0 < sol.demand_scale < 1.0 and not sol.fallback
        acc = achieved_acc(sol.R_W_B, sol.f_th)
        acc_n = acc - (acc @ l) * l
        assert np.allclose(acc_n, sol.demand_scale * a_n, atol=1e-9)


@settings(max_examples=1500, deadline=None)
@given(data=st.data())
def test_tilt_bound_on_setpoints_with_tiny_thrust_floor(data) -> None:
    """The setpoint PX4 gets (NED/FRD Euler) stays inside the envelope, measured as metrics.tilt_deg does, with
    thrust_min down to 0.01 and gamma_bar from 2 to 60 deg; thrust within [thrust_min, 1]."""
    hover = data.draw(st.floats(0.3, 0.7))
    thrust_min = data.draw(st.floats(0.01, 0.05))
    p = GuidanceParams(2.1, 15.0, math.radians(data.draw(st.floats(2.0, 60.0))), G * min(2.0, 1 / hover),
                       G * thrust_min / hover, data.draw(st.sampled_from(["exact", "paper"])),
                       max_tilt=math.radians(data.draw(st.floats(30.0, 70.0))))
    l = data.draw(unit_vectors())  # noqa: E741
    sol = guidance.solve(l, data.draw(demands(l, max_mag=300.0)), p)
    sp = guidance.to_setpoint(sol.R_W_B, sol.f_th, hover, thrust_min)
    assert float(metrics.tilt_deg(sp.roll_deg, sp.pitch_deg)) <= math.degrees(p.max_tilt) + 1e-6
    assert thrust_min <= sp.thrust <= 1.0
    if not sol.fallback:
        assert angle(sp.R_ned_frd[:, 0], P_NED_ENU @ l) <= p.gamma_bar + 1e-9


def test_sideways_demand_exact_fov_keeps_it_paper_fov_caps_it() -> None:
    """6 m/s^2 sideways on a level LOS: the exact bound meets it and still accelerates towards the gate;
    the paper's bound caps sideways acceleration at g tan(gamma_bar) = 3.77 m/s^2."""
    gb = math.radians(21.05)
    l = np.array([0.0, 1.0, 0.0])  # noqa: E741
    a_n = np.array([6.0, 0.0, 0.0])  # east = right
    exact = guidance.solve(l, a_n, GuidanceParams(2.1, 15.0, gb, 2 * G, 0.2 * G, "exact"))
    paper = guidance.solve(l, a_n, GuidanceParams(2.1, 15.0, gb, 2 * G, 0.2 * G, "paper"))
    acc_e, acc_p = achieved_acc(exact.R_W_B, exact.f_th), achieved_acc(paper.R_W_B, paper.f_th)
    assert exact.demand_scale == 1.0 and acc_e[0] == pytest.approx(6.0)
    assert acc_e[1] == pytest.approx(G * math.tan(gb))  # along the LOS: with phi = gamma_bar, as with no demand
    assert angle(exact.R_W_B[:, 0], l) == pytest.approx(gb)
    assert paper.demand_scale < 0.7 and acc_p[0] == pytest.approx(G * math.tan(gb))
    assert acc_p[1] == pytest.approx(0.0, abs=1e-9)  # nothing left for the way to the gate
