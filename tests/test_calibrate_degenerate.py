"""``companion calibrate`` refuses a set that fits well but cannot tell the focal length (issue 22): boards
moved around the image but never tilted. Rendered through the same known lens as tests/test_calibrate.py.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_calibrate import D_TRUE, K_TRUE, H, W, _calibrate, _pose, _write_views

from companion.calibrate import plausibility_problem, tilt_spread
from companion.cameramodel import distortion_problem

# 30 square-on views over the whole image (spun about the optical axis only): a fronto-parallel set.
_GRID = [(u, v) for u in (100, 200, 320, 440, 540) for v in (80, 160, 240, 320, 400)]
FLAT_POSES = [(u, v, 0.5 + 0.1 * (k % 3), 0.0, 0.0, (k % 5 - 2) * 6.0)
              for k, (u, v) in enumerate([*_GRID, (60, 40), (580, 40), (60, 440), (580, 440), (320, 240)])]


@pytest.mark.timeout(300)
def test_calibrate_refuses_square_on_views(tmp_path):
    views = tmp_path / "flat"
    _write_views(views, FLAT_POSES)
    out = tmp_path / "camera.yaml"
    res = _calibrate(views, out)
    # Before the fix: exit 0, fx ~5000 (true 510) at RMS 0.1 px.
    assert res.returncode == 2, res.stdout
    assert not out.exists()
    assert len(res.stderr.strip().splitlines()) == 1 and "hardly tilted" in res.stderr


def test_tilt_spread_measures_the_least_tilted_axis():
    flat = [_pose(*p)[0] for p in FLAT_POSES]
    assert tilt_spread(flat) == pytest.approx(0.0, abs=1e-6)
    # Tilted 30 deg about x only: still no tilt about y -> spread 0 (one axis is not enough).
    one_axis = [_pose(320, 240, 0.5, s * 30.0, 0.0, 0.0)[0] for s in (-1, 1)]
    assert tilt_spread(one_axis) == pytest.approx(0.0, abs=1e-6)
    # +-30 deg about x and about y, one view each: normal offsets (sin 30, 0) x2 and (0, sin 30) x2 -> the
    # second moment is diag(0.125, 0.125), sqrt = 0.354 = sin 20.7 deg.
    both = [_pose(320, 240, 0.5, tx, ty, 0.0)[0] for tx, ty in ((30, 0), (-30, 0), (0, 30), (0, -30))]
    assert tilt_spread(both) == pytest.approx(np.degrees(np.arcsin(np.sqrt(0.125))), abs=1e-6)


def test_plausibility_refuses_the_degenerate_result_and_keeps_the_true_lens():
    std = np.array([1.0, 1.0, 1.0, 1.0])
    bad = np.array([[3646.0, 0, 330], [0, 3640.0, 240], [0, 0, 1]])  # the fx (a 10 deg field of view)
    msg = plausibility_problem(bad, np.array([0, 0, 0, 0, -2182.0]), std, (W, H), 15.0)
    assert msg is not None and "field of view" in msg
    assert plausibility_problem(K_TRUE, D_TRUE, std, (W, H), 15.0) is None
    assert "uncertain" in plausibility_problem(K_TRUE, D_TRUE, np.array([30.0, 1, 1, 1]), (W, H), 15.0)
    off = K_TRUE.copy()
    off[0, 2] = 600.0
    assert "principal point" in plausibility_problem(off, D_TRUE, std, (W, H), 15.0)


def test_distortion_problem_on_real_and_absurd_lenses():
    assert distortion_problem(K_TRUE, D_TRUE, W, H) is None
    assert distortion_problem(K_TRUE, np.zeros(5), W, H) is None
    assert distortion_problem(K_TRUE, np.array([-0.3, 0.1, 0, 0, 0]), W, H) is None  # strong barrel, still 1:1
    assert "tangential" in distortion_problem(K_TRUE, np.array([50, -3000, .5, .5, 1e6]), W, H)
    # The radial part: monotonic, but squeezes the image to a few degrees (6x its pinhole radius).
    assert "implausible" in distortion_problem(K_TRUE, np.array([50, -3000, 0, 0, 1e6]), W, H)
    # k1 = -0.4: r(1 - 0.4 r^2) peaks at 0.61 (310 px at f 510), the corner is 0.79 away: no ray reaches it.
    assert "not invertible" in distortion_problem(K_TRUE, np.array([-0.4, 0, 0, 0, 0]), W, H)
