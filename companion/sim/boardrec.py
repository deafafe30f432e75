"""A rendered mount-calibration recording: a checkerboard fixed in the world, the vehicle turned by hand.

``render_board_recording`` writes the same folder ``companion fly --record`` does (companion/app/record.py:
frames/ + index.csv with PX4's attitude at each capture + meta.json), drawn through a camera that sits on the
body with a *true* mount (which may differ from the configured one), so ``companion calibrate --mount`` can be
tested, and a study can calibrate from a rendered recording, against a known answer.

Each pixel's ray (undistorted with the camera's own distortion) is intersected with the board plane and coloured
by the square it hits; 3 x 3 supersampling smooths the edges as a real lens does (the corner finder's sub-pixel
refinement needs grey edges, not staircases).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from companion.frames import quat_wxyz_from_R

SUPERSAMPLE = 3
BACKGROUND = 110  # grey around the board
MARGIN_SQUARES = 1.0  # white border around the squares (the corner finder needs a quiet zone)


def board_frame(distance: float, cols: int, rows: int, square: float,
                R_ned_cam0: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(R_ned_board, origin_ned) of a board ``distance`` m along the optical axis of a camera at the origin with
    attitude ``R_ned_cam0`` (default: looking north), squarely facing it. Board frame = OpenCV object frame:
    x along the rows of corners, y down, z away from the camera; origin at the first inner corner."""
    R = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]) if R_ned_cam0 is None else R_ned_cam0
    centre = R[:, 2] * distance
    origin = centre - R[:, 0] * (cols - 2) * square / 2.0 - R[:, 1] * (rows - 2) * square / 2.0
    return R, origin


def render_board(K: np.ndarray, dist: np.ndarray, size: tuple[int, int], R_ned_cam: np.ndarray, c_ned: np.ndarray,
                 R_ned_board: np.ndarray, origin: np.ndarray, cols: int, rows: int, square: float) -> np.ndarray:
    """One grey frame (h, w) uint8 of the board seen by a camera at c_ned with attitude R_ned_cam."""
    w, h = size
    s = SUPERSAMPLE
    if not (dist.size and np.any(dist != 0.0)):
        return _render_homography(K, size, R_ned_cam, c_ned, R_ned_board, origin, cols, rows, square)
    u, v = np.meshgrid((np.arange(w * s) + 0.5) / s - 0.5, (np.arange(h * s) + 0.5) / s - 0.5)
    px = np.stack((u.ravel(), v.ravel()), axis=1)
    if dist.size and np.any(dist != 0.0):
        xy = cv2.undistortPoints(px.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
    else:
        xy = (px - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
    rays = np.column_stack((xy, np.ones(len(xy)))) @ R_ned_cam.T  # world NED
    n = R_ned_board[:, 2]
    denom = rays @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((origin - c_ned) @ n) / denom
    hit = np.isfinite(t) & (t > 0.0)
    p = c_ned + rays * np.where(hit, t, 0.0)[:, None]
    bx = (p - origin) @ R_ned_board[:, 0] / square
    by = (p - origin) @ R_ned_board[:, 1] / square
    m = MARGIN_SQUARES
    on_board = hit & (bx >= -1 - m) & (bx <= cols - 1 + m) & (by >= -1 - m) & (by <= rows - 1 + m)
    in_squares = on_board & (bx >= -1) & (bx <= cols - 1) & (by >= -1) & (by <= rows - 1)
    dark = in_squares & ((np.floor(bx) + np.floor(by)) % 2 == 0)
    img = np.full(len(px), float(BACKGROUND))
    img[on_board] = 235.0
    img[dark] = 25.0
    img = img.reshape(h * s, w * s)
    return cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA).round().astype(np.uint8)


def _render_homography(K: np.ndarray, size: tuple[int, int], R_ned_cam: np.ndarray, c_ned: np.ndarray,
                       R_ned_board: np.ndarray, origin: np.ndarray, cols: int, rows: int, square: float) -> np.ndarray:
    """Undistorted camera: the board plane maps to the image by a homography; warp a texture of the board at
    SUPERSAMPLE x the image's resolution, then average down (the same picture as the ray path, ~50x faster)."""
    w, h = size
    s = SUPERSAMPLE
    m = MARGIN_SQUARES
    ppsq = 40  # texture pixels per square
    tex_w, tex_h = round((cols + 2 * m) * ppsq), round((rows + 2 * m) * ppsq)
    ty, tx = np.mgrid[0:tex_h, 0:tex_w]
    bx, by = (tx + 0.5) / ppsq - 1 - m, (ty + 0.5) / ppsq - 1 - m  # board units (squares) of texel centres
    inside = (bx >= -1) & (bx <= cols - 1) & (by >= -1) & (by <= rows - 1)
    tex = np.where(inside & ((np.floor(bx) + np.floor(by)) % 2 == 0), 25, 235).astype(np.uint8)
    # Texel (tx, ty) -> board point (metres) -> camera -> supersampled pixel.
    R_cam_ned = R_ned_cam.T
    T_board = np.array([[1.0 / ppsq, 0.0, 0.5 / ppsq - 1 - m], [0.0, 1.0 / ppsq, 0.5 / ppsq - 1 - m],
                        [0.0, 0.0, 1.0]]) * np.array([[square], [square], [1.0]])
    P = np.column_stack((R_cam_ned @ R_ned_board[:, 0], R_cam_ned @ R_ned_board[:, 1], R_cam_ned @ (origin - c_ned)))
    S = np.array([[s, 0.0, (s - 1) / 2.0], [0.0, s, (s - 1) / 2.0], [0.0, 0.0, 1.0]])  # pixel u -> centre of its s x s
    H = S @ K @ P @ T_board
    big = cv2.warpPerspective(tex, H, (w * s, h * s), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                              borderValue=BACKGROUND)
    return cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA)


def hand_attitudes(n: int, rng: np.random.Generator, roll: float = 30.0, pitch: float = 10.0,
                   yaw: float = 12.0) -> list[np.ndarray]:
    """n body FRD -> NED attitudes of a vehicle held facing north and turned by hand (uniform within +- these
    deg about each axis; 0 for an axis it is not turned about). Roll is free (the board stays near the optical
    axis); pitch and yaw move it towards the image border, so a board filling the view allows less of them."""
    eul = rng.uniform(-1.0, 1.0, (n, 3)) * np.array([yaw, pitch, roll])
    return [Rotation.from_euler("ZYX", e, degrees=True).as_matrix() for e in eul]


def render_board_recording(folder: str | Path, camera: Any, R_body_cam_true: np.ndarray,
                           attitudes: Sequence[np.ndarray], *, cols: int = 10, rows: int = 7, square: float = 0.04,
                           distance: float = 0.8, lever_arm: Sequence[float] = (0.1, 0.0, 0.05),
                           rng: np.random.Generator | None = None, move: float = 0.05, rate: float = 10.0,
                           recorded_attitudes: Sequence[np.ndarray] | None = None) -> Path:
    """Write a recording of the board seen through ``R_body_cam_true`` (camera OpenCV -> body FRD).

    ``camera`` is a ``camera`` config section (intrinsics, distortion, size); the recording's meta.json holds it
    as a flight's would. ``attitudes`` are the true body -> NED rotations; ``recorded_attitudes`` (default: the
    same) are what index.csv says PX4 reported (a test can corrupt them). The vehicle also moves by up to
    ``move`` m (a hand is not a gimbal) and the camera sits ``lever_arm`` m (body FRD) from the body origin:
    neither may matter to a rotation calibration.
    """
    from companion.app.record import Recorder

    rng = rng if rng is not None else np.random.default_rng(0)
    K, dist = np.asarray(camera.K, float), np.asarray(camera.dist, float)
    size = (int(camera.width), int(camera.height))
    # The board stands squarely in front of the camera when the vehicle is level and faces north (as a person
    # would set it up: in view at rest), then the vehicle is turned about that attitude.
    R_ned_board, origin = board_frame(distance, cols, rows, square, R_body_cam_true)
    recorded = list(recorded_attitudes) if recorded_attitudes is not None else list(attitudes)
    rec = Recorder(folder, fmt="png", blocking=True, meta={"source": "companion.sim.boardrec",
                                                           "camera": camera.model_dump(mode="json")})
    try:
        for k, R in enumerate(attitudes):
            p = rng.uniform(-move, move, 3)
            c = p + R @ np.asarray(lever_arm, float)
            img = render_board(K, dist, size, R @ R_body_cam_true, c, R_ned_board, origin, cols, rows, square)
            rec.add(k + 1, k / rate, cv2.cvtColor(img, cv2.COLOR_GRAY2BGR), quat_wxyz_from_R(recorded[k]))
    finally:
        rec.close()
    return Path(folder)


def angle_deg(R: np.ndarray) -> float:
    """Rotation angle of R, deg."""
    return math.degrees(float(np.linalg.norm(Rotation.from_matrix(R).as_rotvec())))
