"""Synthetic camera frames of a gate: for detector training, tests, replay videos and the closed loop.

Geometry: the gate is a flat annulus (ring) or square frame in a plane, in any right-handed world
frame (ENU in this code base). ``radius`` is the OUTER edge of the frame (for a square: half the
outer side); the opening is ``radius - thickness``. The camera pose is ``R_world_cam`` (camera
OpenCV frame x right, y down, z forward -> world) and the camera position in the world. Points are
projected with ``cv2.projectPoints`` through the configured K (and distortion), i.e. the same
pinhole model as the geometric camera, and the ground-truth box is the box of the projected outer
rim, clipped to the image.

Appearance (background texture, clutter, lighting, blur, noise, JPEG) is drawn from a ``Style``
with an ``np.random.Generator``: ``TRAIN_STYLE`` for training, ``HELDOUT_STYLE`` uses gate colours
and background kinds that the training style never produces.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass, field
from typing import Literal, Protocol

import cv2
import numpy as np

from perception.types import BoundingBox

NEAR = 0.05  # m: geometry closer than this to the camera plane is clipped away
_RIM_SEGMENTS = 72  # ring tessellation: < 0.1 % radius error in the box


class CameraLike(Protocol):
    """Anything with intrinsics and an image size (perception.los.CameraModel, CameraConfig, PinholeCamera)."""

    K: np.ndarray
    width: int
    height: int


@dataclass(frozen=True)
class PinholeCamera:
    K: np.ndarray
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @classmethod
    def from_config(cls, cam) -> PinholeCamera:  # cam: companion.config.CameraConfig
        return cls(np.asarray(cam.K, float), int(cam.width), int(cam.height), np.asarray(cam.dist, float))

    @classmethod
    def default(cls, width: int = 640, height: int = 480, half_fov_deg: float = 33.5) -> PinholeCamera:
        f = (width / 2.0) / math.tan(math.radians(half_fov_deg))
        return cls(np.array([[f, 0, width / 2.0], [0, f, height / 2.0], [0, 0, 1.0]]), width, height)


@dataclass(frozen=True)
class Gate:
    centre: np.ndarray  # world, m
    normal: np.ndarray  # world, unit (sign does not matter for drawing)
    radius: float  # m, outer edge (half outer side for a square)
    shape: Literal["ring", "square"] = "ring"
    colour: tuple[int, int, int] = (0, 90, 255)  # BGR
    thickness: float = 0.15  # m, radial width of the frame
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)  # world "up" that orients a square gate in its plane


@dataclass(frozen=True)
class Style:
    """Ranges that appearance parameters are drawn from."""

    name: str
    hue_ranges: tuple[tuple[float, float], ...]  # gate hue ranges, degrees [0, 360)
    backgrounds: tuple[str, ...]  # kinds understood by make_background
    clutter: tuple[int, int] = (3, 14)  # number of distractor shapes
    blur_px: tuple[float, float] = (0.0, 9.0)  # motion blur length
    noise_sigma: tuple[float, float] = (0.0, 8.0)  # sensor noise, grey levels
    gain: tuple[float, float] = (0.55, 1.35)  # global brightness
    jpeg_prob: float = 0.4


# Held-out style: green/cyan gates and tile/blob backgrounds never appear in training.
TRAIN_STYLE = Style(
    "train", hue_ranges=((0.0, 70.0), (200.0, 360.0)), backgrounds=("noise", "gradient", "stripes", "sky_ground")
)
HELDOUT_STYLE = Style("heldout", hue_ranges=((90.0, 180.0),), backgrounds=("tiles", "blobs"))


def random_gate_colour(rng: np.random.Generator, style: Style = TRAIN_STYLE) -> tuple[int, int, int]:
    lo, hi = style.hue_ranges[rng.integers(len(style.hue_ranges))]
    h = rng.uniform(lo, hi) / 360.0
    s = rng.uniform(0.45, 1.0)
    v = rng.uniform(0.45, 1.0)
    r, g, b = colorsys.hsv_to_rgb(h, s, v)
    return int(b * 255), int(g * 255), int(r * 255)


# --------------------------------------------------------------------------- backgrounds


def _smooth_noise(h: int, w: int, rng: np.random.Generator, cells: int) -> np.ndarray:
    small = rng.random((max(2, h // cells), max(2, w // cells), 3)).astype(np.float32)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)


def make_background(width: int, height: int, rng: np.random.Generator, style: Style = TRAIN_STYLE) -> np.ndarray:
    """A textured, cluttered BGR background of one of the style's kinds."""
    kind = style.backgrounds[rng.integers(len(style.backgrounds))]
    h, w = height, width
    base = rng.uniform(30, 220, 3).astype(np.float32)
    if kind == "noise":
        img = base * 0.5 + 255 * 0.5 * _smooth_noise(h, w, rng, int(rng.integers(8, 80)))
        img += 40 * (_smooth_noise(h, w, rng, 4) - 0.5)
    elif kind == "gradient":
        ys = np.linspace(0, 1, h, dtype=np.float32)[:, None, None]
        other = rng.uniform(30, 220, 3).astype(np.float32)
        img = np.broadcast_to(base * (1 - ys) + other * ys, (h, w, 3)).copy()
        img += 50 * (_smooth_noise(h, w, rng, int(rng.integers(4, 30))) - 0.5)
    elif kind == "stripes":
        period = rng.uniform(10, 80)
        ang = rng.uniform(0, math.pi)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        s = 0.5 + 0.5 * np.sin((xx * math.cos(ang) + yy * math.sin(ang)) * 2 * math.pi / period)
        other = rng.uniform(30, 220, 3).astype(np.float32)
        img = base * s[..., None] + other * (1 - s[..., None])
        img += 30 * (_smooth_noise(h, w, rng, 6) - 0.5)
    elif kind == "sky_ground":
        horizon = int(rng.uniform(0.2, 0.8) * h)
        sky = np.array([rng.uniform(150, 250), rng.uniform(110, 210), rng.uniform(60, 170)], np.float32)
        ground = rng.uniform(20, 140, 3).astype(np.float32)
        img = np.empty((h, w, 3), np.float32)
        img[:horizon] = sky
        img[horizon:] = ground
        img += 60 * (_smooth_noise(h, w, rng, int(rng.integers(3, 20))) - 0.5)
    elif kind == "tiles":
        size = int(rng.integers(16, 90))
        yy, xx = np.mgrid[0:h, 0:w]
        checker = ((yy // size + xx // size) % 2).astype(np.float32)[..., None]
        other = rng.uniform(30, 220, 3).astype(np.float32)
        img = base * checker + other * (1 - checker)
        img += 20 * (_smooth_noise(h, w, rng, 5) - 0.5)
    elif kind == "blobs":
        img = np.broadcast_to(base, (h, w, 3)).copy()
        for _ in range(int(rng.integers(10, 40))):
            c = tuple(float(x) for x in rng.uniform(0, 255, 3))
            cv2.ellipse(
                img, (int(rng.integers(0, w)), int(rng.integers(0, h))),
                (int(rng.integers(5, w // 4)), int(rng.integers(5, h // 4))), float(rng.uniform(0, 180)),
                0, 360, c, -1,
            )
        img = cv2.GaussianBlur(img, (0, 0), float(rng.uniform(0.5, 4.0)))
    else:
        raise ValueError(f"render: unknown background kind {kind!r}")
    _clutter(img, rng, style)
    return np.clip(img, 0, 255).astype(np.uint8)


def _clutter(img: np.ndarray, rng: np.random.Generator, style: Style) -> None:
    """Distractors: bars, boxes, discs, arcs (hard negatives for a ring detector)."""
    h, w = img.shape[:2]
    for _ in range(int(rng.integers(style.clutter[0], style.clutter[1] + 1))):
        c = tuple(float(x) for x in rng.uniform(0, 255, 3))
        p = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        k = rng.integers(5)
        if k == 0:
            q = (p[0] + int(rng.integers(-200, 200)), p[1] + int(rng.integers(-200, 200)))
            cv2.line(img, p, q, c, int(rng.integers(1, 12)), cv2.LINE_AA)
        elif k == 1:
            q = (p[0] + int(rng.integers(-120, 120)), p[1] + int(rng.integers(-120, 120)))
            cv2.rectangle(img, p, q, c, -1)
        elif k == 2:
            cv2.circle(img, p, int(rng.integers(3, 60)), c, -1, cv2.LINE_AA)
        elif k == 3:  # open arc: looks like part of a ring, is not a gate
            a0 = float(rng.uniform(0, 360))
            cv2.ellipse(img, p, (int(rng.integers(8, 90)),) * 2, 0, a0, a0 + float(rng.uniform(40, 160)), c,
                        int(rng.integers(2, 10)), cv2.LINE_AA)
        else:  # a tree/pole-like vertical bar
            cv2.rectangle(img, p, (p[0] + int(rng.integers(4, 25)), h), c, -1)


# --------------------------------------------------------------------------- gate geometry


def _gate_axes(gate: Gate) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = np.asarray(gate.normal, float)
    n = n / np.linalg.norm(n)
    up = np.asarray(gate.up, float)
    u = up - (up @ n) * n
    if np.linalg.norm(u) < 1e-6:  # normal along "up": any in-plane axis will do
        u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    return n, u, np.cross(n, u)


def gate_outlines(gate: Gate) -> tuple[np.ndarray, np.ndarray]:
    """Outer and inner rim points in the world, (M, 3) each, same parametrisation (index i matches i)."""
    _, u, v = _gate_axes(gate)
    c = np.asarray(gate.centre, float)
    r_out = float(gate.radius)
    r_in = max(r_out - float(gate.thickness), 0.05 * r_out)
    if gate.shape == "ring":
        a = np.linspace(0.0, 2 * math.pi, _RIM_SEGMENTS, endpoint=False)
        unit = np.stack([np.cos(a), np.sin(a)], axis=1)
    elif gate.shape == "square":
        # 8 points per side so near-plane clipping and shading work per segment.
        t = np.linspace(-1.0, 1.0, 9)[:-1]
        one = np.ones_like(t)
        unit = np.concatenate(
            [np.stack([t, -one], 1), np.stack([one, t], 1), np.stack([-t, one], 1), np.stack([-one, -t], 1)]
        )
    else:
        raise ValueError(f"render: gate shape must be 'ring' or 'square', got {gate.shape!r}")
    outer = c + r_out * (unit[:, :1] * u + unit[:, 1:] * v)
    inner = c + r_in * (unit[:, :1] * u + unit[:, 1:] * v)
    return outer, inner


def _clip_near(poly_cam: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman clip of a polygon (camera frame) to z >= NEAR."""
    out = []
    n = len(poly_cam)
    for i in range(n):
        a, b = poly_cam[i], poly_cam[(i + 1) % n]
        ina, inb = a[2] >= NEAR, b[2] >= NEAR
        if ina:
            out.append(a)
        if ina != inb:
            s = (NEAR - a[2]) / (b[2] - a[2])
            out.append(a + s * (b - a))
    return np.array(out).reshape(-1, 3)


def _project(cam: CameraLike, pts_cam: np.ndarray) -> np.ndarray:
    dist = np.asarray(getattr(cam, "dist", np.zeros(0)), float)
    if dist.size == 0:  # plain pinhole: avoid cv2's per-call overhead
        p = pts_cam @ np.asarray(cam.K, float).T
        return p[:, :2] / p[:, 2:3]
    img, _ = cv2.projectPoints(pts_cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), np.asarray(cam.K, float), dist)
    return img.reshape(-1, 2)


def project_gate_quads(
    cam: CameraLike, R_world_cam: np.ndarray, cam_pos: np.ndarray, gate: Gate
) -> tuple[list[np.ndarray], list[int]]:
    """Image polygons of the gate's frame segments (near-clipped), and each one's segment index."""
    outer, inner = gate_outlines(gate)
    R_cam_world = np.asarray(R_world_cam, float).T
    o_c = (outer - cam_pos) @ R_cam_world.T
    i_c = (inner - cam_pos) @ R_cam_world.T
    m = len(o_c)
    polys: list[np.ndarray] = []
    idx: list[int] = []
    if (o_c[:, 2] >= NEAR).all() and (i_c[:, 2] >= NEAR).all():
        po, pi = _project(cam, o_c), _project(cam, i_c)
        for k in range(m):
            j = (k + 1) % m
            polys.append(np.array([po[k], po[j], pi[j], pi[k]]))
            idx.append(k)
        return polys, idx
    for k in range(m):
        j = (k + 1) % m
        quad = _clip_near(np.array([o_c[k], o_c[j], i_c[j], i_c[k]]))
        if len(quad) >= 3:
            polys.append(_project(cam, quad))
            idx.append(k)
    return polys, idx


def gate_box(
    cam: CameraLike, R_world_cam: np.ndarray, cam_pos: np.ndarray, gate: Gate, t: float = 0.0,
    min_size: float = 2.0,
) -> BoundingBox | None:
    """Ground-truth box: the projected outer rim (near-clipped), clipped to the image; None if not visible."""
    polys, _ = project_gate_quads(cam, R_world_cam, cam_pos, gate)
    if not polys:
        return None
    w, h = int(cam.width), int(cam.height)
    pts = np.clip(np.concatenate(polys), -1e6, 1e6)  # points just past the near plane project very far out
    lo, hi = pts.min(0), pts.max(0)
    x0, y0 = float(max(lo[0], 0.0)), float(max(lo[1], 0.0))
    x1, y1 = float(min(hi[0], w)), float(min(hi[1], h))
    if lo[0] < 0 or lo[1] < 0 or hi[0] > w or hi[1] > h:
        # Partly out of view: the vertex extent can span the image while the band itself misses
        # parts of it, so tighten to the pixels actually covered.
        mask = np.zeros((h, w), np.uint8)
        _fill(mask, polys, [255] * len(polys), aa=False)
        if not mask.any():
            return None
        mx, my, mw, mh = cv2.boundingRect(mask)
        x0, y0, x1, y1 = max(x0, mx), max(y0, my), min(x1, mx + mw), min(y1, my + mh)
    if x1 - x0 < min_size or y1 - y0 < min_size:
        return None
    return BoundingBox.from_xyxy(x0, y0, x1, y1, 1.0, t)


def _fill(img: np.ndarray, polys: list[np.ndarray], colours: list, aa: bool = True) -> None:
    h, w = img.shape[:2]
    lim = 4 * max(w, h)
    for poly, col in zip(polys, colours, strict=True):
        p = np.clip(poly, -lim, lim + max(w, h))  # keep fillConvexPoly's fixed-point maths in range
        cv2.fillConvexPoly(img, np.round(p * 16).astype(np.int32), col, cv2.LINE_AA if aa else cv2.LINE_8, shift=4)


# --------------------------------------------------------------------------- frames


def _motion_blur(img: np.ndarray, length: float, angle: float) -> np.ndarray:
    k = max(3, round(length) | 1)
    kern = np.zeros((k, k), np.float32)
    c = k // 2
    dx, dy = math.cos(angle) * c, math.sin(angle) * c
    cv2.line(kern, (round(c - dx), round(c - dy)), (round(c + dx), round(c + dy)), 1.0, 1, cv2.LINE_AA)
    kern /= kern.sum()
    return cv2.filter2D(img, -1, kern)


def render_gate_frame(
    camera: CameraLike,
    R_world_cam: np.ndarray,
    cam_pos: np.ndarray,
    gate: Gate | None,
    style: Style | None = TRAIN_STYLE,
    rng: np.random.Generator | None = None,
    background: np.ndarray | None = None,
    t: float = 0.0,
) -> tuple[np.ndarray, BoundingBox | None]:
    """Render one BGR frame (camera.height x camera.width) of ``gate`` seen from the camera pose.

    ``R_world_cam``: camera (OpenCV x right, y down, z forward) -> world; ``cam_pos``: camera position
    in the world. ``style=None`` gives a clean frame (no lighting change, blur, noise or JPEG);
    ``background`` (BGR, camera size) replaces the random background. Returns the image and the
    ground-truth box of the gate's outer rim (None when the gate is not in view).
    """
    rng = rng if rng is not None else np.random.default_rng(0)
    w, h = int(camera.width), int(camera.height)
    if background is not None:
        if background.shape[:2] != (h, w):
            raise ValueError(f"render: background is {background.shape[1]}x{background.shape[0]}, camera {w}x{h}")
        img = background.copy()
    elif style is not None:
        img = make_background(w, h, rng, style)
    else:
        img = np.full((h, w, 3), 128, np.uint8)
    box = None
    if gate is not None:
        polys, idx = project_gate_quads(camera, R_world_cam, cam_pos, gate)
        if polys:
            _draw_gate(img, polys, idx, gate, rng, shaded=style is not None)
            box = gate_box(camera, R_world_cam, cam_pos, gate, t)
    if style is not None:
        img = _photometric(img, rng, style)
    return img, box


def _draw_gate(img: np.ndarray, polys: list[np.ndarray], idx: list[int], gate: Gate,
               rng: np.random.Generator, shaded: bool) -> None:
    base = np.asarray(gate.colour, np.float32)
    m = max(idx) + 1 if idx else 1
    # Directional light across the rim + a little per-gate variation: real gates are not flat-coloured.
    phase = float(rng.uniform(0, 2 * math.pi)) if shaded else 0.0
    amp = float(rng.uniform(0.0, 0.35)) if shaded else 0.0
    cols = []
    for k in idx:
        shade = 1.0 + amp * math.cos(2 * math.pi * k / max(m, 1) + phase)
        cols.append(tuple(float(x) for x in np.clip(base * shade, 0, 255)))
    _fill(img, polys, cols)


def _photometric(img: np.ndarray, rng: np.random.Generator, style: Style) -> np.ndarray:
    h, w = img.shape[:2]
    f = img.astype(np.float32)
    # Lighting: global gain + a smooth illumination gradient.
    gain = rng.uniform(*style.gain)
    ang = rng.uniform(0, 2 * math.pi)
    amp = rng.uniform(0, 0.35)
    gx = (np.arange(w, dtype=np.float32) / w - 0.5) * math.cos(ang)
    gy = (np.arange(h, dtype=np.float32) / h - 0.5) * math.sin(ang)
    f *= (gain * (1.0 + amp * (gy[:, None] + gx[None, :])))[..., None]
    blur = rng.uniform(*style.blur_px)
    if blur >= 2.0:
        f = _motion_blur(f, blur, rng.uniform(0, math.pi))
    sigma = rng.uniform(*style.noise_sigma)
    if sigma > 0.5:
        # cv2.randn is ~10x faster than numpy's normal; seeded from rng so frames stay reproducible.
        cv2.setRNGSeed(int(rng.integers(2**31 - 1)))
        noise = np.empty_like(f)
        cv2.randn(noise, 0.0, float(sigma))
        f += noise
    out = np.clip(f, 0, 255).astype(np.uint8)
    if rng.random() < style.jpeg_prob:
        ok, enc = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(30, 90))])
        if ok:
            out = cv2.imdecode(enc, cv2.IMREAD_COLOR)
    return out


# --------------------------------------------------------------------------- random scenes (training / eval)


def look_at(cam_pos: np.ndarray, target: np.ndarray, up: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """R_world_cam of a camera at cam_pos looking at target, image y pointing away from ``up``."""
    z = np.asarray(target, float) - np.asarray(cam_pos, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def random_scene(
    rng: np.random.Generator, camera: CameraLike, style: Style = TRAIN_STYLE, p_empty: float = 0.08
) -> tuple[np.ndarray, BoundingBox | None]:
    """A random training/eval frame: gate at 1.5-40 m, anywhere in (or partly out of) view, tilted."""
    fx = float(camera.K[0, 0])
    r = float(rng.uniform(0.4, 2.0))
    # Distance drawn so the gate spans ~8 px to ~full frame, log-uniform in apparent size.
    size_px = math.exp(rng.uniform(math.log(9.0), math.log(0.9 * camera.height)))
    dist = float(np.clip(2 * r * fx / size_px, 1.0, 80.0))
    # Direction: anywhere in the frame, sometimes beyond the border (partial gates).
    u = rng.uniform(-0.1, 1.1) * camera.width
    v = rng.uniform(-0.1, 1.1) * camera.height
    ray = np.linalg.solve(np.asarray(camera.K, float), np.array([u, v, 1.0]))
    ray /= np.linalg.norm(ray)
    R_wc = look_at(np.zeros(3), np.array([1.0, 0.0, 0.0]))
    roll = rng.normal(0, math.radians(12))
    cr, sr = math.cos(roll), math.sin(roll)
    R_wc = R_wc @ np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1.0]])
    centre = R_wc @ (ray * dist)
    # Normal: towards the camera, tilted up to ~60 deg.
    to_cam = -centre / np.linalg.norm(centre)
    tilt = rng.normal(0, 0.5, 3)
    normal = to_cam + np.clip(tilt - (tilt @ to_cam) * to_cam, -1.7, 1.7)
    gate = Gate(
        centre=centre,
        normal=normal / np.linalg.norm(normal),
        radius=r,
        shape="ring" if rng.random() < 0.6 else "square",
        colour=random_gate_colour(rng, style),
        thickness=float(r * rng.uniform(0.08, 0.3)),
        up=(0.0, 0.0, 1.0),
    )
    if rng.random() < p_empty:
        gate = None
    return render_gate_frame(camera, R_wc, np.zeros(3), gate, style, rng)
