"""Is a camera model (K + OpenCV distortion) a lens at all? Checked where a camera YAML is loaded and where
``companion calibrate`` writes one.

A distortion polynomial can fold the image over itself (two pixels seeing one ray) or send rays outward
without bound; ``cv2.undistortPoints`` then returns *some* ray for every pixel without complaint, and every
LOS computed through it is wrong. A usable model maps the image one-to-one: on a grid over the whole image,
the undistorted rays keep the pixels' order along every row and column (monotonic) and distorting them again
gives back the pixel (invertible).
"""

from __future__ import annotations

import cv2
import numpy as np

_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)  # as perception/los.py
GRID = 33  # grid points across and down the image (borders included)
ROUND_TRIP_PX = 0.5  # largest pixel -> ray -> pixel error accepted
MAX_RAY_DEG = 89.0  # a pinhole-model ray must stay in front of the camera
# How far the lens may move a pixel from the centre relative to the pinhole position: a wide lens's barrel
# squeezes the edge to ~0.3 of it (a 150 deg diagonal); no real lens pushes pixels out to twice the distance.
RADIAL_RATIO = (0.2, 2.0)
MAX_TANGENTIAL = 0.1  # |p1|, |p2|: decentring of a real lens is ~1e-3; 0.1 is a broken or mis-entered model


def distortion_problem(K: np.ndarray, dist: np.ndarray, width: int, height: int) -> str | None:
    """Why the model is not one-to-one over the image (one line), or None if it is."""
    dist = np.asarray(dist, dtype=float).ravel()
    if dist.size == 0 or not np.any(dist):
        return None
    if dist.size >= 4 and max(abs(dist[2]), abs(dist[3])) > MAX_TANGENTIAL:
        return f"tangential coefficients p1 {dist[2]:g}, p2 {dist[3]:g} beyond +-{MAX_TANGENTIAL:g} (not a real lens)"
    u, v = np.meshgrid(np.linspace(0.0, width - 1.0, GRID), np.linspace(0.0, height - 1.0, GRID))
    pix = np.stack([u.ravel(), v.ravel()], axis=1)
    with np.errstate(all="ignore"):
        und = cv2.undistortPoints(pix.reshape(-1, 1, 2), K, dist, None, None, None, _CRITERIA).reshape(GRID, GRID, 2)
        if not np.isfinite(und).all():
            return "the undistortion gives no ray for part of the image"
        if np.degrees(np.arctan(np.hypot(und[..., 0], und[..., 1]))).max() > MAX_RAY_DEG:
            return f"the undistortion sends pixels to rays over {MAX_RAY_DEG:.0f} deg off the optical axis"
        back, _ = cv2.projectPoints(np.column_stack([und.reshape(-1, 2), np.ones(GRID * GRID)]).reshape(-1, 1, 3),
                                    np.zeros(3), np.zeros(3), K, dist)
        err = np.linalg.norm(back.reshape(-1, 2) - pix, axis=1)
    worst = int(np.nanargmax(np.where(np.isfinite(err), err, np.inf)))
    if not np.isfinite(err[worst]) or err[worst] > ROUND_TRIP_PX:
        return (f"not invertible: pixel ({pix[worst, 0]:.0f}, {pix[worst, 1]:.0f}) -> ray -> pixel is off by "
                f"{err[worst]:.3g} px (the polynomial folds the image)")
    # Pinhole radius of each pixel vs the ray's radius: the share of the lens's own doing.
    norm = (pix - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
    rd, ru = np.hypot(norm[:, 0], norm[:, 1]), np.hypot(*und.reshape(-1, 2).T)
    far = rd > 0.05 * rd.max()
    ratio = rd[far] / np.maximum(ru[far], 1e-12)
    if ratio.min() < RADIAL_RATIO[0] or ratio.max() > RADIAL_RATIO[1]:
        return (f"implausible: the distortion moves pixels to {ratio.min():.2g}-{ratio.max():.2g} times their "
                f"pinhole distance from the centre (a lens: {RADIAL_RATIO[0]:g}-{RADIAL_RATIO[1]:g})")
    # Order along rows (x) and columns (y): a fold that the iteration happens to invert still shows here.
    if (np.diff(und[..., 0], axis=1) <= 0).any() or (np.diff(und[..., 1], axis=0) <= 0).any():
        return "not monotonic: the undistorted rays change order across the image (the polynomial folds it)"
    return None
