"""The simulator's per-frame noise drawn a block ahead gives the very floats of a draw a frame (issue 21)."""

from __future__ import annotations

import numpy as np
import pytest

from companion.config import load_config
from companion.sim.camera import GeometricCamera
from companion.sim.draws import NormalReadAhead
from companion.sim.runner import _camera_model
from companion.sim.sensors import Sensors


def _bits(values: list[float] | tuple[float, ...] | np.ndarray) -> bytes:
    return np.asarray(values, dtype=float).tobytes()


def test_blocks_hand_out_the_stream_in_order_whatever_the_sizes():
    ahead, direct = NormalReadAhead(np.random.default_rng(3), block=7), np.random.default_rng(3)
    for n in (1, 4, 9, 7, 3, 20, 2) * 5:
        assert _bits(ahead.take(n)) == _bits(direct.standard_normal(n))


@pytest.mark.parametrize("attitude_noise", [0.3, 0.0])
def test_sensor_frames_read_ahead_equal_the_per_frame_draws(attitude_noise):
    cfg = load_config().sim.sensors.model_copy(update={"attitude_noise": attitude_noise})
    a, b = Sensors(cfg, np.random.default_rng(8)), Sensors(cfg, np.random.default_rng(8))
    b.read_ahead(block=50)
    rng = np.random.default_rng(9)
    for _ in range(200):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        f = tuple(rng.normal(0.0, 5.0, 3).tolist())
        (qa, fa), (qb, fb) = a.frame(q, f), b.frame(q, f)
        assert _bits(qa) == _bits(qb) and _bits(fa) == _bits(fb)
    with pytest.raises(RuntimeError):
        b.imu(np.zeros(3), np.zeros(3))  # the stream is frame()'s alone


def test_sensor_frame_equals_attitude_then_imu():
    cfg = load_config().sim.sensors
    a, b = Sensors(cfg, np.random.default_rng(4)), Sensors(cfg, np.random.default_rng(4))
    q, f = np.array([0.1, -0.2, 0.3, 0.9]) / np.linalg.norm([0.1, -0.2, 0.3, 0.9]), (0.3, -0.1, 9.7)
    for _ in range(50):
        q_est, acc = a.frame(q, f)
        assert _bits(q_est) == _bits(b.attitude_wxyz_ned_frd(q))
        assert _bits(acc) == _bits(b.imu(np.array(f), np.zeros(3)).accel)


def test_camera_pixel_noise_read_ahead_equals_per_frame_draws():
    cfg = load_config()
    cams = [GeometricCamera(_camera_model(cfg), 1.5, 0.0, 2.0, np.random.default_rng(5), True) for _ in range(2)]
    cams[1].read_ahead(block=10)
    R = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    for k in range(60):
        boxes = [c.capture(0.1 * k, np.zeros(3), R, np.array([20.0, 0.5, 0.2 * (k % 5)]), np.array([-1.0, 0.0, 0.0]),
                           0.75) for c in cams]
        assert boxes[0] is not None and boxes[1] is not None
        assert _bits([boxes[0].cx, boxes[0].cy, boxes[0].w, boxes[0].h]) == _bits(
            [boxes[1].cx, boxes[1].cy, boxes[1].w, boxes[1].h])
    with pytest.raises(RuntimeError):
        GeometricCamera(_camera_model(cfg), 1.5, 0.1, 2.0, np.random.default_rng(5)).read_ahead()
