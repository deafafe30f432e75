"""perception.realworld: training frames for real cameras (boxes follow the gate's pixels)."""

from __future__ import annotations

import numpy as np

from perception.realworld import draw_hard_negative, photo_backgrounds, real_scene


def test_real_scenes_have_boxes_inside_the_image() -> None:
    rng = np.random.default_rng(5)
    n_boxes = 0
    for _ in range(12):
        img, boxes = real_scene(rng, photos=())  # procedural backgrounds: no optional package needed
        h, w = img.shape[:2]
        assert img.dtype == np.uint8 and w == 640 and h in (480, 360, 330)
        assert boxes.shape[1] == 4 and np.isfinite(boxes).all()
        assert (boxes[:, 0] >= 0).all() and (boxes[:, 2] <= w).all() and (boxes[:, 1] >= 0).all()
        assert (boxes[:, 3] <= h).all() and (boxes[:, 2] - boxes[:, 0] >= 3).all()
        n_boxes += len(boxes)
    assert n_boxes >= 6


def test_gate_free_scenes_and_negatives() -> None:
    rng = np.random.default_rng(1)
    img, boxes = real_scene(rng, photos=(), p_empty=1.0)
    assert len(boxes) == 0 and img.std() > 5  # something is drawn, nothing is a gate
    canvas = np.full((200, 300, 3), 128, np.uint8)
    for _ in range(20):
        draw_hard_negative(canvas, rng)
    assert (canvas != 128).any()
    assert all(p.ndim == 3 and p.shape[2] == 3 for p in photo_backgrounds())


def test_board_behind_a_gate_stays_out_of_its_box() -> None:
    from perception.realworld import _board_behind

    rng = np.random.default_rng(3)
    canvas = np.zeros((240, 320, 3), np.uint8)
    outer = np.array([[140.0, 100.0], [180.0, 100.0], [180.0, 140.0], [140.0, 140.0]])
    _board_behind(canvas, rng, outer)
    _, xs = np.nonzero(canvas.max(axis=2) > 100)  # a light board was drawn around the gate's place ...
    assert len(xs) > 40 * 40 * 0.5 and xs.min() < 180 and xs.max() > 140
    before = canvas.copy()
    _board_behind(canvas, rng, np.full((4, 2), np.inf))  # ... and nothing for a gate projected to infinity
    assert (canvas == before).all()

