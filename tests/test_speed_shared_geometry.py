"""Issue 21 (the engagement's per-frame checks): the work shared between checks, and the growth check's float
arithmetic, give the same floats, bit for bit, as each check computing its own (the suites must not move)."""

from __future__ import annotations

import math

import numpy as np

from companion.config import Config, camera_model, load_config
from companion.core import FlightCore, FrameInput
from companion.engagement import Engagement
from companion.frames import R_from_quat_wxyz
from companion.growthcheck import G, GrowthCheck, GrowthParams
from companion.targetlock import LockParams, TargetLock
from perception.los import los_world
from perception.types import BoundingBox

RNG = np.random.default_rng(2121)
CFG = Config()
CAM = camera_model(CFG.camera)


class _NumpyGrowth(GrowthCheck):
    """The growth check's integration as numpy arrays (the form the float arithmetic replaced)."""

    def integrate(self, t: float, R: np.ndarray, accel: np.ndarray) -> None:
        a_ned = R @ accel + np.array([0.0, 0.0, G])
        if not np.all(np.isfinite(a_ned)):
            return
        if self._t is None:
            self._t, self._a_prev = t, a_ned  # type: ignore[assignment]
            return
        dt = t - self._t
        if not (0.0 < dt <= self.p.max_dt):
            self._t, self._a_prev = t, a_ned  # type: ignore[assignment]
            return
        v0 = float(self._v @ self._l)  # type: ignore[operator]
        self._v = self._v + 0.5 * (self._a_prev + a_ned) * dt  # type: ignore[operator]
        self._s += 0.5 * (v0 + float(self._v @ self._l)) * dt  # type: ignore[operator]
        self._t, self._a_prev = t, a_ned  # type: ignore[assignment]


def test_the_growth_checks_float_trapezoids_are_the_array_form() -> None:
    params = GrowthParams(float(CAM.K[0, 0]), 0.75, CAM.width, CAM.height, max_push=1e9, min_scale=-1e9)
    for _ in range(40):
        new, ref = GrowthCheck(params, CAM), _NumpyGrowth(params, CAM)
        t = 0.0
        for k in range(60):
            t += float(RNG.choice([1 / 30, 2 / 30, 0.7]))
            R = R_from_quat_wxyz(RNG.standard_normal(4))
            accel = RNG.standard_normal(3) * RNG.uniform(0.1, 20.0)
            if k % 17 == 5:
                accel[k % 3] = math.nan
            box = BoundingBox(float(RNG.uniform(50, 590)), float(RNG.uniform(50, 430)), 40.0, 38.0)
            new.update(t, box, R, accel)
            ref._l = los_world(CAM, box.cx, box.cy, R)
            ref.integrate(t, R, accel)
            assert new._s == ref._s
            assert np.asarray(new._v).tobytes() == np.asarray(ref._v).tobytes()


def test_the_locks_los_is_the_growth_checks_own() -> None:
    lock = TargetLock(LockParams(v_max=15.0, gate_radius=0.75, max_los_rate=3.0), CAM)
    for _ in range(200):
        R = R_from_quat_wxyz(RNG.standard_normal(4))
        box = BoundingBox(float(RNG.uniform(0, 640)), float(RNG.uniform(0, 480)), 30.0, 30.0)
        lock.reset()
        assert lock.check(0.0, box, R).ok
        assert lock.ref_los is not None
        assert lock.ref_los.tobytes() == los_world(CAM, box.cx, box.cy, R).tobytes()


def test_one_attitude_matrix_a_frame_is_the_quaternions() -> None:
    cfg = load_config()
    core = FlightCore.from_config(cfg)
    eng: Engagement = core.engagement
    for _ in range(20):
        q = RNG.standard_normal(4)
        core.step(FrameInput(0.1, None, q, 10.0))
        R = eng.frame_attitude()
        assert R is eng.frame_attitude()  # built once a frame
        assert R.tobytes() == R_from_quat_wxyz(q.copy()).tobytes()

