"""Zoomed detection (perception/zoom.py): the crop, the merge, and a far gate kept in the real pipeline."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from companion.config import load_config
from perception.simcamera import RenderedCamera
from perception.types import BoundingBox
from perception.zoom import Crop, merge, scan_crop, zoom_crop

W, H, IN = 640, 480, (320, 320)


def box(cx: float, cy: float, w: float, h: float | None = None, conf: float = 0.5) -> BoundingBox:
    return BoundingBox(cx, cy, w, w if h is None else h, conf)


def test_the_crop_is_the_models_input_centred_on_a_small_target_and_kept_in_the_frame() -> None:
    c = zoom_crop(box(300, 200, 40), W, H, IN, 80.0)
    assert c == Crop(140, 40, 320, 320, W, H)
    # near a corner the window slides to stay in the frame (same size, no padding)
    c = zoom_crop(box(620, 470, 30), W, H, IN, 80.0)
    assert (c.x0, c.y0, c.w, c.h) == (W - 320, H - 320, 320, 320)
    c = zoom_crop(box(5, 3, 30), W, H, IN, 80.0)
    assert (c.x0, c.y0) == (0, 0)


def test_no_zoom_for_a_large_target_when_off_or_when_the_detector_already_sees_full_resolution() -> None:
    assert zoom_crop(box(300, 200, 80), W, H, IN, 80.0) is None  # the larger side decides
    assert zoom_crop(box(300, 200, 20, 90), W, H, IN, 80.0) is None
    assert zoom_crop(box(300, 200, 20), W, H, IN, 0.0) is None
    assert zoom_crop(box(150, 80, 20), 312, 160, IN, 80.0) is None  # 312x160 fits 320x320 unshrunk


@pytest.mark.parametrize("frame", [(640, 480), (1280, 720), (400, 300), (330, 900)])
def test_the_scan_tiles_cover_the_frame_with_half_a_tile_of_overlap(frame: tuple[int, int]) -> None:
    fw, fh = frame
    tiles = []
    k = 0
    while (c := scan_crop(k, fw, fh, IN)) not in tiles:
        tiles.append(c)
        k += 1
    covered = np.zeros((fh, fw), int)
    for c in tiles:
        assert c.x0 >= 0 and c.x0 + c.w <= fw and c.y0 >= 0 and c.y0 + c.h <= fh
        assert (c.w, c.h) == (min(320, fw), min(320, fh))
        covered[c.y0:c.y0 + c.h, c.x0:c.x0 + c.w] += 1
    assert covered.min() >= 1
    # any object up to half a tile across lies wholly inside some tile (neighbours overlap by >= half a tile)
    xs = sorted({c.x0 for c in tiles})
    ys = sorted({c.y0 for c in tiles})
    assert all(b - a <= 160 for a, b in itertools.pairwise(xs))
    assert all(b - a <= 160 for a, b in itertools.pairwise(ys))
    if frame == (640, 480):
        assert len(tiles) == 6


def test_no_scan_for_a_frame_the_detector_sees_whole() -> None:
    assert scan_crop(0, 312, 160, IN) is None


def test_holds_judges_only_the_crop_edges_inside_the_frame() -> None:
    c = Crop(140, 40, 320, 320, W, H)
    assert c.holds(box(300, 200, 40))
    assert not c.holds(box(145, 200, 20))  # touches the crop's left edge (x = 140, inside the frame)
    assert not c.holds(box(500, 200, 40))  # outside
    corner = Crop(0, 0, 320, 320, W, H)
    assert corner.holds(box(10, 10, 20))  # touching the frame's own corner is no cut by the crop
    assert not corner.holds(box(310, 10, 20))  # the crop's right edge is inside the frame


def test_merge_takes_the_crops_boxes_inside_it_and_the_frames_elsewhere() -> None:
    c = Crop(140, 40, 320, 320, W, H)
    gate_full = box(300, 200, 38, conf=0.36)  # the gate as the half-size frame saw it
    clutter_far = box(600, 400, 50, conf=0.4)  # outside the crop: only the frame saw it
    cut = box(150, 100, 60, conf=0.45)  # straddles the crop's left edge: the frame's box stands
    zoomed = [box(300 - 140, 200 - 40, 40, conf=0.9),  # the gate at full resolution, crop pixels
              box(15, 100 - 40, 30, conf=0.6)]  # the straddler's part the crop saw: cut, dropped
    out = merge([gate_full, clutter_far, cut], zoomed, c, 0.5)
    assert [(b.cx, b.cy, b.w, b.confidence) for b in out] == [
        (300, 200, 40, 0.9), (150, 100, 60, 0.45), (600, 400, 50, 0.4)]


def test_a_frame_box_the_crop_missed_stays() -> None:
    c = Crop(140, 40, 320, 320, W, H)
    gate_full = box(300, 200, 60, conf=0.45)
    assert merge([gate_full], [], c, 0.5) == [gate_full]
    other = box(200, 100, 30, conf=0.6)  # the crop saw something else: the gate's frame box still stands
    assert merge([gate_full], [box(60, 60, 30, conf=0.6)], c, 0.5) == [other, gate_full]


def test_merge_drops_a_frame_box_a_crop_box_duplicates() -> None:
    c = Crop(0, 0, 320, 320, W, H)
    big = box(300, 150, 60, conf=0.5)  # right side past the crop: not held, but the crop box is the same object
    out = merge([big], [box(300, 150, 36, conf=0.8)], c, 0.3)
    assert [b.confidence for b in out] == [0.8]
    out = merge([big], [box(100, 150, 36, conf=0.8)], c, 0.3)  # a different object: both stay
    assert sorted(b.confidence for b in out) == [0.5, 0.8]
    # the half-size frame's box of a small gate, ~1.45x the full-resolution one (IoU 0.47 < 0.5): one object
    out = merge([box(320, 188, 61, 63, conf=0.46)], [box(315 - 140, 189 - 40, 42, conf=0.9)], Crop(140, 40, 320,
                320, W, H), 0.5)
    assert [(b.cx, b.w) for b in out] == [(315, 42)]


def _far_gate_track(zoom_below: float, frames: int = 60, dist: float = 33.0, scan: bool = True,
                    seed: int = 7) -> tuple[int, int, int]:
    """A gate ~30 px across, hovering: frames with a box on it, frames with a box elsewhere, zoom runs."""
    cfg = load_config(overrides=[f"perception.zoom_below={zoom_below}", f"perception.zoom_scan={scan}"])
    cam = RenderedCamera.from_config(cfg, seed=seed)
    yaw = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # body x -> north
    on = off = 0
    for k in range(frames):
        t = k / 30.0
        p = np.array([0.2 * math.sin(k / 9), 0.0, 10.0 + 0.1 * math.cos(k / 7)])
        b = cam.capture(t, p, yaw, np.array([0.0, dist, 10.0]), np.array([0.0, 1.0, 0.0]), 1.0)
        truth = cam.last_truth
        assert truth is not None and max(truth.w, truth.h) < 40
        if b is not None:
            near = abs(b.cx - truth.cx) < 0.5 * truth.w + 4 and abs(b.cy - truth.cy) < 0.5 * truth.h + 4
            on, off = on + near, off + (not near)
    return on, off, cam.pipeline.stats.zoom_runs


@pytest.mark.slow
def test_a_far_gate_is_boxed_on_more_frames_with_the_zoom_and_never_off_it() -> None:
    on0, off0, z0 = _far_gate_track(0.0)
    on1, off1, z1 = _far_gate_track(80.0, scan=False)  # the zoom on the track alone
    assert z0 == 0 and z1 > 0.8 * 60
    assert off0 == 0 and off1 == 0
    assert on1 >= 58, (on0, on1)
    assert on1 >= on0 + 5, (on0, on1)


@pytest.mark.slow
def test_the_scan_finds_a_far_gate_the_whole_frame_never_shows() -> None:
    on_frame, _, _ = _far_gate_track(80.0, scan=False, seed=10)  # no box in the whole frame: nothing to zoom on
    on_scan, off_scan, _ = _far_gate_track(80.0, scan=True, seed=10)
    assert on_frame == 0
    assert on_scan >= 55 and off_scan == 0


def test_the_scan_is_off_by_default_on_a_real_camera_and_on_when_asked() -> None:
    from perception.pipeline import Pipeline

    cfg = load_config()
    assert Pipeline.from_config(cfg).scan is True  # rendered frames
    assert Pipeline.from_config(cfg, real_frames=True).scan is False  # auto: unmeasured on real frames
    assert Pipeline.from_config(load_config(overrides=["perception.zoom_scan=true"]), real_frames=True).scan is True
    assert Pipeline.from_config(load_config(overrides=["perception.zoom_scan=false"])).scan is False


class _BorderBoxDetector:
    """A detector that sees one big box cut by the bottom border in the whole frame, and nothing in a crop."""

    input_hw = IN

    def __init__(self) -> None:
        self.last_ms = 0.0
        self.crops = 0

    def detect(self, image: np.ndarray, t: float = 0.0) -> list[BoundingBox]:
        if image.shape[:2] != (H, W):
            self.crops += 1
            return []
        return [box(300, 412, 128, 136, conf=0.8)]  # its bottom edge at 480: touching the border


def test_a_large_candidate_held_by_the_search_does_not_stop_the_scan() -> None:
    """SIH run000 of the twelfth session's PX4 table: the search held a 128x136 px border box for 15 s (it may not
    acquire it: cut by the border), too big to zoom on, and that stopped the tile scan, so the 40 px gate 25 m
    ahead was never looked at at full resolution."""
    from perception.pipeline import Pipeline

    det = _BorderBoxDetector()
    pipe = Pipeline.from_config(load_config(), detector=det)  # type: ignore[arg-type]
    frame = np.zeros((H, W, 3), np.uint8)
    for k in range(30):
        assert pipe.process(frame, k / 30.0) is None  # never acquired: it touches the border
        assert pipe.candidate is not None and pipe.candidate.w == 128  # ...but held as the candidate
    assert det.crops == 30 and pipe.stats.zoom_runs == 30
