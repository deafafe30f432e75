"""``companion calibrate`` on checkerboard views rendered through known intrinsics and distortion.

Each image pixel is traced back through the true distortion (``cv2.undistortPoints`` with tight criteria) and the
board pose (plane homography) onto a drawn board, so the images carry the lens exactly; the command
must recover fx, fy, cx, cy within 1 % and the distortion's effect within 0.5 px over the part of the
image the views cover, and refuse poor sets with one line and exit 2.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from companion.config import load_config

W, H = 640, 480
K_TRUE = np.array([[510.0, 0.0, 326.0], [0.0, 505.0, 236.0], [0.0, 0.0, 1.0]])
D_TRUE = np.array([-0.15, 0.04, 0.001, -0.0008, 0.0])  # barrel, typical of a ~70 deg webcam lens
COLS, ROWS, SQ = 10, 7, 0.025  # squares; 9 x 6 inner corners
PX = 40  # board image: px per square
MARGIN = 1  # white squares around the pattern


def _board_image() -> np.ndarray:
    nx, ny = COLS + 2 * MARGIN, ROWS + 2 * MARGIN
    img = np.full((ny * PX, nx * PX), 255, np.uint8)
    for j in range(ROWS):
        for i in range(COLS):
            if (i + j) % 2 == 0:
                y0, x0 = (j + MARGIN) * PX, (i + MARGIN) * PX
                img[y0:y0 + PX, x0:x0 + PX] = 0
    return img


def _rays() -> np.ndarray:
    """Undistorted normalised coordinates (x, y) of every pixel centre under the true lens."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    pts = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    und = cv2.undistortPoints(pts, K_TRUE, D_TRUE, None, None, None, crit).reshape(H, W, 2)
    return und


def _render(rays: np.ndarray, board: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, rng) -> np.ndarray:
    R = Rotation.from_rotvec(rvec).as_matrix()
    Hm = np.column_stack([R[:, 0], R[:, 1], tvec])  # board (X, Y, 1) -> normalised camera (x, y, 1) ~
    Hinv = np.linalg.inv(Hm)
    x, y = rays[..., 0], rays[..., 1]
    X = Hinv[0, 0] * x + Hinv[0, 1] * y + Hinv[0, 2]
    Y = Hinv[1, 0] * x + Hinv[1, 1] * y + Hinv[1, 2]
    Z = Hinv[2, 0] * x + Hinv[2, 1] * y + Hinv[2, 2]
    X, Y = X / Z, Y / Z
    # Inner corner (0, 0) is the corner between the first two squares: board-image pixel (MARGIN + 1) * PX.
    mx = ((X / SQ + MARGIN + 1) * PX - 0.5).astype(np.float32)
    my = ((Y / SQ + MARGIN + 1) * PX - 0.5).astype(np.float32)
    img = cv2.remap(board, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                    borderValue=150)
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    noisy = img.astype(np.float32) + rng.normal(0, 2.0, img.shape)
    return cv2.cvtColor(np.clip(noisy, 0, 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)


def _pose(u: float, v: float, depth: float, tilt_x: float, tilt_y: float, spin: float) -> tuple[np.ndarray, ...]:
    """Board pose whose centre lands on pixel (u, v) of the undistorted image at the given depth."""
    R = Rotation.from_euler("xyz", [tilt_x, tilt_y, spin], degrees=True)
    centre = np.array([(COLS - 2) * SQ / 2, (ROWS - 2) * SQ / 2, 0.0])
    ray = np.linalg.inv(K_TRUE) @ np.array([u, v, 1.0])
    t = depth * ray - R.apply(centre)
    return R.as_rotvec(), t


def _write_views(folder: Path, poses: list[tuple[float, ...]], seed: int = 0) -> None:
    folder.mkdir(parents=True)
    rays, board, rng = _rays(), _board_image(), np.random.default_rng(seed)
    for k, p in enumerate(poses):
        rvec, tvec = _pose(*p)
        cv2.imwrite(str(folder / f"view_{k:02d}.png"), _render(rays, board, rvec, tvec, rng))


def _good_poses() -> list[tuple[float, ...]]:
    """(u, v, depth m, tilt about x deg, tilt about y deg, spin deg): the centre tilted four ways, the
    edges and corners tilted twice each, and a small far board in each corner of the image."""
    poses: list[tuple[float, ...]] = []
    k = 0
    for u, v in ((320, 240), (150, 110), (490, 110), (150, 370), (490, 370), (320, 100), (320, 380), (130, 240),
                 (510, 240)):
        sx, sy = np.sign(u - 320), np.sign(240 - v)
        tilts = ([(35, 0), (-35, 0), (0, 35), (0, -35)] if (u, v) == (320, 240) else
                 [(25 * sy if sy else 0, -25 * sx if sx else 0), (-15 * sy if sy else 30, 15 * sx if sx else 30)])
        for tx, ty in tilts:
            poses.append((u, v, 0.5 + 0.05 * (k % 3), tx, ty, (k % 5 - 2) * 6))
            k += 1
    poses += [(u, v, 0.7, 10 * np.sign(240 - v), 10 * np.sign(u - 320), 0) for u in (40, 600) for v in (30, 450)]
    return poses


GOOD_POSES = _good_poses()


def _covered_area(poses: list[tuple[float, ...]]) -> np.ndarray:
    """Convex hull of the true image positions of every board corner that is fully in view."""
    obj = np.array([(i * SQ, j * SQ, 0.0) for j in range(ROWS - 1) for i in range(COLS - 1)])
    pts = []
    for p in poses:
        rvec, tvec = _pose(*p)
        img, _ = cv2.projectPoints(obj, rvec, tvec, K_TRUE, D_TRUE)
        img = img.reshape(-1, 2)
        if (img.min(0) >= 2).all() and (img.max(0) <= (W - 3, H - 3)).all():
            pts.append(img)
    return cv2.convexHull(np.vstack(pts).astype(np.float32))


def _distortion_effect(pix: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """How far the lens moves each pixel, in the true camera's pixels: undistorted minus pinhole position."""
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    n = cv2.undistortPoints(pix.reshape(-1, 1, 2), K, dist, None, None, None, crit).reshape(-1, 2)
    pinhole = (pix - K[:2, 2]) / np.diag(K)[:2]
    return (n - pinhole) * K_TRUE[0, 0]


def _calibrate(folder: Path, out: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "companion.cli", "calibrate", str(folder), "--cols", str(COLS),
                           "--rows", str(ROWS), "--square", str(SQ), "-o", str(out), *extra],
                          capture_output=True, text=True, timeout=300)


@pytest.mark.timeout(300)
def test_calibrate_recovers_known_intrinsics_and_distortion(tmp_path):
    views = tmp_path / "views"
    _write_views(views, GOOD_POSES)
    out = tmp_path / "camera.yaml"
    res = _calibrate(views, out)
    assert res.returncode == 0, res.stderr
    cam = yaml.safe_load(out.read_text())["camera"]
    for key, true in (("fx", K_TRUE[0, 0]), ("fy", K_TRUE[1, 1]), ("cx", K_TRUE[0, 2]), ("cy", K_TRUE[1, 2])):
        assert cam[key] == pytest.approx(true, rel=0.01), (key, cam)
    assert (cam["width"], cam["height"]) == (W, H)

    # The distortion's effect (how far the lens moves a pixel) under the true and the estimated model, on a
    # 4 px grid over the part of the image the views cover (outside it a calibration only extrapolates).
    K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1.0]])
    u, v = np.meshgrid(np.arange(0, W, 4, dtype=float), np.arange(0, H, 4, dtype=float))
    pix = np.stack([u.ravel(), v.ravel()], 1)
    hull = _covered_area(GOOD_POSES)
    inside = np.array([cv2.pointPolygonTest(hull, (float(x), float(y)), False) >= 0 for x, y in pix])
    assert inside.mean() > 0.6  # the views reach most of the image
    true_effect = _distortion_effect(pix[inside], K_TRUE, D_TRUE)
    err = np.linalg.norm(true_effect - _distortion_effect(pix[inside], K, np.array(cam["distortion"])), axis=1)
    assert err.max() < 0.5, f"max {err.max():.2f} px, median {np.median(err):.2f} px"
    # The effect being checked is large: it moves pixels by 15-20 px near the edges.
    assert np.linalg.norm(true_effect, axis=1).max() > 15.0

    assert "RMS reprojection error" in out.read_text() and "RMS reprojection error" in res.stdout
    cfg = load_config([out])  # --config accepts the file as it is
    assert cfg.camera.K[0, 0] == pytest.approx(cam["fx"]) and list(cfg.camera.distortion) == cam["distortion"]


@pytest.mark.timeout(300)
def test_calibrate_refuses_poor_sets(tmp_path):
    few = tmp_path / "few"
    _write_views(few, GOOD_POSES[:4])
    res = _calibrate(few, tmp_path / "a.yaml")
    assert res.returncode == 2 and not (tmp_path / "a.yaml").exists()
    assert len(res.stderr.strip().splitlines()) == 1 and "too few views" in res.stderr

    centre = tmp_path / "centre"  # 12 views, all in the middle of the image
    _write_views(centre, [(290 + 30 * (k % 3), 215 + 15 * (k // 3), 0.9, 8 * ((k % 2) - 0.5), 6 * (k % 3 - 1), k)
                          for k in range(12)])
    res = _calibrate(centre, tmp_path / "b.yaml")
    assert res.returncode == 2 and not (tmp_path / "b.yaml").exists()
    assert len(res.stderr.strip().splitlines()) == 1 and "too little of the image covered" in res.stderr

    res = _calibrate(tmp_path / "missing", tmp_path / "c.yaml")
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1


def _charuco_views(folder: Path, poses: list[tuple[float, ...]]) -> None:
    """The same lens and poses, a ChArUco board (7 x 5 squares of 40 mm, 30 mm markers) instead."""
    cols, rows, sq, px = 7, 5, 0.04, 80
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    board = cv2.aruco.CharucoBoard((cols, rows), sq, 0.03, d).generateImage((cols * px, rows * px), marginSize=0)
    board = cv2.copyMakeBorder(board, px, px, px, px, cv2.BORDER_CONSTANT, value=255)
    folder.mkdir(parents=True)
    rays, rng = _rays(), np.random.default_rng(1)
    for k, (u, v, depth, tx, ty, spin) in enumerate(poses):
        R = Rotation.from_euler("xyz", [tx, ty, spin], degrees=True)
        t = depth * (np.linalg.inv(K_TRUE) @ np.array([u, v, 1.0])) - R.apply([cols * sq / 2, rows * sq / 2, 0.0])
        Rm = R.as_matrix()
        Hinv = np.linalg.inv(np.column_stack([Rm[:, 0], Rm[:, 1], t]))
        x, y = rays[..., 0], rays[..., 1]
        Z = Hinv[2, 0] * x + Hinv[2, 1] * y + Hinv[2, 2]
        X = (Hinv[0, 0] * x + Hinv[0, 1] * y + Hinv[0, 2]) / Z
        Y = (Hinv[1, 0] * x + Hinv[1, 1] * y + Hinv[1, 2]) / Z
        mx = ((X / sq + 1) * px - 0.5).astype(np.float32)
        my = ((Y / sq + 1) * px - 0.5).astype(np.float32)
        img = cv2.GaussianBlur(cv2.remap(board, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                         borderValue=150), (0, 0), 0.8)
        noisy = np.clip(img.astype(np.float32) + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)
        cv2.imwrite(str(folder / f"view_{k:02d}.png"), noisy)


@pytest.mark.timeout(300)
def test_calibrate_with_a_charuco_board(tmp_path):
    views = tmp_path / "charuco"
    _charuco_views(views, GOOD_POSES)
    out = tmp_path / "camera.yaml"
    res = subprocess.run([sys.executable, "-m", "companion.cli", "calibrate", str(views), "--board", "charuco",
                          "--cols", "7", "--rows", "5", "--square", "0.04", "--marker", "0.03", "-o", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    cam = yaml.safe_load(out.read_text())["camera"]
    for key, true in (("fx", K_TRUE[0, 0]), ("fy", K_TRUE[1, 1]), ("cx", K_TRUE[0, 2]), ("cy", K_TRUE[1, 2])):
        assert cam[key] == pytest.approx(true, rel=0.01), (key, cam)


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_calibrate_from_a_video_counts_a_held_board_once(tmp_path):
    """The same views as a video file, each held for 2 frames: one view each, intrinsics still within 1 %."""
    views = tmp_path / "views"
    _write_views(views, GOOD_POSES)
    video = tmp_path / "board.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (W, H))
    for f in sorted(views.iterdir()):
        img = cv2.imread(str(f))
        w.write(img)
        w.write(img)
    w.release()
    out = tmp_path / "camera.yaml"
    res = _calibrate(video, out)
    assert res.returncode == 0, res.stderr
    cam = yaml.safe_load(out.read_text())["camera"]
    for key, true in (("fx", K_TRUE[0, 0]), ("fy", K_TRUE[1, 1]), ("cx", K_TRUE[0, 2]), ("cy", K_TRUE[1, 2])):
        assert cam[key] == pytest.approx(true, rel=0.01), (key, cam)
    found = int(res.stdout.split(" views,")[0].split()[-1])
    assert 10 <= found <= len(GOOD_POSES)  # 2 identical frames = 1 view (else up to twice as many)
