"""The target lock (companion/targetlock.py): the engaged gate's boxes pass, another object's do not.

Checked against hand numbers, against a gate approached in 3D and projected through the camera (its box size
from the range, its centre from the attitude: independent of the lock's own range and LOS formulas), and in the
engagement: a box of another object after a gap is no box (the controller coasts, no false "close")."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from companion.config import Config, load_config
from companion.controller import PNController
from companion.engagement import Engagement, EngagementParams, Phase
from companion.targetlock import LockParams, TargetLock
from perception.los import CameraModel
from perception.types import BoundingBox

CFG = Config()
CAM = CameraModel.from_config(CFG.camera)
F = float(CAM.K[0, 0])  # 483.47 px: 640 px over a 67 deg field of view
LEVEL_R = np.eye(3)


def lock(**kw) -> TargetLock:
    return TargetLock(LockParams(v_max=15.0, gate_radius=1.0, max_los_rate=3.0, **kw), CAM)


def box(size: float, cx: float = 320.0, cy: float = 240.0) -> BoundingBox:
    return BoundingBox(cx, cy, size, size, 0.9, 0.0)


def test_hand_numbers_for_the_size_bound():
    # A 1 m-radius ring 45 px wide is 2 * 483.47 / 45 = 21.49 m away. Closing at 15 m/s for 0.07 s it is at least
    # 20.44 m away: at most 2 * 483.47 / 20.44 = 47.31 px; with the detector's 1.5x jitter 70.97 px.
    assert pytest.approx(483.467, abs=1e-3) == F
    for size, ok in ((70.0, True), (72.0, False), (29.0, True), (28.0, False)):  # shrink: 45 / 70.97 * 45 = 28.5
        lk = lock()
        assert lk.check(0.0, box(45.0), LEVEL_R).ok
        assert lk.check(0.07, box(size), LEVEL_R).ok is ok, size
    # Without a gate size the bound is a growth rate: exp(4 / s x 0.1 s) x 1.5 = 2.24.
    lk = TargetLock(LockParams(15.0, 0.0, 3.0), CAM)
    assert lk.check(0.0, box(40.0), LEVEL_R).ok
    assert lk.check(0.1, box(40.0 * 2.2), LEVEL_R).ok
    lk = TargetLock(LockParams(15.0, 0.0, 3.0), CAM)
    lk.check(0.0, box(40.0), LEVEL_R)
    assert not lk.check(0.1, box(40.0 * 2.3), LEVEL_R).ok


def test_the_clutter_box_seen_on_real_px4_is_rejected_and_the_gate_taken_back():
    """Real PX4 Table I, x500, run 46: the gate 45 px at (309, 67), two frames without a box, then a 198 x 154 box
    at (515, 403) that the engagement took for the gate come near. The attitude did not change between them."""
    lk = lock()
    assert lk.check(4.109, BoundingBox(309.2, 67.3, 44.8, 45.8, 0.57, 0.0), LEVEL_R).ok
    chk = lk.check(4.207, BoundingBox(514.9, 403.0, 197.7, 153.9, 0.51, 0.0), LEVEL_R)
    assert not chk.ok and chk.why.startswith("not the engaged gate: box 198 px vs 46 px")
    assert lk.rejected == 1
    # The gate itself, 0.2 s later and a little larger, is the target again.
    assert lk.check(4.31, BoundingBox(312.0, 70.0, 47.0, 47.0, 0.6, 0.0), LEVEL_R).ok
    # Same size, but 40 deg away in the world (the vehicle did not turn): another object.
    u = 320.0 + F * math.tan(math.radians(40.0))
    assert not lk.check(4.34, BoundingBox(u, 240.0, 47.0, 47.0, 0.6, 0.0), LEVEL_R).ok


def test_the_closing_filter_bounds_the_growth_after_a_gap():
    """Real PX4, SIH quad, 100-run table (2026-12-06) run 057, linear fast: the gate 45x53 px at (312, 93), the
    closing-speed filter at 3.2 +- 0.84 m/s; it slid out of view, and 0.96 s later a 154x335 px background box at
    (77, 312) came (the filter, driven by the IMU, at 4.3 +- 1.3 m/s). With v_max (15 m/s) a gate 18.2 m away may
    come to 3.8 m in 0.96 s: x4.8, x7.2 with the detector's jitter, so the box was taken for the gate, flown at
    and claimed as passed. At the filter's upper speed 4.3 + 3 x 1.3 = 8.1 m/s it comes to 10.4 m at most:
    x1.75, x2.63 with the jitter, and 335 / 53 = 6.3 is another object. (Both boxes level: the size rule
    decides.)"""
    gate, clutter = BoundingBox(312.0, 93.0, 45.0, 53.0, 0.6, 0.0), BoundingBox(77.0, 312.0, 154.0, 335.0, 0.5, 0.0)
    lk = lock()
    assert lk.check(8.672, gate, LEVEL_R).ok
    assert lk.check(9.636, clutter, LEVEL_R).ok  # what flew on real PX4
    lk = lock()
    assert lk.check(8.672, gate, LEVEL_R, (-3.2, 0.84)).ok
    chk = lk.check(9.636, clutter, LEVEL_R, (-4.28, 1.28))
    assert not chk.ok and "an approach at 8.1 m/s explains x2.63" in chk.why, chk.why
    # Hand numbers for the bound: d = 2 f r / 53 = 18.24 m; 8.14 m/s x 0.964 s = 7.85 m; 18.24 / 10.40 x 1.5.
    d = 2.0 * F / 53.0
    assert lk.size_bound(53.0, 0.964, 4.28 + 3 * 1.28) == pytest.approx(1.5 * d / (d - 8.12 * 0.964), rel=1e-9)
    # The gate itself, larger by what 8 m/s explains, is taken back; the speed is the larger of then and now.
    assert lk.check(9.7, BoundingBox(300.0, 100.0, 80.0, 80.0, 0.6, 0.0), LEVEL_R, (-4.3, 1.3)).ok
    # A filter still at its prior (-v_rel_bar +- v_rel_bar / 2) bounds nothing more than v_max.
    assert lk.closing_bound((-15.0, 7.5)) == 15.0 and lk.closing_bound(None) == 15.0
    assert lk.closing_bound((2.0, 0.5)) == pytest.approx(1.5)  # receding: only the uncertainty may close


def test_a_shrink_keeps_the_v_max_bound():
    """A ring turning edge-on or leaving across a border shrinks whatever the closing speed: a receding
    filter does not make a shrink another object."""
    lk = lock()
    assert lk.check(0.0, box(346.0), LEVEL_R, (4.4, 0.9)).ok
    assert lk.check(1 / 30, box(198.0), LEVEL_R, (4.4, 0.9)).ok  # 1.75x smaller: v_max allows x1.83
    assert not lk.check(2 / 30, box(100.0), LEVEL_R, (4.4, 0.9)).ok


def _project(p_gate_body: np.ndarray) -> tuple[float, float] | None:
    return CAM.project_body(p_gate_body)


@settings(max_examples=300, deadline=None)
@given(
    d0=st.floats(8.0, 40.0),
    v=st.floats(0.0, 15.0),
    lateral=st.floats(-5.0, 5.0),
    seed=st.integers(0, 2**31 - 1),
)
@pytest.mark.parametrize("filtered", [False, True], ids=["v_max", "closing_filter"])
def test_a_real_gate_approached_in_3d_is_never_rejected(d0, v, lateral, seed, filtered):
    """The vehicle closes on a 1 m ring at v <= v_max while the ring slides sideways (<= 5 m/s) and the vehicle
    rotates freely (the box jumps in the image; the world line of sight does not): frames 33-300 ms apart, box
    size 2 f r / d with +-15 % detector noise, centre +-3 px. Every box is the engaged gate.
    ``closing_filter``: the closing-speed filter is also given, its speed wrong by up to 2 of its standard
    deviations (0.3-2 m/s) either way, as it may be."""
    rng = np.random.default_rng(seed)
    lk = lock()
    sigma = float(rng.uniform(0.3, 2.0))
    closing = (-(v + float(rng.uniform(-2.0, 2.0)) * sigma), sigma) if filtered else None
    t, p_rel = 0.0, np.array([d0, 0.0, 0.0])  # gate relative to the vehicle, NED
    checked = 0
    while np.linalg.norm(p_rel) > 3.0 and checked < 60:
        # An attitude that keeps the gate in view: look at it, then up to +-15 deg off in yaw/pitch and any roll.
        los = p_rel / np.linalg.norm(p_rel)
        yaw, pitch = math.atan2(los[1], los[0]), -math.asin(los[2])
        R = Rotation.from_euler("ZYX", [yaw + rng.uniform(-0.26, 0.26), pitch + rng.uniform(-0.26, 0.26),
                                        rng.uniform(-0.6, 0.6)]).as_matrix()
        uv = _project(R.T @ p_rel)
        if uv is not None and 0 < uv[0] < CAM.width and 0 < uv[1] < CAM.height:
            size = 2.0 * F * 1.0 / np.linalg.norm(p_rel) * rng.uniform(0.85, 1.15)
            b = BoundingBox(uv[0] + rng.uniform(-3, 3), uv[1] + rng.uniform(-3, 3), size, size, 0.8, t)
            chk = lk.check(t, b, R, closing)
            assert chk.ok, (t, chk.why)
            checked += 1
        dt = float(rng.choice([1 / 30, 1 / 30, 1 / 15, 0.1, 0.3]))
        t += dt
        p_rel = p_rel + dt * np.array([-v, lateral, 0.0])
    assert lk.rejected == 0


def test_a_gate_at_both_noise_extremes_after_a_gap_is_refused_the_price_of_the_clutter_bound():
    """A known limit, found by the random search of the test above (d0 8 m, 15 m/s, lateral 0, seed 10707): the
    gate's box 14 % small at 8 m, nothing for 0.3 s, then 15 % large at 3.5 m. The lock takes the range from the
    reference box as measured (9.3 m for 8), so a 15 m/s approach explains x1.94, x2.91 with the jitter, and the
    boxes say x3.06: refused. Allowing for the reference box's own noise (its range over sqrt(size_jitter)) took it
    back, but also took the clutter of ``test_another_objects_box_is_no_box_for_the_engagement`` for the gate before
    the target-lost timeout: the lock keeps the tighter bound. A refused box is coasted, never flown at."""
    d0, d1 = 8.0, 8.0 - 15.0 * 0.3
    lk = lock()
    assert lk.check(0.0, box(2.0 * F / d0 * 0.86), LEVEL_R).ok
    chk = lk.check(0.3, box(2.0 * F / d1 * 1.15), LEVEL_R)
    d = d0 / 0.86  # the range the 104 px box says: 9.30 m; 1.5 x 9.30 / 4.80 = 2.91
    assert not chk.ok and f"explains x{1.5 * d / (d - 4.5):.2f} at most" in chk.why, chk.why
    # The same gate with boxes of its true size, or with the noise the other way, is taken.
    for k0, k1 in ((1.0, 1.0), (1.15, 0.86), (0.86, 1.0)):
        lk = lock()
        assert lk.check(0.0, box(2.0 * F / d0 * k0), LEVEL_R).ok
        assert lk.check(0.3, box(2.0 * F / d1 * k1), LEVEL_R).ok, (k0, k1)


# The engaged box of real PX4 SIH run004 (2026-12-07, linear-fast gate): (t s, box, the closing filter's range rate
# and its std dev as of the frame before). The ring stayed ~110-125 px (truth) while its box merged with the
# background beside it: x1.03-1.5 a frame, each within the frame-to-frame bound.
RAMP = [(9.09, (362.4, 67.1, 95.1, 121.9), (-2.57, 0.83)), (9.13, (368.8, 66.0, 94.0, 122.7), (-3.07, 0.72)),
        (9.15, (373.3, 64.5, 93.7, 119.8), (-3.17, 0.67)), (9.19, (367.2, 66.0, 96.2, 123.8), (-3.12, 0.64)),
        (9.23, (354.6, 70.5, 98.8, 130.8), (-3.16, 0.63)), (9.26, (333.5, 77.5, 103.0, 135.1), (-3.45, 0.63)),
        (9.30, (288.2, 92.6, 134.3, 147.1), (-3.78, 0.61)), (9.34, (251.7, 104.9, 156.4, 157.2), (-4.42, 0.61)),
        (9.36, (233.5, 110.9, 167.4, 162.2), (-5.23, 0.60)), (9.40, (197.0, 123.1, 189.5, 172.2), (-5.94, 0.59)),
        (9.44, (128.9, 149.6, 238.2, 287.2), (-6.74, 0.58))]


@pytest.mark.parametrize("window", [0.0, 0.3], ids=["frame_to_frame", "window"])
def test_a_box_that_grows_by_merging_with_the_background_is_refused_within_the_window(window):
    """Frame by frame every step of RAMP is one an approach explains (x1.5 jitter each time, compounding: 122 ->
    287 px in 0.35 s); against the boxes of the last 0.3 s the last one is not: the median of what they explain
    is 130.8 px's, 0.21 s before: closing at most 6.74 + 3 x 0.58 = 8.5 m/s from 7.39 m explains x1.32, x1.98
    with the jitter once. Its growth had made a time-to-contact of 0.18 s and a pass claimed 7.5 m from the
    gate."""
    lk = lock(window_s=window)
    for t, (cx, cy, w, h), closing in RAMP[:-1]:
        assert lk.check(t, BoundingBox(cx, cy, w, h, 0.5, t), LEVEL_R, closing).ok, t
    t, (cx, cy, w, h), closing = RAMP[-1]
    chk = lk.check(t, BoundingBox(cx, cy, w, h, 0.5, t), LEVEL_R, closing)
    assert chk.ok is (window == 0.0), chk.why
    if window:
        # The window's median: 9.23's 130.8 px box, 0.21 s before
        d, v, dt = 2.0 * F / 130.8, 6.74 + 3.0 * 0.58, 9.44 - 9.23
        assert f"287 px vs 131 px 0.21 s before (the median of the last 0.3 s; an approach at 8.5 m/s explains " \
            f"x{1.5 * d / (d - v * dt):.2f} at most)" in chk.why, chk.why


def test_a_ring_back_from_a_border_cut_is_not_held_to_its_cut_size():
    """A box the border cut is not a size to bound growth by: the ring coming back into view grows by more than
    any approach (here x1.6 in 0.1 s at 20 m)."""
    lk = lock()
    assert lk.check(0.0, BoundingBox(10.0, 240.0, 30.0, 48.0, 0.8, 0.0), LEVEL_R, (-3.0, 0.5)).ok  # cut: x0 = -5
    assert lk.check(0.033, BoundingBox(16.0, 240.0, 40.0, 48.0, 0.8, 0.0), LEVEL_R, (-3.0, 0.5)).ok  # still cut
    assert lk.check(0.066, BoundingBox(26.0, 240.0, 48.0, 48.0, 0.8, 0.0), LEVEL_R, (-3.0, 0.5)).ok  # clear of it
    assert lk.check(0.1, BoundingBox(30.0, 240.0, 48.0, 48.0, 0.8, 0.0), LEVEL_R, (-3.0, 0.5)).ok


# -- in the engagement -----------------------------------------------------------------------------------------
DT = 1.0 / 30.0
LEVEL = np.array([1.0, 0.0, 0.0, 0.0])


def _engaged(*overrides: str) -> tuple[Engagement, float]:
    cfg = load_config([], list(overrides)) if overrides else CFG
    eng = Engagement.from_config(cfg, PNController.from_config(cfg))
    t = 0.0
    for _ in range(cfg.app.acquire_frames):
        eng.step(t, box(45.0, 309.0, 67.0), LEVEL, 10.0)
        t += DT
    assert eng.phase is Phase.ENGAGE
    return eng, t


def test_another_objects_box_is_no_box_for_the_engagement():
    eng, t = _engaged()
    eng.step(t, None, LEVEL, 10.0)
    t += DT
    decisions = []
    for i in range(12):  # the clutter box, growing a little: big and far from the gate
        decisions.append(eng.step(t, box(198.0 + 3 * i, 515.0, 403.0), LEVEL, 10.0))
        t += DT
    assert all(d.phase is Phase.ENGAGE for d in decisions)  # never "close" on it
    assert all(d.control.mode == "coast" for d in decisions)  # the controller never steered at it
    rejected = [e for d in decisions for e in d.events if "box rejected" in e]
    assert len(rejected) == 1 and rejected[0].startswith("gate 1: box rejected, not the engaged gate")
    # It stays no box: the target-lost timeout ends the engagement in a named abort, never at the clutter.
    end = None
    for _ in range(60):
        end = eng.step(t, box(240.0, 515.0, 403.0), LEVEL, 10.0)
        t += DT
        if end.phase.done:
            break
    assert end is not None and end.phase is Phase.ABORT and end.reason.name == "TARGET_LOST"


def test_without_the_lock_the_clutter_box_is_flown_at():
    """What the lock prevents (app.target_lock=false): the same boxes steer the controller."""
    eng, t = _engaged("app.target_lock=false")
    eng.step(t, None, LEVEL, 10.0)
    t += DT
    modes = []
    for i in range(12):
        modes.append(eng.step(t, box(198.0 + 3 * i, 515.0, 403.0), LEVEL, 10.0).control.mode)
        t += DT
    assert modes.count("pn") >= 6, modes  # the LOS filter rejects the jump once, then steers at the clutter


def test_a_synthetic_course_caps_the_gates_engaged():
    cfg = load_config([], ["app.camera=synthetic", "app.synthetic.count=2", "app.max_gates=10"])
    assert EngagementParams.from_config(cfg).max_gates == 2
    cfg = load_config([], ["app.camera=source", "app.max_gates=10"])
    assert EngagementParams.from_config(cfg).max_gates == 10


def test_the_engagement_bounds_the_lock_with_its_closing_filter():
    """In the engagement: a gate approached at 3 m/s for 1.5 s, lost for 0.9 s, then a box 6x its size. The
    controller's closing-speed filter (its IMU a hovering vehicle's: nothing explains a faster closing)
    bounds the lock: no box (coast). With the paper's fixed closing speed (``guidance.closing_speed=fixed``, no
    filter) the lock allows v_max and the box is taken."""
    hover_imu = np.array([0.0, 0.0, -9.80665])  # FRD specific force, level and unaccelerated
    def run(*overrides: str) -> tuple[Engagement, object]:
        cfg = load_config([], list(overrides))
        eng = Engagement.from_config(cfg, PNController.from_config(cfg))
        t, d = 0.0, 20.0
        for _ in range(cfg.app.acquire_frames + 45):
            s = 2.0 * F / d
            eng.step(t, box(s, 320.0, 240.0), LEVEL, 10.0, accel_frd=hover_imu, t_now=t)
            t, d = t + DT, d - 3.0 * DT
        assert eng.phase is Phase.ENGAGE
        for _ in range(27):  # 0.9 s without a box
            eng.step(t, None, LEVEL, 10.0, accel_frd=hover_imu, t_now=t)
            t += DT
        return eng, eng.step(t, box(6.0 * 2.0 * F / d, 330.0, 250.0), LEVEL, 10.0, accel_frd=hover_imu, t_now=t)

    eng, dec = run()
    v = eng.controller.closing_rate
    assert v is not None and 2.0 < -v[0] < 4.0 and v[1] < 2.5, v  # the filter saw ~3 m/s
    assert dec.control.mode == "coast" and any("box rejected" in e for e in dec.events), dec.events
    eng, dec = run("guidance.closing_speed=fixed")
    assert eng.controller.closing_rate is None
    assert dec.control.mode == "pn" and not dec.events


def test_the_tracker_is_told_to_drop_a_target_the_engagement_keeps_refusing():
    """Real PX4, x500 (runs 012 and 092 of a 100-run table): perception's one box went to the ground while the gate
    stayed in view, and the lock refused it for 0.4-1.0 s until TARGET_LOST. The core now tells the loop to reset
    the tracker at every ``drop_tracker_after`` refusals in a row; frames without a box do not break the count, a
    box taken does. Before the engagement (ACQUIRE) nothing is dropped."""
    from companion.core import FlightCore, FrameInput

    core = FlightCore.from_config(CFG)
    k = core.engagement.params.drop_tracker_after
    assert k == 3
    t = 0.0

    def step(b: BoundingBox | None):
        nonlocal t
        s = core.step(FrameInput(t, b, LEVEL, 10.0))
        t += DT
        return s

    gate, ground = box(45.0, 309.0, 67.0), box(400.0, 330.0, 380.0)
    assert not any(step(gate).reset_tracker for _ in range(CFG.app.acquire_frames))
    assert core.phase is Phase.ENGAGE
    resets = [step(b).reset_tracker for b in (ground, ground, None, ground)]
    assert resets == [False, False, False, True]
    s = step(ground)
    assert not s.reset_tracker and core.engagement.refused == 4
    assert step(gate).decision.control.mode == "pn" and core.engagement.refused == 0  # the gate again: taken
    steps = [step(ground) for _ in range(6)]
    assert [s.reset_tracker for s in steps] == [False, False, True, False, False, True]
    ev = [e for e in steps[2].decision.events if "tracker told to drop" in e]
    assert ev == ["gate 1: tracker told to drop its target (its box refused 3 frames in a row)"], ev
    # drop_tracker_after 0: never.
    eng = Engagement.from_config(CFG, PNController.from_config(CFG),
                                 replace(EngagementParams.from_config(CFG), drop_tracker_after=0))
    t = 0.0
    for b in [gate] * CFG.app.acquire_frames + [ground] * 9:
        eng.step(t, b, LEVEL, 10.0)
        t += DT
        assert not eng.drop_tracker
    assert eng.phase is Phase.ENGAGE and eng.refused == 9


def test_a_far_gate_lost_leaves_no_range_to_dead_reckon_when_a_box_comes_back():
    """Real PX4 (SIH run057, 2026-12-06): the gate's box was 0.13 of the image when the detector lost it; 0.84 s later
    a background box 0.69 of the image tall appeared, and the engagement closed on the range it had dead-reckoned
    from the far box ("range -1.34 m"), 4 m beside the gate. Dead-reckoning is for the last metres of a ring that
    came to fill the view: the box must have been near when the image last gave a range. Here every other condition
    of the reckoned close holds at the background box (checked), and the engagement does not close on it."""
    imu = np.array([0.0, 0.0, -9.80665])
    v, t, d = 10.0, 0.0, 25.0
    eng = Engagement.from_config(CFG, PNController.from_config(CFG))
    p = eng.params
    while d > 9.0:  # the gate, growing to 107 px (0.17 of the width)
        eng.step(t, box(2.0 * F / d), LEVEL, 10.0, accel_frd=imu, t_now=t)
        t, d = t + DT, d - v * DT
    assert eng.phase is Phase.ENGAGE
    for _ in range(27):  # 0.9 s without a box
        eng.step(t, None, LEVEL, 10.0, accel_frd=imu, t_now=t)
        t, d = t + DT, d - v * DT
    dec = eng.step(t, box(400.0, 330.0, 250.0), LEVEL, 10.0, accel_frd=imu, t_now=t)
    d_est, d_dot, t_range = eng.controller.closing_estimate
    assert t_range is not None and 0.0 < t - t_range <= p.reckon_max and d_dot < -0.5
    assert d_est <= p.reckon_range, d_est  # dead-reckoned: the plane is reached
    assert dec.control.mode == "pn"  # the lock took the box (a gap that long explains any size)...
    assert eng.close.peak(t, p.near_window) >= p.lost_min_size  # ...and it is near now, but was not at the range
    assert eng.close.peak(t_range, p.near_window, until=t_range) < p.lost_min_size
    assert dec.phase is Phase.ENGAGE and "dead-reckoned" not in dec.why, dec.why


def test_the_gate_plane_reached_by_dead_reckoning_closes_the_engagement():
    """PX4 SIH (2026-12-06): after the ring filled the view, the detector's boxes were background of the same size
    ("2 m away", neither growing nor shrinking) and the app steered at them for up to 1.2 s after the crossing. An
    approach at 7 m/s (the IMU: unaccelerated) until the ring's box reaches 0.8 of the image height, then such boxes:
    the filter takes no range from them and dead-reckons; the engagement closes when that range reaches half the
    ring's radius (a pass off the centre never reaches 0), within a frame of the time the last range and the speed
    give. With ``app.close_reckoning=false`` it steers on."""
    imu = np.array([0.0, 0.0, -9.80665])  # FRD specific force of level, unaccelerated flight
    v = 7.0

    def run(*overrides: str) -> tuple[list, float]:
        cfg = load_config([], list(overrides))
        eng = Engagement.from_config(cfg, PNController.from_config(cfg))
        t, d, decs, t_fill = 0.0, 20.0, [], math.nan
        while t < 4.0:
            s = 2.0 * F / d
            if math.isnan(t_fill) and s < 0.8 * 480:
                b = box(s)
            else:  # the ring fills the view; then a background box that stays put
                t_fill = t if math.isnan(t_fill) else t_fill
                b = box(400.0)
            decs.append(eng.step(t, b, LEVEL, 10.0, accel_frd=imu, t_now=t))
            t, d = t + DT, d - v * DT
        return decs, t_fill

    decs, t_fill = run()
    close = next(x for x in decs if x.phase is Phase.PASS and x.changed)
    assert "dead-reckoned" in close.why, close.why
    d_fill = 2.0 * F / (0.8 * 480)  # ~2.5 m: the last range is at most one frame before t_fill
    assert t_fill - DT <= close.t <= t_fill + d_fill / v + 2 * DT, (close.t, t_fill, d_fill / v)
    r_half = 0.5 * load_config([], []).guidance.gate_radius
    assert abs(close.t - (20.0 - r_half) / v) <= 2 * DT, (close.t, (20.0 - r_half) / v)  # truth: r/2 from the plane
    decs, _ = run("app.close_reckoning=false")
    assert not any(x.phase is Phase.PASS for x in decs)  # without it: still steering at the background box
    assert decs[-1].phase is Phase.ENGAGE


def test_a_los_jump_onto_a_ring_filling_the_view_keeps_the_range_to_dead_reckon():
    """PX4 x500 (2026-12-06, run014): as the ring came to fill the view its box jumped sideways (its LOS moved
    faster than ``los_filter.max_rate``); the jump's frames were rejected, so the closing-speed filter never saw
    their size, and when the jump persisted the controller took it for a new target and forgot the range. With
    nothing to dead-reckon, the app steered at background boxes for 1.4 s after flying through the gate. Here: an
    approach at 10 m/s until the box is 0.75 of the image height, then the filling box 150 px to the side. The
    range survives the re-acquisition and the engagement closes where the truth is half the ring's radius out."""
    imu = np.array([0.0, 0.0, -9.80665])
    v, t, d = 10.0, 0.0, 20.0
    eng = Engagement.from_config(CFG, PNController.from_config(CFG))
    p, jumped, decs = eng.params, math.nan, []
    while t < 2.6:
        s = 2.0 * F / d
        if math.isnan(jumped) and s < 0.75 * 480:
            b = box(s)
        else:
            jumped = t if math.isnan(jumped) else jumped
            # >= closing_max_box (0.8) of the height: the ring fills the view; then it shrinks a little, as the
            # ring's and background's boxes did (no time-to-contact from the image)
            b = box(430.0 - 100.0 * (t - jumped), cx=470.0)
        decs.append(eng.step(t, b, LEVEL, 10.0, accel_frd=imu, t_now=t))
        if not math.isnan(jumped) and t - jumped < 1.5 * DT:  # the jump's first frames are rejected...
            assert decs[-1].control is not None and decs[-1].control.rejected.startswith("LOS jump")
        elif not math.isnan(jumped) and t - jumped < 2.5 * DT:  # ...until it persists: a new target
            assert decs[-1].control is not None and decs[-1].control.rejected is None
        t, d = t + DT, d - v * DT
    assert eng.controller.closing_estimate is not None  # the range is kept (and dead-reckoned)
    close = next(x for x in decs if x.phase is Phase.PASS and x.changed)
    assert "dead-reckoned" in close.why, close.why
    assert abs(close.t - (20.0 - p.reckon_range) / v) <= 2 * DT, (close.t, (20.0 - p.reckon_range) / v)
