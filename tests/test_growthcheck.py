"""The growth check (companion/growthcheck.py): a box whose size does not follow our own acceleration towards it is
not the configured ring. Frames are made from a kinematic approach: the accelerometer's specific force from a
chosen acceleration along the line of sight, the box's size from the object's true size and distance."""

from __future__ import annotations

import numpy as np
import pytest

from companion.config import Config, camera_model, load_config
from companion.controller import PNController
from companion.engagement import Engagement, Phase
from companion.growthcheck import G, GrowthCheck, GrowthParams
from perception.los import los_world
from perception.types import BoundingBox

CFG = Config()
CAM = camera_model(CFG.camera)
F = float(CAM.K[0, 0])
R_LEVEL = np.eye(3)  # level, heading north
DT = 1.0 / 30.0
CX, CY = CAM.width / 2, CAM.height / 2
L = los_world(CAM, CX, CY, R_LEVEL)  # the line of sight of a box at the image centre, world NED


def frames(d0: float, radius: float, accel: float = 4.0, t_accel: float = 2.5, v0: float = 0.0,
           v_obj: float = 0.0, seconds: float = 4.0, noise: float = 0.0, seed: int = 0):
    """(t, box, specific force FRD) of an approach along L: we accelerate at ``accel`` for ``t_accel`` s from ``v0``,
    the object (true ``radius``) recedes along L at ``v_obj``; box size 2 f radius / distance (+ relative noise)."""
    rng = np.random.default_rng(seed)
    v, s, t = v0, 0.0, 0.0
    out = []
    while t < seconds:
        a = accel if t < t_accel else 0.0
        d = d0 - s + v_obj * t
        if d < 3.0:
            break
        size = 2.0 * F * radius / d * (1.0 + noise * rng.standard_normal())
        f_frd = R_LEVEL.T @ (a * L - np.array([0.0, 0.0, G]))  # what the accelerometer reads
        out.append((t, BoundingBox(CX, CY, size, size, 0.9, t), f_frd))
        v += a * DT
        s += v * DT
        t += DT
    return out


def run(check: GrowthCheck, seq) -> tuple[str, float | None]:
    """The first refusal and when (None: never)."""
    for t, b, f in seq:
        why = check.update(t, b, R_LEVEL, f)
        if why:
            return why, t
    return "", None


def check(**kw) -> GrowthCheck:
    p = GrowthParams(F, CFG.guidance.gate_radius, CAM.width, CAM.height, **kw)
    return GrowthCheck(p, CAM)


r = CFG.guidance.gate_radius


@pytest.mark.parametrize("d0,radius,v_obj,noise", [
    (20.0, r, 0.0, 0.0),  # the configured ring, still
    (20.0, r, 0.0, 0.03),  # with a detector's 3 % size noise
    (25.0, 2.0 * r, 0.0, 0.03),  # a gate twice the configured size (its box says half its distance)
    (20.0, r, 3.0, 0.03),  # receding at 3 m/s along the line of sight
    (20.0, r, -3.0, 0.0),  # coming at us
])
def test_a_ring_that_grows_as_our_motion_says_is_never_refused(d0, radius, v_obj, noise) -> None:
    for seed in range(5):
        why, _ = run(check(), frames(d0, radius, v_obj=v_obj, noise=noise, seed=seed))
        assert why == "", why


def test_a_far_object_whose_size_says_near_is_refused_after_the_push() -> None:
    # 100 m away, its box the size of the ring at 12 m: flying 10 m at it, the box grows 11 %, a ring's 500 %.
    seq = frames(100.0, r * 100.0 / 12.0, noise=0.03)
    why, t = run(check(), seq)
    assert why.startswith("not the target (growth)") and " m, but our own acceleration moved us " in why
    # judged once our acceleration moved us min_push (4 m: 1.41 s at 4 m/s^2), before max_push (10 m: 2.24 s)
    assert t is not None and 1.41 <= t <= 2.3
    c = check()
    run(c, seq)
    assert c.failed and c.scale is not None and max(c.scale) < 0.3
    # and it stays refused for the engagement, box or not
    assert c.update(5.0, seq[-1][1], R_LEVEL, seq[-1][2]) == c.failed
    assert c.update(5.1, None, R_LEVEL, seq[-1][2]) == c.failed


def test_nothing_is_judged_without_acceleration_or_accelerometer_or_size() -> None:
    far = r * 100.0 / 12.0
    cruise = frames(100.0, far, accel=0.0, v0=8.0)  # at cruise: our acceleration moved us nowhere
    assert run(check(), cruise) == ("", None)
    no_imu = [(t, b, None) for t, b, _ in frames(100.0, far)]
    assert run(check(), no_imu) == ("", None)
    assert run(GrowthCheck(GrowthParams(F, 0.0, CAM.width, CAM.height), CAM), frames(100.0, far)) == ("", None)


def test_cut_boxes_say_no_range() -> None:
    far = r * 100.0 / 12.0
    cut = [(t, BoundingBox(b.w / 2, CY, b.w, b.h, 0.9, t), f) for t, b, f in frames(100.0, far)]  # left edge at 0
    assert run(check(), cut) == ("", None)


def test_judged_only_within_the_push_window() -> None:
    far = r * 100.0 / 12.0
    seq = frames(100.0, far)
    c = check(max_push=3.0)  # stops judging before min_push is reached
    assert run(c, seq) == ("", None)


def _engage(overrides: list[str], seq) -> list:
    cfg = load_config([], overrides)
    eng = Engagement.from_config(cfg, PNController.from_config(cfg))
    level = np.array([1.0, 0.0, 0.0, 0.0])
    out = []
    b0 = seq[0][1]
    t = 0.0
    while eng.phase is Phase.ACQUIRE:  # hover on the first box until engaged
        out.append(eng.step(t, BoundingBox(b0.cx, b0.cy, b0.w, b0.h, 0.9, t), level, 10.0,
                            accel_frd=np.array([0.0, 0.0, -G])))
        t += DT
    for ts, b, f in seq:
        out.append(eng.step(t + ts, b, level, 10.0, accel_frd=f))
        if eng.phase is not Phase.ENGAGE:
            break
    return out


def test_the_engagement_coasts_then_loses_a_far_object_and_logs_why() -> None:
    far = r * 100.0 / 12.0
    seq = frames(100.0, far, seconds=6.0)
    out = _engage(["app.verify.growth=true"], seq)
    events = [e for d in out for e in d.events]
    assert any("box rejected, not the target (growth)" in e for e in events), events
    assert out[-1].phase is Phase.ABORT and "no usable box" in out[-1].why
    off = _engage(["app.verify.growth=false"], seq)  # the same frames without the check: flown at to the end
    assert all(d.phase in (Phase.ACQUIRE, Phase.ENGAGE) for d in off)
    ring = _engage(["app.verify.growth=true"], frames(20.0, r, seconds=3.0, noise=0.03))
    assert not any("growth" in e for d in ring for e in d.events)
