"""The flight plot's box-size series stays on the image's scale (a projected ring at the pass is huge)."""

import numpy as np

from companion.app.plot import box_sizes


def _det(w, h, valid):
    n = len(w)
    return {"t": np.arange(n, dtype=float), "w": np.array(w, float), "h": np.array(h, float),
            "valid": np.array(valid, float)}


def test_boxes_beyond_the_image_are_marked_not_plotted_at_their_size():
    det = _det([50, 300, 3005, 120, 9000], [40, 320, 3008, 100, 10], [1, 1, 1, 0, 1])
    t_in, size_in, t_over, top = box_sizes(det, {"width": 640, "height": 480})
    assert top == 640.0
    assert t_in.tolist() == [0.0, 1.0] and size_in.tolist() == [50.0, 320.0]  # the larger side; invalid dropped
    assert t_over.tolist() == [2.0, 4.0]


def test_without_a_camera_size_the_largest_box_sets_the_scale():
    t_in, size_in, t_over, top = box_sizes(_det([50, 200], [60, 10], [1, 1]), {})
    assert top == 200.0 and t_in.tolist() == [0.0, 1.0] and size_in.tolist() == [60.0, 200.0] and len(t_over) == 0

