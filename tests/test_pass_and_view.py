"""The straight pass that keeps the velocity (drag cancelled) and the ring-in-view FOV bound (pure)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion import guidance
from companion.config import Config, load_config
from companion.controller import PNController, half_fov
from companion.engagement import Engagement, Phase
from perception.los import CameraModel
from perception.types import BoundingBox

CFG = Config()
DT = 1.0 / 30.0
LEVEL = np.array([1.0, 0.0, 0.0, 0.0])  # level, heading north (NED/FRD wxyz)
W, H = CFG.camera.width, CFG.camera.height


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


@settings(max_examples=2000, deadline=None)
@given(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(-0.6, 0.6),
       st.floats(-15.0, 15.0), st.floats(-15.0, 15.0), st.floats(-5.0, 5.0),
       st.floats(15.0, 85.0), st.floats(0.1, 5.0), st.floats(10.0, 40.0))
def test_drag_pass_keeps_the_velocity_inside_the_envelope(lx, ly, lz, dx, dy, dz, max_tilt_deg, f_min, f_max):
    l = np.array([lx, ly, lz])  # noqa: E741
    if np.linalg.norm(l[:2]) < 1e-2:
        return
    l = _unit(l)  # noqa: E741
    drag = np.array([dx, dy, dz])
    mt = math.radians(max_tilt_deg)
    sol = guidance.straight_pass(l, f_min, f_max, max_tilt=mt, drag=drag)
    R = sol.R_W_B
    assert np.all(np.isfinite(R)) and math.isfinite(sol.f_th)
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-9) and np.linalg.det(R) == pytest.approx(1.0, abs=1e-9)
    tilt = math.acos(min(1.0, R[2, 2]))
    assert tilt <= mt + 1e-9  # the envelope holds
    assert f_min - 1e-12 <= sol.f_th <= f_max + 1e-12
    # Body x: the LOS projected normal to the thrust axis (the nearest the optical axis can get to it).
    proj = l - (l @ R[:, 2]) * R[:, 2]
    if np.linalg.norm(proj) > 1e-6:
        assert R[:, 0] @ _unit(proj) == pytest.approx(1.0, abs=1e-9)
    # Within the envelope and the thrust limits the net acceleration (thrust + gravity + drag) is zero: the
    # vehicle keeps its velocity. Independent of the code's own formula: the required thrust vector.
    need = np.array([0.0, 0.0, guidance.G]) - drag
    need_tilt = math.atan2(math.hypot(need[0], need[1]), need[2]) if need[2] > 0 else math.pi
    if need_tilt <= mt and f_min <= np.linalg.norm(need) <= f_max:
        net = sol.f_th * R[:, 2] + guidance.g_W + drag
        assert np.allclose(net, 0.0, atol=1e-9)


def test_drag_pass_constant_velocity_with_linear_drag():
    """A point mass with linear drag (the SIH profile: 1 N/(m/s) on 1 kg), flown with the pass setpoint computed
    from its own drag: the velocity stays (before: level thrust, the lateral speed decayed at 1/s)."""
    v0 = np.array([4.0, 3.0, 0.0])  # m/s, ENU: chasing a gate that moves sideways
    k = 1.0
    l = _unit(np.array([1.0, 0.3, 0.05]))  # noqa: E741
    sol = guidance.straight_pass(l, 0.5, 20.0, max_tilt=math.radians(50.0), drag=-k * v0)
    sol_level = guidance.straight_pass(l, 0.5, 20.0, max_tilt=math.radians(50.0))
    for s, expect_kept in ((sol, True), (sol_level, False)):
        v = v0.copy()
        for _ in range(150):  # 0.5 s at 300 Hz, the thrust held as in PASS
            v = v + (s.f_th * s.R_W_B[:, 2] + guidance.g_W - k * v) / 300.0
        lost = np.linalg.norm(v - v0)
        assert (lost < 1e-9) if expect_kept else (lost > 1.0)


def _close_run(*overrides: str, accel_frd: np.ndarray | None):
    cfg = load_config([], list(overrides)) if overrides else CFG
    eng = Engagement.from_config(cfg, PNController.from_config(cfg))
    t = 0.0
    d = None
    for i in range(CFG.app.acquire_frames + 20):
        b = BoundingBox(W / 2 + 2 * i, H / 2, 60.0, 60.0, 0.9, t)
        d = eng.step(t, b, LEVEL, 10.0, (), accel_frd, t)
        t += DT
    assert d is not None and d.phase is Phase.ENGAGE
    # The 1 m ring comes near at 15 m/s (v_rel_bar) until its box is 620 px: an approach the target lock explains
    # (a jump from 60 to 620 px, or a faster growth compounded frame by frame, would be another object).
    f = float(CameraModel.from_config(cfg.camera).K[0, 0])
    rng = 2.0 * f / 60.0
    while rng > 2.0 * f / 620.0:
        rng -= 15.0 * DT
        size = min(620.0, 2.0 * f / max(rng, 1e-3))
        d = eng.step(t, BoundingBox(W / 2 + 40, H / 2, size, size, 0.9, t), LEVEL, 10.0, (), accel_frd, t)
        t += DT
        if d.phase is not Phase.ENGAGE:
            break
    assert d.phase is Phase.PASS
    return d, cfg


def test_the_pass_cancels_the_drag_the_accelerometer_measures():
    # Level, heading north, the accelerometer sees 3 m/s^2 of specific force to the left (FRD y < 0): drag from
    # flying to the right (east). The pass thrust must push east by 3 m/s^2 and still carry the weight.
    accel = np.array([0.0, -3.0, -guidance.G])
    d, cfg = _close_run(accel_frd=accel)
    R = d.setpoint.R_ned_frd
    up_ned = -R[:, 2]  # thrust axis (body -z FRD) in NED
    expect = _unit(np.array([0.0, 3.0, -guidance.G]))  # NED: east 3, up g
    assert up_ned == pytest.approx(expect, abs=1e-9)
    f = math.hypot(3.0, guidance.G)
    assert d.setpoint.thrust == pytest.approx(cfg.airframe.hover_thrust * f / guidance.G, rel=1e-9)
    # The optical axis stays as close to the last LOS as the thrust axis allows.
    los = d.control.los_ned
    proj = los - (los @ R[:, 2]) * R[:, 2]
    assert R[:, 0] @ _unit(proj) == pytest.approx(1.0, abs=1e-9)


def test_without_an_accelerometer_or_with_the_option_off_the_pass_is_level():
    for over, acc in (((), None), (("guidance.drag_compensation=0",), np.array([0.0, -3.0, -guidance.G]))):
        d, cfg = _close_run(*over, accel_frd=acc)
        R = d.setpoint.R_ned_frd
        assert R[:, 0] @ d.control.los_ned == pytest.approx(1.0, abs=1e-9)  # optical axis on the LOS
        assert R[2, 1] == pytest.approx(0.0, abs=1e-9)  # no roll about it
        assert d.setpoint.thrust * R[2, 2] == pytest.approx(cfg.airframe.hover_thrust, rel=1e-9)


def test_half_fov_is_the_nearest_image_border():
    cam = CameraModel.from_config(CFG.camera)
    fy = float(cam.K[1, 1])
    assert half_fov(cam) == pytest.approx(math.atan((H / 2) / fy))  # 640 x 480: the top/bottom borders
    assert math.degrees(half_fov(cam)) < CFG.camera.half_fov


@given(st.floats(1.0, 60.0), st.floats(5.0, 45.0), st.floats(0.0, 40.0), st.floats(-5.0, 5.0), st.floats(0.5, 5.0))
def test_ring_view_gamma(gamma_bar_deg, half_fov_deg, ring_deg, margin_deg, gamma_min_deg):
    r = math.radians
    g = guidance.ring_view_gamma(r(gamma_bar_deg), r(half_fov_deg), r(ring_deg), r(margin_deg), r(gamma_min_deg))
    assert g <= r(gamma_bar_deg) + 1e-15
    assert g >= min(r(gamma_min_deg), r(gamma_bar_deg)) - 1e-15
    room = r(half_fov_deg - ring_deg - margin_deg)
    if min(r(gamma_min_deg), r(gamma_bar_deg)) <= room:
        assert g <= room + 1e-15  # the rim stays inside the view (with the margin)


def _optical_axis_to_los_deg(*overrides: str, size: float) -> float:
    cfg = load_config([], list(overrides))
    ctrl = PNController.from_config(cfg)
    out = None
    for i in range(10):
        out = ctrl.step(i * DT, BoundingBox(W / 2, H / 2 - 40, size, size, 0.9, i * DT), LEVEL)
    assert out is not None and out.mode == "pn"
    R = out.setpoint.R_ned_frd
    return math.degrees(math.acos(min(1.0, float(R[:, 0] @ out.los_ned))))


def test_keep_ring_in_view_bounds_the_optical_axis_to_los_angle():
    cam = CameraModel.from_config(CFG.camera)
    size = 200.0  # px: the ring's angular radius is atan(100 / f)
    ring = math.degrees(math.atan(0.5 * size / float(cam.K[0, 0])))
    bound = math.degrees(half_fov(cam)) - ring - 2.0
    assert bound < CFG.guidance.gamma_bar  # the case where the bound binds
    off = _optical_axis_to_los_deg("guidance.keep_ring_in_view=false", size=size)
    on = _optical_axis_to_los_deg("guidance.keep_ring_in_view=true", "guidance.view_margin=2 deg", size=size)
    # The solver maximises thrust along the LOS, so the angle sits on the FOV bound in use.
    assert off == pytest.approx(CFG.guidance.gamma_bar, abs=1e-6)
    assert on == pytest.approx(bound, abs=1e-6)
    small = _optical_axis_to_los_deg("guidance.keep_ring_in_view=true", "guidance.view_margin=2 deg", size=20.0)
    assert small == pytest.approx(CFG.guidance.gamma_bar, abs=1e-6)  # a small (far) ring: the paper's bound


# -- boxes cut by the image border ------------------------------------------------------------------------


def _xyxy(x0: float, y0: float, x1: float, y1: float) -> BoundingBox:
    return BoundingBox.from_xyxy(x0, y0, x1, y1, 0.9, 0.0)


def test_a_box_within_three_pixels_of_the_border_is_completed_the_same_way():
    """A detector's edges are noisy (~1 px): a ring on the top border must be completed in every frame, not in one
    frame and not in the next (its LOS jumped by half the missing height, tens of pixels)."""
    from companion.engagement import complete_clipped_box

    centres = []
    for top in (0.0, 0.8, 1.6, 2.4, 2.99):  # noisy top edges of the same cut ring
        b = complete_clipped_box(_xyxy(300.0, top, 420.0, 90.0), W, H)
        assert b.h == pytest.approx(120.0)  # completed to the whole (horizontal) extent
        centres.append(b.cy)
    assert max(centres) - min(centres) == pytest.approx(0.0, abs=1e-9)  # anchored at the uncut bottom edge
    assert centres[0] == pytest.approx(90.0 - 60.0)
    whole = _xyxy(300.0, 3.5, 420.0, 90.0)  # clear of the border: a whole box, left alone
    assert complete_clipped_box(whole, W, H) is whole


@settings(max_examples=500, deadline=None)
# gap < edge_px: at exactly 3.0 the box's edge, rebuilt from centre and size, lands a few ulp either side of the
# 3 px threshold (a property of floating point, not of the completion).
@given(st.sampled_from(["left", "right", "top", "bottom"]), st.floats(0.0, 2.999), st.floats(20.0, 300.0),
       st.floats(20.0, 300.0), st.floats(0.2, 0.8))
def test_completion_of_one_cut_side(side: str, gap: float, a: float, b: float, pos: float):
    from companion.engagement import complete_clipped_box

    # A box touching one border (within gap px), whole along the other axis, inside the image there.
    if side in ("top", "bottom"):
        x0 = pos * (W - a)
        y0, y1 = (gap, gap + b) if side == "top" else (H - gap - b, H - gap)
        box = _xyxy(x0, y0, x0 + a, y1)
    else:
        y0 = pos * (H - b)
        x0, x1 = (gap, gap + a) if side == "left" else (W - gap - a, W - gap)
        box = _xyxy(x0, y0, x1, y0 + b)
    if max(box.w, box.h) > min(W, H) - 8:  # would touch the opposite border too
        return
    out = complete_clipped_box(box, W, H)
    bx0, by0, bx1, by1 = box.xyxy
    ox0, oy0, ox1, oy1 = out.xyxy
    size = max(box.w, box.h)
    assert out.w >= box.w - 1e-9 and out.h >= box.h - 1e-9  # never shorter than what is visible
    if side == "top":
        assert (ox0, ox1, oy1) == pytest.approx((bx0, bx1, by1)) and out.h == pytest.approx(size)
    elif side == "bottom":
        assert (ox0, ox1, oy0) == pytest.approx((bx0, bx1, by0)) and out.h == pytest.approx(size)
    elif side == "left":
        assert (oy0, oy1, ox1) == pytest.approx((by0, by1, bx1)) and out.w == pytest.approx(size)
    else:
        assert (oy0, oy1, ox0) == pytest.approx((by0, by1, bx0)) and out.w == pytest.approx(size)


def test_boxes_cut_on_both_sides_or_both_axes_are_left_alone():
    from companion.engagement import complete_clipped_box

    for b in (_xyxy(0.0, 100.0, W, 200.0), _xyxy(100.0, 0.0, 200.0, H), _xyxy(0.0, 0.0, 100.0, 120.0),
              _xyxy(2.0, 100.0, W - 2.0, 300.0)):
        assert complete_clipped_box(b, W, H) is b


# -- delay compensation (Smith predictor on our own motion) ----------------------------------------------


def _feed(ctrl: PNController, age: float, n: int = 40):
    outs = []
    for i in range(n):
        t = i * DT
        b = BoundingBox(W / 2 + 3 * i, H / 2 - i, 40.0 + i, 40.0 + i, 0.9, t)
        outs.append(ctrl.step(t, b, LEVEL, None, t + age))
    return outs


def test_delay_compensation_changes_nothing_for_a_fresh_frame():
    on = PNController.from_config(load_config([], ["guidance.delay_compensation=true"]))
    off = PNController.from_config(load_config([], ["guidance.delay_compensation=false"]))
    for a, b in zip(_feed(on, 0.0), _feed(off, 0.0), strict=True):
        assert a.setpoint.R_ned_frd == pytest.approx(b.setpoint.R_ned_frd, abs=0.0)
        assert a.setpoint.thrust == b.setpoint.thrust and a.lambda_dot == b.lambda_dot


def test_delay_compensation_acts_on_late_frames_only_through_our_own_commands():
    on = PNController.from_config(load_config([], ["guidance.delay_compensation=true"]))
    off = PNController.from_config(load_config([], ["guidance.delay_compensation=false"]))
    late_on, late_off = _feed(on, 0.2), _feed(off, 0.2)
    assert late_on[0].lambda_dot == late_off[0].lambda_dot  # no command yet: nothing to bring forward
    assert any(abs(a.lambda_dot - b.lambda_dot) > 1e-6 for a, b in zip(late_on, late_off, strict=True))


@settings(max_examples=60, deadline=None)
@given(st.floats(0.05, 2.0), st.floats(0.0, 0.5), st.floats(0.01, 0.4), st.floats(-5.0, 5.0))
def test_own_velocity_model_against_an_integral(tau: float, t0: float, width: float, a_y: float):
    """The velocity our commanded accelerations add in [t0, t0 + width]: commands held until the next one, each
    reached with a first-order lag ``tau`` -- checked against a fine numerical integration of the same model."""
    cfg = load_config([], ["guidance.delay_compensation=true", f"guidance.delay_compensation_lag={tau} s"])
    ctrl = PNController.from_config(cfg)
    cmds = [(0.0, np.array([0.0, a_y, 0.0])), (0.1, np.array([1.0, -a_y, 0.5])), (0.25, np.array([0.0, 0.0, 2.0]))]
    for t, a in cmds:
        ctrl._t_now = t
        ctrl._note_command(a)
    t1 = t0 + width
    dv = ctrl._own.dv(t0, t1)
    # Independent: Euler integration of tau * da_eff/dt = a_cmd(t) - a_eff, a_eff(0) = 0.
    h = 1e-4
    eff = np.zeros(3)
    acc = np.zeros(3)
    t = 0.0
    while t < t1:
        cmd = [a for tc, a in cmds if tc <= t][-1]
        if t >= t0:
            acc += eff * h
        eff = eff + (cmd - eff) * (h / tau)
        t += h
    assert dv == pytest.approx(acc, abs=2e-3 * (1 + np.abs(acc).max()))
