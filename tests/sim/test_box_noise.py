"""The geometric camera's detector-like box error model: statistics over many draws, and white noise unchanged."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from companion.config import CameraConfig, Config
from companion.sim.boxnoise import PROFILES, DetectorNoise, DetectorNoiseParams, ar2_coefficients
from companion.sim.camera import GeometricCamera
from companion.sim.runner import RunSpec, run_once, with_overrides
from perception.los import CameraModel
from perception.types import BoundingBox

MODEL = CameraModel.from_config(CameraConfig())
P = np.array([0.0, 0.0, 10.0])
LEVEL = np.eye(3)
FACING = np.array([-1.0, 0.0, 0.0])
CLEAN = dataclasses.replace(PROFILES["x500"], wrong=(0.0,) * 6, glitch=(0.0,) * 6, miss=(0.0,) * 6)


def _errors(params: DetectorNoiseParams, box: BoundingBox, n: int, seed: int = 0) -> list[BoundingBox | None]:
    dn = DetectorNoise(params, np.random.default_rng(seed), 640, 480)
    return [dn.apply(box) for _ in range(n)]


def _autocorr(x: np.ndarray, k: int) -> float:
    x = x - x.mean()
    return float(x[:-k] @ x[k:] / (x @ x))


@pytest.mark.parametrize("rho1,rho2", [(0.78, 0.39), (0.85, 0.55), (0.5, 0.0), (0.3, 0.3)])
def test_yule_walker_coefficients_reproduce_the_autocorrelations(rho1, rho2):
    a1, a2 = ar2_coefficients(rho1, rho2)
    # The AR(2)'s own autocorrelation recursion: rho1 = a1 + a2 rho1, rho2 = a1 rho1 + a2.
    assert math.isclose(a1 + a2 * rho1, rho1, abs_tol=1e-12)
    assert math.isclose(a1 * rho1 + a2, rho2, abs_tol=1e-12)


@pytest.mark.parametrize("width", [20.0, 100.0, 300.0])
def test_centre_error_std_and_autocorrelation_match_the_parameters(width):
    box = BoundingBox(320.0, 240.0, width, width, 1.0, 0.0)
    boxes = _errors(CLEAN, box, 40_000, seed=int(width))
    ex = np.array([b.cx for b in boxes]) - 320.0
    ey = np.array([b.cy for b in boxes]) - 240.0
    sx, sy, _, _, bias, _ = CLEAN.at(width)
    assert abs(ex.mean()) < 0.1 * sx and abs(ey.mean()) < 0.1 * sy
    assert math.isclose(ex.std(), sx, rel_tol=0.05) and math.isclose(ey.std(), sy, rel_tol=0.05)
    for e in (ex, ey):
        assert abs(_autocorr(e, 1) - CLEAN.rho1) < 0.03
        assert abs(_autocorr(e, 2) - CLEAN.rho2) < 0.05
    # x and y errors are independent
    assert abs(np.corrcoef(ex, ey)[0, 1]) < 0.05
    w = np.array([b.w for b in boxes]) / width - 1.0
    assert math.isclose(float(np.median(w)), bias, abs_tol=0.005)
    assert math.isclose(float(w.std()), CLEAN.size_std, rel_tol=0.05)


def test_size_dependence_interpolates_and_holds_at_the_ends():
    p = PROFILES["x500"]
    assert p.at(5.0)[:2] == (p.std_x[0], p.std_y[0])
    assert p.at(5000.0)[:2] == (p.std_x[-1], p.std_y[-1])
    mid = math.sqrt(p.widths[1] * p.widths[2])  # log-midpoint
    assert math.isclose(p.at(mid)[0], 0.5 * (p.std_x[1] + p.std_x[2]), rel_tol=1e-9)


@pytest.mark.parametrize("stay", [0.0, 0.6])
def test_miss_wrong_target_and_glitch_rates(stay):
    n = 40_000 if stay == 0.0 else 160_000  # spells: fewer independent draws per frame
    params = dataclasses.replace(CLEAN, miss=(0.05,) * 6, wrong=(0.1,) * 6, glitch=(0.06,) * 6,
                                 std_x=(0.5,) * 6, std_y=(0.5,) * 6, miss_stay=stay, wrong_stay=stay)
    box = BoundingBox(320.0, 240.0, 100.0, 100.0, 1.0, 0.0)
    boxes = _errors(params, box, n, seed=7)
    got = [b for b in boxes if b is not None]
    miss = 1.0 - len(got) / n
    tol = 4.0 * math.sqrt(0.05 * 0.95 / n) * math.sqrt((1 + stay) / (1 - stay))  # AR(1)-like variance inflation
    assert abs(miss - 0.05) < tol
    spells = np.diff(np.flatnonzero(np.diff(np.r_[0, [b is None for b in boxes], 0])))[::2]
    start = 0.05 * (1.0 - stay) / (1.0 - 0.05 * stay - 0.1 * stay)  # a new miss spell's chance per draw
    assert math.isclose(float(spells.mean()), 1.0 / (1.0 - stay - (1.0 - stay) * start), rel_tol=0.05)
    off = np.array([math.hypot(b.cx - 320.0, b.cy - 240.0) for b in got])
    # With 0.5 px noise, an error over 10 px is a wrong target (> 50 px) or a glitch (15-50 px).
    for share, lo, hi in ((0.1, 50.0, 1e9), (0.06, 15.0, 50.0)):
        frac = float(np.mean((off > lo - 2.0) & (off <= hi + 2.0)))
        if lo == 15.0:
            share *= 1.0 - 0.1  # glitches are drawn on the frames that are not wrong targets
        infl = math.sqrt((1 + stay) / (1 - stay)) if lo == 50.0 else 1.0
        assert abs(frac - share) < 4.0 * math.sqrt(share * (1 - share) / len(got)) * infl + 0.005
    assert np.all(off[off > 10.0] >= 13.0)  # nothing in between: the inliers are tight
    assert all(0.0 <= b.cx <= 640.0 and 0.0 <= b.cy <= 480.0 and b.w >= 1.0 for b in got)


def test_the_box_trails_the_image_motion_by_the_lag():
    params = dataclasses.replace(CLEAN, std_x=(1e-6,) * 6, std_y=(1e-6,) * 6, lag_x=0.01, lag_y=0.005)
    dn = DetectorNoise(params, np.random.default_rng(0), 640, 480)
    for k in range(10):  # the ring moves at 300 px/s right and 150 px/s down
        b = dn.apply(BoundingBox(200.0 + 10.0 * k, 200.0 + 5.0 * k, 50.0, 50.0, 1.0, k / 30))
    assert math.isclose(b.cx, 290.0 - 0.01 * 300.0, abs_tol=1e-3)
    assert math.isclose(b.cy, 245.0 - 0.005 * 150.0, abs_tol=1e-3)


def test_no_box_in_gives_no_box_out():
    dn = DetectorNoise(PROFILES["sih"], np.random.default_rng(0), 640, 480)
    assert dn.apply(None) is None


def test_parameters_are_checked():
    with pytest.raises(ValueError, match="same non-zero length"):
        dataclasses.replace(CLEAN, wrong=(0.0,))
    with pytest.raises(ValueError, match="increasing"):
        dataclasses.replace(CLEAN, widths=(60.0, 38.0, 113.0, 253.0, 400.0, 450.0))
    with pytest.raises(ValueError, match="stationary"):
        dataclasses.replace(CLEAN, rho1=0.9, rho2=0.6)


def test_white_noise_is_unchanged_bit_for_bit():
    # The white model: the exact box plus four N(0, sigma) draws from the camera's generator, in that order.
    centre = P + np.array([20.0, 1.0, 0.5])
    cam = GeometricCamera(MODEL, pixel_noise=1.5, rng=np.random.default_rng(11))
    exact = cam.box_exact(P, LEVEL, centre, FACING, 1.0, 2.0)
    ref = np.random.default_rng(11).normal(0.0, 1.5, 4)
    box = cam.capture(2.0, P, LEVEL, centre, FACING, 1.0)
    assert (box.cx, box.cy, box.w, box.h) == (exact.cx + ref[0], exact.cy + ref[1], exact.w + ref[2], exact.h + ref[3])
    assert Config().sim.camera.noise_model == "white"
    a = run_once(Config(), RunSpec("planar", 3))
    b = run_once(with_overrides(Config(), {"sim": {"camera": {"noise_model": "white", "detector_profile": "sih"}}}),
                 RunSpec("planar", 3))
    assert a.as_dict([1.0]) == b.as_dict([1.0])


def test_the_simulator_uses_the_detector_model_when_asked():
    cfg = with_overrides(Config(), {"sim": {"camera": {"noise_model": "detector"}}})
    a = run_once(Config(), RunSpec("planar", 3))
    b = run_once(cfg, RunSpec("planar", 3))
    assert a.as_dict([1.0]) != b.as_dict([1.0])
    assert b.frames_with_box < b.frames  # misses
