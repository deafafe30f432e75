"""Frame conventions and pixel -> world LOS, checked on geometry computed by hand and with OpenCV."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from companion import frames
from companion.config import CameraConfig, MountConfig
from perception.los import CameraModel, LosFilter, los_world

vec = st.lists(st.floats(-1e3, 1e3, allow_nan=False), min_size=3, max_size=3).map(np.array)
rotations = st.integers(0, 2**31 - 1).map(lambda s: Rotation.random(random_state=s))


@given(v=vec)
def test_ned_enu_and_frd_flu_round_trips(v) -> None:
    assert np.allclose(frames.ned_to_enu(frames.enu_to_ned(v)), v)
    assert np.allclose(frames.frd_to_flu(frames.flu_to_frd(v)), v)
    east, north, up = v
    assert np.allclose(frames.enu_to_ned(v), [north, east, -up])
    fwd, left, upb = v
    assert np.allclose(frames.flu_to_frd(v), [fwd, -left, -upb])


@settings(max_examples=300)
@given(rot=rotations, v=vec)
def test_rotation_conversion_maps_the_same_physical_vectors(rot, v) -> None:
    R_enu_flu = rot.as_matrix()
    R_ned_frd = frames.R_ned_frd_from_enu_flu(R_enu_flu)
    # A body vector rotated to the world must be the same physical vector in either convention.
    assert np.allclose(R_ned_frd @ frames.flu_to_frd(v), frames.enu_to_ned(R_enu_flu @ v))
    assert np.allclose(frames.R_enu_flu_from_ned_frd(R_ned_frd), R_enu_flu)


@settings(max_examples=300)
@given(rot=rotations)
def test_euler_and_quaternion_against_scipy(rot) -> None:
    R = rot.as_matrix()
    roll, pitch, yaw = frames.euler_ned_deg_from_R(R)
    yaw_s, pitch_s, roll_s = rot.as_euler("ZYX", degrees=True)
    assert (roll, pitch, yaw) == pytest.approx((roll_s, pitch_s, yaw_s), abs=1e-6)
    q = frames.quat_wxyz_from_R(R)
    assert q[0] >= 0
    assert np.allclose(frames.R_from_quat_wxyz(q), R)
    assert np.allclose(frames.R_from_quat_wxyz(-2.0 * q), R)  # sign and scale do not matter


def test_euler_meaning_in_ned() -> None:
    # Yaw 90 deg: nose east. Pitch +10: nose up (NED z is down, so body x gets a negative z).
    R = frames.R_from_euler_ned_deg(0.0, 10.0, 90.0)
    assert np.allclose(R[:, 0], [0.0, math.cos(math.radians(10)), -math.sin(math.radians(10))], atol=1e-12)
    R = frames.R_from_euler_ned_deg(30.0, 0.0, 0.0)
    assert R[2, 1] > 0


def test_quaternion_rejects_garbage() -> None:
    with pytest.raises(ValueError, match="not a rotation"):
        frames.R_from_quat_wxyz(np.array([0.0, 0.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match="not a rotation"):
        frames.R_from_quat_wxyz(np.array([np.nan, 0.0, 0.0, 1.0]))


# --- pixel -> ray -> body -> world ----------------------------------------------------------------


def model(**kw) -> CameraModel:
    return CameraModel.from_config(CameraConfig(**kw))


def test_default_intrinsics_from_half_fov() -> None:
    m = model()
    assert m.K[0, 0] == pytest.approx(320.0 / math.tan(math.radians(33.5)))
    # The image edge at mid-height is exactly 33.5 deg right of the optical axis.
    ray = m.ray_body(640.0, 240.0)
    assert math.degrees(math.atan2(ray[1], ray[0])) == pytest.approx(33.5)
    assert ray[2] == pytest.approx(0.0)


def test_pixel_to_world_ray_with_a_rotated_vehicle() -> None:
    m = model()
    fx = m.K[0, 0]
    # Vehicle yawed 90 deg (nose east) and pitched 20 deg up; a pixel 10 deg right of centre, 5 deg up.
    R = frames.R_from_euler_ned_deg(0.0, 20.0, 90.0)
    u = 320.0 + fx * math.tan(math.radians(10.0))
    v = 240.0 - fx * math.tan(math.radians(5.0)) * math.sqrt(1 + math.tan(math.radians(10.0)) ** 2)
    l = los_world(m, u, v, R)  # noqa: E741
    # By hand: in the body, the ray is az 10 deg right, el 5 deg up (FRD: y right, z down).
    ray_b = np.array([math.cos(math.radians(5)) * math.cos(math.radians(10)),
                      math.cos(math.radians(5)) * math.sin(math.radians(10)),
                      -math.sin(math.radians(5))])
    assert np.allclose(m.ray_body(u, v), ray_b, atol=1e-12)
    assert np.allclose(l, R @ ray_b, atol=1e-12)
    assert np.linalg.norm(l) == pytest.approx(1.0)
    # Centre pixel = the body x axis in the world: east, tilted up 20 deg (NED z negative).
    c = los_world(m, 320.0, 240.0, R)
    assert np.allclose(c, [0.0, math.cos(math.radians(20)), -math.sin(math.radians(20))], atol=1e-12)


def test_camera_mount_pitch_up() -> None:
    m = model(mount=MountConfig(pitch=10.0))
    # The optical axis is 10 deg above body x: FRD up is -z.
    assert np.allclose(m.ray_body(320.0, 240.0), [math.cos(math.radians(10)), 0.0, -math.sin(math.radians(10))])
    # Image right stays body right for a pure pitch.
    r = m.ray_body(400.0, 240.0)
    assert r[1] > 0


def test_camera_mount_upside_down() -> None:
    m = model(mount=MountConfig(roll=180.0))
    r = m.ray_body(400.0, 200.0)  # right and up in the image
    assert r[1] < 0 and r[2] > 0  # is left and down on the body


@settings(max_examples=200, deadline=None)
@given(u=st.floats(20, 620), v=st.floats(20, 460))
def test_distortion_round_trip_against_opencv_projection(u, v) -> None:
    m = model(distortion=[-0.28, 0.07, 0.001, -0.0005, 0.0])
    ray = m.ray_cam(u, v)
    # Independent: OpenCV's forward projection of our undistorted ray lands back on the pixel.
    img, _ = cv2.projectPoints(ray.reshape(1, 1, 3), np.zeros(3), np.zeros(3), m.K, m.dist)
    assert img[0, 0] == pytest.approx([u, v], abs=1e-3)
    assert m.project_body(m.ray_body(u, v)) == pytest.approx((u, v), abs=1e-3)


def test_project_behind_camera_is_none() -> None:
    assert model().project_body(np.array([-1.0, 0.0, 0.0])) is None


# --- LOS filter ---------------------------------------------------------------------------------------


def test_los_filter_first_order_response() -> None:
    f = LosFilter(cutoff_hz=2.0)
    a = np.array([1.0, 0.0, 0.0])
    b = Rotation.from_rotvec([0, 0, math.radians(1.0)]).apply(a)  # a 1 deg step
    f.update(0.0, a)
    dt = 1 / 30
    angles = []
    for k in range(1, 31):
        out = f.update(k * dt, b)
        angles.append(math.degrees(math.atan2(np.linalg.norm(np.cross(out, b)), out @ b)))
    alpha = 1 - math.exp(-2 * math.pi * 2.0 * dt)
    # For a small step the unit-vector filter is the scalar first-order filter: error (1 - alpha)^k.
    assert angles[0] == pytest.approx((1 - alpha) * 1.0, rel=1e-3)
    assert angles[9] == pytest.approx((1 - alpha) ** 10, rel=2e-3)
    assert np.linalg.norm(out) == pytest.approx(1.0)


def test_los_filter_restarts_after_a_gap_and_survives_opposite_vectors() -> None:
    f = LosFilter(cutoff_hz=5.0, max_dt=0.5)
    a = np.array([1.0, 0.0, 0.0])
    f.update(0.0, a)
    assert np.allclose(f.update(2.0, -a), -a)  # long gap: restart at the measurement
    f2 = LosFilter(cutoff_hz=1.0 / (2 * math.pi) * math.log(2) * 30)  # alpha = 0.5 at 30 Hz
    f2.update(0.0, a)
    out = f2.update(1 / 30, -a)
    assert np.all(np.isfinite(out)) and np.linalg.norm(out) == pytest.approx(1.0)
