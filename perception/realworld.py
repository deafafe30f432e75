"""Training frames for real cameras: photographic backgrounds, frame-like hard negatives, real gate kinds.

``real_scene(rng, backgrounds)`` draws one frame and its gate boxes (0-2 gates):

* background: a random crop of a licensed photograph (``photo_backgrounds``: scikit-image's CC0 /
  public-domain sample images and scikit-learn's two CC BY 2.0 sample photos; see docs/perception.md)
  or the procedural backgrounds of ``perception.render``, jittered in colour, scale and flip;
* hard negatives: windows, doors, glass cabinets, picture frames, screens, floor markers, QR codes /
  fiducials, signs with lettering, ceiling trusses (things the shipped detector boxed as gates);
* gates: ring and square tube gates (thin, optionally on a pole), printed panel gates (wide frame with
  a checker border and lettering), seen up to ~70 deg off-axis, cut by the border when close;
* camera: pinhole or wide-angle/fisheye barrel distortion, low resolution (small sensor frames scaled
  up), motion blur, noise, low light, JPEG.

The boxes are the boxes of the gate's pixels after every geometric step (clip, distortion).
"""

from __future__ import annotations

import math
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from perception.render import (
    TRAIN_STYLE,
    Gate,
    PinholeCamera,
    Style,
    _draw_gate,
    _fill,
    _motion_blur,
    look_at,
    make_background,
    project_gate_quads,
    random_gate_colour,
)

# scikit-image sample images with a CC0 / public-domain statement in skimage/data/_fetchers.py
SKIMAGE_PHOTOS = ("astronaut.png", "brick.png", "camera.png", "chelsea.png", "clock_motion.png", "coffee.png",
                  "coins.png", "grass.png", "gravel.png", "hubble_deep_field.jpg", "rocket.jpg", "text.png",
                  "horse.png")
SKLEARN_PHOTOS = ("china.jpg", "flower.jpg")  # CC BY 2.0 (attribution in sklearn/datasets/images/README.txt)

REAL_STYLE = Style("real", hue_ranges=((0.0, 360.0),), backgrounds=("noise", "gradient", "stripes", "sky_ground"),
                   clutter=(0, 6), blur_px=(0.0, 7.0), noise_sigma=(0.0, 7.0), gain=(0.3, 1.3), jpeg_prob=0.5)


@lru_cache(maxsize=1)
def photo_backgrounds() -> tuple[np.ndarray, ...]:
    """The licensed sample photographs that are installed (BGR uint8); empty if neither package is."""
    out = []
    dirs = []
    try:
        import skimage.data

        dirs.append((Path(skimage.data.__file__).parent, SKIMAGE_PHOTOS))
    except ImportError:
        pass
    try:
        import sklearn.datasets

        dirs.append((Path(sklearn.datasets.__file__).parent / "images", SKLEARN_PHOTOS))
    except ImportError:
        pass
    for d, names in dirs:
        for n in names:
            img = cv2.imread(str(d / n), cv2.IMREAD_COLOR)
            if img is not None and min(img.shape[:2]) >= 128:
                out.append(img)
    return tuple(out)


def _photo_crop(rng: np.random.Generator, photos: tuple[np.ndarray, ...], w: int, h: int) -> np.ndarray:
    src = photos[int(rng.integers(len(photos)))]
    sh, sw = src.shape[:2]
    scale = rng.uniform(0.35, 1.0)
    cw, ch = max(int(sw * scale), 32), max(int(sw * scale * h / w), 32)
    ch = min(ch, sh)
    cw = min(cw, sw)
    x0, y0 = int(rng.integers(0, sw - cw + 1)), int(rng.integers(0, sh - ch + 1))
    img = cv2.resize(src[y0:y0 + ch, x0:x0 + cw], (w, h), interpolation=cv2.INTER_LINEAR)
    if rng.random() < 0.5:
        img = img[:, ::-1]
    f = img.astype(np.float32)
    f = f * rng.uniform(0.6, 1.3, 3)[None, None, :].astype(np.float32) + rng.uniform(-30, 30)
    return np.clip(f, 0, 255).astype(np.uint8)


def _dull_colour(rng: np.random.Generator) -> tuple[float, float, float]:
    """Colours of furniture, walls, frames: grey, white, black, wood, blue, glass cyan (low-mid saturation)."""
    k = rng.integers(6)
    if k == 0:
        g = rng.uniform(0, 255)
        return (g, g, g)
    if k == 1:  # wood
        return tuple(float(x) for x in (rng.uniform(20, 90), rng.uniform(60, 140), rng.uniform(100, 190)))
    if k == 2:  # blue / glass cyan
        return tuple(float(x) for x in (rng.uniform(150, 255), rng.uniform(120, 240), rng.uniform(20, 140)))
    if k == 3:  # white-ish
        g = rng.uniform(180, 255)
        return (g, g * rng.uniform(0.9, 1.0), g * rng.uniform(0.85, 1.0))
    g = rng.uniform(0, 255)  # any hue, washed out: a saturated thin frame is what a gate looks like
    return tuple(float(0.35 * x + 0.65 * g) for x in rng.uniform(0, 255, 3))


def _rect_pts(rng: np.random.Generator, w: int, h: int, min_side: int = 12) -> np.ndarray:
    """A rectangle in perspective (a random homography of an axis-aligned one), (4, 2) float."""
    bw = rng.uniform(min_side, w * 0.7)
    bh = bw * math.exp(rng.uniform(-1.0, 1.2))
    cx, cy = rng.uniform(-0.1, 1.1) * w, rng.uniform(-0.1, 1.1) * h
    pts = np.array([[-bw / 2, -bh / 2], [bw / 2, -bh / 2], [bw / 2, bh / 2], [-bw / 2, bh / 2]])
    a = rng.normal(0, 0.15)
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    pts = pts @ R.T
    # perspective: shrink one side (a plane seen obliquely)
    side = rng.integers(4)
    k = rng.uniform(0.6, 1.0)
    if side == 0:
        pts[[0, 3], 1] *= k
    elif side == 1:
        pts[[1, 2], 1] *= k
    elif side == 2:
        pts[[0, 1], 0] *= k
    else:
        pts[[2, 3], 0] *= k
    return pts + np.array([cx, cy])


def _poly(img: np.ndarray, pts: np.ndarray, col, thick: int = -1) -> None:
    p = np.round(pts * 16).astype(np.int32).reshape(-1, 1, 2)
    if thick < 0:
        cv2.fillPoly(img, [p], col, cv2.LINE_AA, shift=4)
    else:
        cv2.polylines(img, [p], True, col, max(int(thick), 1), cv2.LINE_AA, shift=4)


def _inset(pts: np.ndarray, f: float) -> np.ndarray:
    c = pts.mean(0)
    return c + (pts - c) * f


def _qr(rng: np.random.Generator, n: int) -> np.ndarray:
    g = (rng.random((n, n)) < 0.5).astype(np.uint8) * 255
    for y, x in ((0, 0), (0, n - 7), (n - 7, 0)):  # finder patterns
        if n >= 14:
            g[y:y + 7, x:x + 7] = 0
            g[y + 1:y + 6, x + 1:x + 6] = 255
            g[y + 2:y + 5, x + 2:x + 5] = 0
    return np.pad(g, 2, constant_values=255)


def _warp_patch(img: np.ndarray, patch: np.ndarray, pts: np.ndarray) -> None:
    h, w = img.shape[:2]
    ph, pw = patch.shape[:2]
    src = np.array([[0, 0], [pw, 0], [pw, ph], [0, ph]], np.float32)
    M = cv2.getPerspectiveTransform(src, pts.astype(np.float32))
    if patch.ndim == 2:
        patch = cv2.cvtColor(patch, cv2.COLOR_GRAY2BGR)
    warped = cv2.warpPerspective(patch, M, (w, h), flags=cv2.INTER_NEAREST)
    mask = cv2.warpPerspective(np.full((ph, pw), 255, np.uint8), M, (w, h), flags=cv2.INTER_NEAREST)
    img[mask > 0] = warped[mask > 0]


def _text(img: np.ndarray, rng: np.random.Generator, x: float, y: float, size: float, col) -> None:
    letters = "ABCDEFGHIJKLMNOPRSTUVWXYZ0123456789"
    s = "".join(letters[int(i)] for i in rng.integers(len(letters), size=int(rng.integers(2, 9))))
    cv2.putText(img, s, (int(x), int(y)), int(rng.integers(0, 8)), max(size, 0.3), col,
                max(int(size * 2), 1), cv2.LINE_AA)


def draw_hard_negative(img: np.ndarray, rng: np.random.Generator) -> None:
    """One frame-like non-gate object drawn into img (in place)."""
    h, w = img.shape[:2]
    # windows / glass cabinets most often: the shipped detector's most confident false boxes on real frames
    kind = int(rng.choice(12, p=[0.17, 0.17, 0.09, 0.09, 0.06, 0.07, 0.07, 0.06, 0.05, 0.05, 0.06, 0.06]))
    pts = _rect_pts(rng, w, h)
    side = float(np.ptp(pts[:, 0]))
    if kind in (0, 1):  # window / glass cabinet: frame + tinted glass + mullions
        glass = _dull_colour(rng)
        over = img.copy()
        _poly(over, pts, glass)
        a = rng.uniform(0.25, 0.7)
        img[:] = cv2.addWeighted(over, a, img, 1 - a, 0)
        col = _dull_colour(rng)
        _poly(img, pts, col, int(max(2, side * rng.uniform(0.02, 0.08))))
        if kind == 1:  # shelves / mullions
            for t in np.linspace(0.25, 0.75, int(rng.integers(1, 4))):
                a0 = pts[0] + (pts[3] - pts[0]) * t
                a1 = pts[1] + (pts[2] - pts[1]) * t
                cv2.line(img, tuple(int(v) for v in a0), tuple(int(v) for v in a1), col, 2, cv2.LINE_AA)
            _shelf_content(img, rng, pts)
    elif kind == 2:  # door: tall frame reaching the floor
        pts = _rect_pts(rng, w, h, 30)
        pts[2:, 1] = np.maximum(pts[2:, 1], h * rng.uniform(0.8, 1.1))
        _poly(img, pts, _dull_colour(rng))
        _poly(img, pts, _dull_colour(rng), int(max(2, side * 0.06)))
        cv2.circle(img, (int(pts[1, 0] - side * 0.15), int(pts[:, 1].mean())), 3, _dull_colour(rng), -1)
    elif kind == 3:  # picture frame with content
        _poly(img, pts, tuple(float(x) for x in rng.uniform(0, 255, 3)))
        inner = _inset(pts, rng.uniform(0.6, 0.85))
        noise = (rng.random((8, 8, 3)) * 255).astype(np.uint8)
        _warp_patch(img, cv2.resize(noise, (64, 64)), inner)
    elif kind == 4:  # screen: dark/bright panel with a thin bezel
        _poly(img, pts, (20, 20, 20))
        _poly(img, _inset(pts, 0.92), tuple(float(x) for x in rng.uniform(0, 255, 3)))
    elif kind == 5:  # QR code / fiducial marker
        pts = _inset(pts, min(1.0, 120 / max(side, 1)))
        _warp_patch(img, _qr(rng, int(rng.choice([5, 7, 21, 25]))), pts)
    elif kind == 6:  # sign with lettering (often saturated: it must still not be a gate)
        col = tuple(float(x) for x in rng.uniform(0, 255, 3))
        _poly(img, pts, col)
        c = pts.mean(0)
        _text(img, rng, c[0] - side / 3, c[1], side / 80, tuple(255 - v for v in col))
    elif kind == 7:  # truss: two rails and a zigzag
        p0 = np.array([rng.uniform(-0.2, 1.2) * w, rng.uniform(0, 0.5) * h])
        d = np.array([math.cos(rng.uniform(0, math.pi)), math.sin(rng.uniform(-0.3, 0.3))])
        nrm = np.array([-d[1], d[0]]) * rng.uniform(8, 40)
        length = rng.uniform(0.5, 1.5) * w
        col = _dull_colour(rng)
        th = int(rng.integers(1, 5))
        for off in (0, 1):
            a, b = p0 + off * nrm, p0 + off * nrm + d * length
            cv2.line(img, tuple(int(v) for v in a), tuple(int(v) for v in b), col, th, cv2.LINE_AA)
        n = int(rng.integers(4, 14))
        for i in range(n):
            a = p0 + d * length * i / n + (i % 2) * nrm
            b = p0 + d * length * (i + 1) / n + ((i + 1) % 2) * nrm
            cv2.line(img, tuple(int(v) for v in a), tuple(int(v) for v in b), col, th, cv2.LINE_AA)
    elif kind == 8:  # floor marker / tape square (coloured, any hue)
        col = tuple(float(x) for x in rng.uniform(0, 255, 3))
        p = pts.copy()
        p[:, 1] = p[:, 1].mean() + (p[:, 1] - p[:, 1].mean()) * rng.uniform(0.15, 0.4)  # flat: lies on the floor
        _poly(img, p, col, int(rng.integers(2, 6)) if rng.random() < 0.5 else -1)
    elif kind == 10:  # a light board / wall panel on its own (it also stands behind gates: not a gate cue)
        _board_behind(img, rng, pts)
    elif kind == 11:  # over-exposed lamp, ceiling light streak or white object: a bright blob is not a gate
        glow = np.zeros_like(img)
        c = pts.mean(0)
        ax = (max(int(side * rng.uniform(0.1, 0.5)), 3), max(int(side * rng.uniform(0.04, 0.25)), 2))
        cv2.ellipse(glow, (int(c[0]), int(c[1])), ax, float(rng.uniform(0, 180)), 0.0,
                    360.0 if rng.random() < 0.6 else float(rng.uniform(60, 180)), (255, 255, 255),
                    -1 if rng.random() < 0.6 else max(ax[1] // 2, 2), cv2.LINE_AA)
        glow = cv2.GaussianBlur(glow, (0, 0), float(rng.uniform(0.5, 3.0)))
        img[:] = np.maximum(img, glow)
    else:  # lettering / printed text alone
        for _ in range(int(rng.integers(1, 4))):
            _text(img, rng, rng.uniform(0, w), rng.uniform(0, h), rng.uniform(0.4, 2.5),
                  tuple(float(x) for x in rng.uniform(0, 255, 3)))


def _shelf_content(img: np.ndarray, rng: np.random.Generator, pts: np.ndarray) -> None:
    """Objects behind the glass of a display cabinet: small blobs of any colour (bright, busy)."""
    lo, hi = pts.min(0), pts.max(0)
    size = max(float(min(hi - lo)), 4.0)
    for _ in range(int(rng.integers(2, 12))):
        c = lo + rng.random(2) * (hi - lo)
        r = rng.uniform(0.03, 0.15) * size
        col = tuple(float(x) for x in rng.uniform(0, 255, 3))
        if rng.random() < 0.5:
            cv2.rectangle(img, (int(c[0] - r), int(c[1] - r)), (int(c[0] + r), int(c[1] + r * rng.uniform(0.5, 2))),
                          col, -1)
        else:
            cv2.circle(img, (int(c[0]), int(c[1])), max(int(r), 1), col, -1, cv2.LINE_AA)


def _board_behind(img: np.ndarray, rng: np.random.Generator, outer: np.ndarray) -> None:
    """A light board or wall panel behind a thin gate: the gate, not the board, is the box."""
    if not np.isfinite(outer).all():
        return
    lo, hi = outer.min(0), outer.max(0)
    c, half = (lo + hi) / 2, (hi - lo) / 2
    if half.max() > 4 * max(img.shape[:2]):
        return
    half = half * rng.uniform(0.9, 1.7, 2)
    c = c + rng.normal(0, 0.3, 2) * half
    pts = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float) * half
    pts += rng.normal(0, 0.08, (4, 2)) * half  # a plane at another angle than the gate's
    g = rng.uniform(140, 240)
    col = (g * rng.uniform(0.85, 1.0), g * rng.uniform(0.9, 1.0), g * rng.uniform(0.85, 1.0))
    _poly(img, pts + c, col)


def _random_gate(rng: np.random.Generator, cam: PinholeCamera, colour_style: Style) -> tuple[Gate, np.ndarray, str]:
    """A gate of a real kind at a random pose in view (camera at the origin looking along +x)."""
    fx = float(cam.K[0, 0])
    kind = ("tube", "panel", "ring")[int(rng.choice(3, p=[0.5, 0.25, 0.25]))]
    r = float(rng.uniform(0.4, 1.5))
    size_px = math.exp(rng.uniform(math.log(7.0), math.log(1.6 * cam.height)))  # bigger than the frame: cut
    dist = float(np.clip(2 * r * fx / size_px, 0.4, 80.0))
    u, v = rng.uniform(-0.1, 1.1) * cam.width, rng.uniform(-0.1, 1.1) * cam.height
    ray = np.linalg.solve(np.asarray(cam.K, float), np.array([u, v, 1.0]))
    ray /= np.linalg.norm(ray)
    R_wc = look_at(np.zeros(3), np.array([1.0, 0.0, 0.0]))
    # the camera banks: real drone frames show the gate rolled by up to ~45 deg (a diamond)
    roll = rng.normal(0, math.radians(10)) if rng.random() < 0.5 else rng.uniform(-0.8, 0.8)
    cr, sr = math.cos(roll), math.sin(roll)
    R_wc = R_wc @ np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1.0]])
    centre = R_wc @ (ray * dist)
    to_cam = -centre / np.linalg.norm(centre)
    # off-axis angle up to ~70 deg, about the vertical mostly (a gate stands upright)
    yaw = rng.uniform(-1.2, 1.2) if rng.random() < 0.7 else rng.normal(0, 0.4)
    pitch = rng.normal(0, 0.2)
    cy, sy = math.cos(yaw), math.sin(yaw)
    n = np.array([cy * to_cam[0] - sy * to_cam[1], sy * to_cam[0] + cy * to_cam[1], to_cam[2] + pitch])
    n /= np.linalg.norm(n)
    if kind == "tube":
        colour = random_gate_colour(rng, colour_style) if rng.random() < 0.5 else (0, int(rng.integers(60, 160)), 255)
        thick = r * rng.uniform(0.04, 0.12)
        shape = "square" if rng.random() < 0.7 else "ring"
    elif kind == "panel":
        colour = random_gate_colour(rng, colour_style)
        thick = r * rng.uniform(0.2, 0.4)
        shape = "square"
    else:
        colour = random_gate_colour(rng, colour_style)
        thick = r * rng.uniform(0.08, 0.3)
        shape = "ring"
    gate = Gate(centre=centre, normal=n, radius=r, shape=shape, colour=colour, thickness=float(thick))
    return gate, R_wc, kind


def _draw_real_gate(img: np.ndarray, mask: np.ndarray, rng: np.random.Generator, cam: PinholeCamera,
                    gate: Gate, R_wc: np.ndarray, kind: str) -> bool:
    polys, idx = project_gate_quads(cam, R_wc, np.zeros(3), gate)
    if not polys:
        return False
    if kind == "panel":  # checker border: alternate segments dark / gate colour, sometimes white
        base = np.asarray(gate.colour, float)
        light = (255.0, 255.0, 255.0) if rng.random() < 0.4 else tuple(base)
        dark = tuple(float(x) for x in rng.uniform(0, 60, 3))
        cols = [dark if k % 2 else light for k in idx]
        _fill(img, polys, cols)
        # lettering printed on the panel (the shipped detector boxed it)
        top = np.concatenate(polys[: max(len(polys) // 8, 1)])
        c = top.mean(0)
        if rng.random() < 0.5 and np.isfinite(c).all() and abs(c[0]) < 4 * cam.width:
            _text(img, rng, c[0], c[1], float(rng.uniform(0.3, 1.2)), dark)
    else:
        if kind == "tube" and rng.random() < 0.3:
            _board_behind(img, rng, np.concatenate(polys))
        _draw_gate(img, polys, idx, gate, rng, shaded=True)
    _fill(mask, polys, [255] * len(polys), aa=False)
    if kind == "tube" and rng.random() < 0.7:  # a pole (or two feet) from the bottom edge to the floor
        outer = np.concatenate(polys)
        x = float(np.median(outer[:, 0]))
        y0 = float(outer[:, 1].max())
        if np.isfinite([x, y0]).all() and abs(x) < 4 * cam.width and y0 < cam.height:
            width = max(1, int(np.ptp(outer[:, 0]) * rng.uniform(0.02, 0.06)))
            cv2.line(img, (int(x), int(y0)), (int(x), int(cam.height + 5)), gate.colour, width, cv2.LINE_AA)
    return True


def _fisheye_maps(w: int, h: int, k1: float) -> tuple[np.ndarray, np.ndarray]:
    """remap() maps for barrel distortion: destination pixel -> source pixel (k1 < 0 is barrel)."""
    f = 0.5 * w
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    x, y = (xx - w / 2) / f, (yy - h / 2) / f
    r2 = x * x + y * y
    s = 1.0 / (1.0 + k1 * r2)  # inverse of r_d = r_u (1 + k1 r_u^2), to first order: enough for augmentation
    # normalise so the corners still sample inside the source (zoom in a little)
    return (x * s * f + w / 2).astype(np.float32), (y * s * f + h / 2).astype(np.float32)


def _box_of_mask(mask: np.ndarray, min_px: int = 3) -> tuple[float, float, float, float] | None:
    if not mask.any():
        return None
    x, y, bw, bh = cv2.boundingRect((mask > 127).astype(np.uint8))
    if bw < min_px or bh < min_px:
        return None
    return float(x), float(y), float(x + bw), float(y + bh)


def real_scene(rng: np.random.Generator, photos: tuple[np.ndarray, ...] | None = None,
               p_empty: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """One BGR frame and its gate boxes (K, 4) xyxy in pixels, with the variety described above."""
    photos = photo_backgrounds() if photos is None else photos
    w = 640
    h = int(rng.choice([480, 360, 330]))  # 4:3, 16:9 and the ~2:1 of small drone cameras
    cam = PinholeCamera.default(w, h, half_fov_deg=float(rng.uniform(30, 60)))
    photo = bool(photos) and rng.random() < 0.7
    img = _photo_crop(rng, photos, w, h) if photo else make_background(w, h, rng, TRAIN_STYLE)
    for _ in range(int(rng.integers(1, 9))):
        draw_hard_negative(img, rng)
    masks = []
    n_gates = 0 if rng.random() < p_empty else (1 if rng.random() < 0.85 else 2)
    colour_style = TRAIN_STYLE if rng.random() < 0.7 else REAL_STYLE
    for _ in range(n_gates):
        gate, R_wc, kind = _random_gate(rng, cam, colour_style)
        m = np.zeros((h, w), np.uint8)
        if _draw_real_gate(img, m, rng, cam, gate, R_wc, kind):
            for prev in masks:  # a later gate hides what it covers of an earlier one
                prev[m > 0] = 0
            masks.append(m)
    if rng.random() < 0.3:  # a few hard negatives in front of the gate too
        draw_hard_negative(img, rng)
    if rng.random() < 0.4:  # wide-angle / fisheye lens
        mx, my = _fisheye_maps(w, h, float(rng.uniform(-0.45, -0.05)))
        img = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        masks = [cv2.remap(m, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT) for m in masks]
    img = _camera_effects(img, rng)
    boxes = [b for b in (_box_of_mask(m) for m in masks) if b is not None]
    return img, np.array(boxes, np.float32).reshape(-1, 4)


def _camera_effects(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    h, w = img.shape[:2]
    f = img.astype(np.float32)
    # low light / colour cast / vignetting
    gain = rng.uniform(*REAL_STYLE.gain)
    cast = rng.uniform(0.8, 1.2, 3).astype(np.float32)
    if rng.random() < 0.25:  # fluorescent / cheap-sensor cyan-green cast (the basement frames): red suppressed
        cast = np.array([rng.uniform(1.0, 1.4), rng.uniform(1.0, 1.35), rng.uniform(0.55, 0.85)], np.float32)
    f *= gain * cast[None, None, :]
    if rng.random() < 0.4:
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        r2 = ((xx - w / 2) / (w / 2)) ** 2 + ((yy - h / 2) / (h / 2)) ** 2
        f *= (1.0 - rng.uniform(0.1, 0.5) * r2 / 2)[..., None]
    blur = rng.uniform(*REAL_STYLE.blur_px)
    if blur >= 2.0:
        f = _motion_blur(f, blur, rng.uniform(0, math.pi))
    if rng.random() < 0.4:  # a small sensor scaled up (e.g. 312x160 drone frames)
        s = rng.uniform(0.25, 0.6)
        small = cv2.resize(f, (max(int(w * s), 16), max(int(h * s), 16)), interpolation=cv2.INTER_AREA)
        f = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
    sigma = rng.uniform(*REAL_STYLE.noise_sigma)
    if sigma > 0.5:
        cv2.setRNGSeed(int(rng.integers(2**31 - 1)))
        noise = np.empty_like(f)
        cv2.randn(noise, 0.0, float(sigma))
        f += noise
    if rng.random() < 0.3:  # washed-out, low-saturation frames (cheap cameras, glare)
        grey = cv2.cvtColor(np.clip(f, 0, 255).astype(np.uint8), cv2.COLOR_BGR2GRAY).astype(np.float32)
        a = rng.uniform(0.3, 0.8)
        f = f * a + grey[..., None] * (1 - a)
    out = np.clip(f, 0, 255).astype(np.uint8)
    if rng.random() < REAL_STYLE.jpeg_prob:
        ok, enc = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(30, 90))])
        if ok:
            out = cv2.imdecode(enc, cv2.IMREAD_COLOR)
    return out
