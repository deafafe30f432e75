"""``companion calibrate --mount``: the camera -> body rotation from a recording of a still board, against
recordings rendered through known true mounts (companion/sim/boardrec.py)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from companion.calibrate import Board
from companion.config import load_config
from companion.mountcal import MountRefused, board_views, mount_angles, solve_mount, write_mount
from companion.sim.boardrec import angle_deg, hand_attitudes, render_board_recording
from companion.sim.camera import true_camera_config

pytestmark = pytest.mark.timeout(120)
BOARD = Board("checkerboard", 10, 7, 0.04)


def _true(mount: tuple[float, float, float], error: tuple[float, float, float]):
    """(config the app holds, the camera's true R_body_cam) for a configured mount and a mount error."""
    ov = [f"camera.mount.{k}={v}" for k, v in zip(("roll", "pitch", "yaw"), mount, strict=True)]
    ov += [f"sim.camera.mount_error.{k}={v}" for k, v in zip(("roll", "pitch", "yaw"), error, strict=True)]
    cfg = load_config([], ov)
    return cfg, true_camera_config(cfg).R_body_cam


def _record(tmp_path, cfg, R_true, n=16, seed=1, name="rec", **kw):
    return render_board_recording(tmp_path / name, cfg.camera, R_true, hand_attitudes(n, np.random.default_rng(seed)),
                                  rng=np.random.default_rng(seed + 100), **kw)


@pytest.mark.parametrize(("mount", "error"), [((0, 0, 0), (0, 5, 0)), ((0, 0, 0), (1, -5, 3)),
                                              ((0, 20, 0), (-2, 4, -3))])
def test_the_mount_is_recovered_from_a_rendered_recording(tmp_path, mount, error):
    cfg, R_true = _true(mount, error)
    rec = _record(tmp_path, cfg, R_true)
    R_wb, R_cb, frames = board_views(rec, BOARD, cfg.camera.K, cfg.camera.dist)
    assert frames == 16 and len(R_wb) >= 12
    r = solve_mount(R_wb, R_cb)
    assert angle_deg(r.R_body_cam.T @ R_true) < 0.3
    expected = np.add(mount, error)  # the true mount angles (small angles, roll/yaw about the same axes)
    assert np.allclose((r.roll, r.pitch, r.yaw), mount_angles(R_true), atol=0.3)
    assert np.allclose(mount_angles(R_true), expected, atol=1e-9)
    assert r.residual_deg < 0.2


def test_cli_writes_the_mount_into_the_camera_yaml_and_keeps_the_rest(tmp_path):
    cfg, R_true = _true((0, 0, 0), (0, 5, -3))
    rec = _record(tmp_path, cfg, R_true)
    cam = tmp_path / "camera.yaml"
    K = cfg.camera.K
    cam.write_text("# my camera, calibrated 2026-12-01\ncamera:\n  width: 640\n  height: 480\n"
                   f"  fx: {K[0, 0]:.6f}  # from companion calibrate\n  fy: {K[1, 1]:.6f}\n"
                   "  mount:\n    roll: 0\n    pitch: 0\n    yaw: 0\n  rate: 30\nsim:\n  seed: 7\n", encoding="utf-8")
    res = subprocess.run([sys.executable, "-m", "companion.cli", "calibrate", str(rec), "--mount", "--cols", "10",
                          "--rows", "7", "--square", "0.04", "-o", str(cam)], capture_output=True, text=True,
                         timeout=100)
    assert res.returncode == 0, res.stderr
    assert "residual" in res.stdout
    text = cam.read_text(encoding="utf-8")
    assert text.startswith("# my camera, calibrated 2026-12-01\n") and "# from companion calibrate" in text
    data = yaml.safe_load(text)
    assert data["sim"] == {"seed": 7} and data["camera"]["rate"] == 30 and data["camera"]["width"] == 640
    # The app, loading the written file, now holds the true mount.
    held = load_config([cam]).camera.R_body_cam
    assert angle_deg(held.T @ R_true) < 0.3


def test_a_recording_without_enough_views_is_refused(tmp_path):
    cfg, R_true = _true((0, 0, 0), (0, 5, 0))
    rec = _record(tmp_path, cfg, R_true, n=5)
    out = tmp_path / "camera.yaml"
    args = [sys.executable, "-m", "companion.cli", "calibrate", str(rec), "--mount", "--cols", "10", "--rows", "7",
            "-o", str(out)]
    res = subprocess.run(args, capture_output=True, text=True, timeout=100)
    assert res.returncode == 2 and "no such camera YAML" in res.stderr  # no intrinsics: nothing to calibrate with
    out.write_text("camera:\n  width: 640  # mine\n", encoding="utf-8")
    res = subprocess.run(args, capture_output=True, text=True, timeout=100)
    assert res.returncode == 2 and "refused: too few views" in res.stderr
    assert out.read_text(encoding="utf-8") == "camera:\n  width: 640  # mine\n"  # left as it was
    assert len(res.stderr.strip().splitlines()) == 1


def _synthetic_views(rng, R_true, attitudes, noise_deg=0.0):
    """Board poses an ideal camera would measure: R_cam_board = (R_wb X)^T W, W fixed; attitude noise optional."""
    W = Rotation.from_euler("xyz", [3, -2, 90], degrees=True).as_matrix()
    R_cb = [(R @ R_true).T @ W for R in attitudes]
    noisy = [Rotation.from_rotvec(np.radians(noise_deg) * rng.normal(size=3)).as_matrix() @ R for R in attitudes]
    return noisy, R_cb


def test_rotation_about_one_axis_only_is_refused_and_two_axes_are_enough():
    rng = np.random.default_rng(3)
    _, R_true = _true((0, 0, 0), (2, 5, -3))
    yaw_only = [Rotation.from_euler("z", a, degrees=True).as_matrix() for a in rng.uniform(-30, 30, 20)]
    with pytest.raises(MountRefused, match="rotation diversity"):
        solve_mount(*_synthetic_views(rng, R_true, yaw_only))
    two = [Rotation.from_euler("ZY", e, degrees=True).as_matrix() for e in rng.uniform(-20, 20, (20, 2))]
    r = solve_mount(*_synthetic_views(rng, R_true, two))
    assert angle_deg(r.R_body_cam.T @ R_true) < 1e-6 and r.residual_deg < 1e-6


def test_attitudes_that_do_not_match_the_frames_are_refused_on_the_residual():
    rng = np.random.default_rng(4)
    _, R_true = _true((0, 0, 0), (0, 5, 0))
    att = hand_attitudes(20, rng)
    r = solve_mount(*_synthetic_views(rng, R_true, att, noise_deg=0.05))
    assert r.residual_deg < 1.0 and angle_deg(r.R_body_cam.T @ R_true) < 0.3
    with pytest.raises(MountRefused, match="residual"):
        solve_mount(*_synthetic_views(rng, R_true, att, noise_deg=3.0))


def test_write_mount_adds_a_camera_block_to_a_file_without_one(tmp_path):
    _, R_true = _true((0, 0, 0), (0, 5, 0))
    rng = np.random.default_rng(5)
    r = solve_mount(*_synthetic_views(rng, R_true, hand_attitudes(12, rng)))
    f = tmp_path / "c.yaml"
    f.write_text("guidance:\n  k_pn: 3\n", encoding="utf-8")
    write_mount(f, r, "rec")
    data = yaml.safe_load(f.read_text(encoding="utf-8"))
    assert data["guidance"] == {"k_pn": 3} and data["camera"]["mount"]["pitch"] == pytest.approx(5.0, abs=1e-3)
    flow = tmp_path / "flow.yaml"
    flow.write_text("camera: {width: 640}\n", encoding="utf-8")
    with pytest.raises(ValueError, match="not a block"):
        write_mount(flow, r, "rec")
