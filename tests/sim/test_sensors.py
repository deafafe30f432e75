"""Sensor models: the attitude estimate PX4 would report, IMU, baro, wind."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from companion.frames import R_from_quat_wxyz, R_ned_frd_from_enu_flu
from companion.sim.config import SensorsConfig, WindConfig
from companion.sim.sensors import Sensors, Wind


def test_attitude_estimate_is_the_true_attitude_in_ned_frd_without_noise():
    s = Sensors(SensorsConfig(attitude_noise=0.0, attitude_bias=0.0), np.random.default_rng(0))
    for q in Rotation.random(50, random_state=2).as_quat():
        q_wxyz = s.attitude_wxyz_ned_frd(q)
        assert q_wxyz[0] >= 0
        expected = R_ned_frd_from_enu_flu(Rotation.from_quat(q).as_matrix())
        assert np.allclose(R_from_quat_wxyz(q_wxyz), expected, atol=1e-12)


def test_attitude_noise_has_the_configured_size():
    s = Sensors(SensorsConfig(attitude_noise=0.5, attitude_bias=0.0), np.random.default_rng(1))
    q = Rotation.from_euler("zyx", [30, 10, -5], degrees=True).as_quat()
    R_true = R_ned_frd_from_enu_flu(Rotation.from_quat(q).as_matrix())
    errs = [Rotation.from_matrix(R_true.T @ R_from_quat_wxyz(s.attitude_wxyz_ned_frd(q))).as_rotvec()
            for _ in range(3000)]
    std = np.degrees(np.std(errs, axis=0))
    assert np.all(np.abs(std - 0.5) < 0.04)


def test_imu_bias_and_noise():
    s = Sensors(SensorsConfig(accel_noise=0.1, accel_bias=0.0, gyro_noise=0.0, gyro_bias=0.0),
                np.random.default_rng(2))
    acc = np.array([s.imu(np.array([0.0, 0.0, 9.81]), np.zeros(3)).accel for _ in range(4000)])
    assert np.allclose(acc.mean(axis=0), [0, 0, 9.81], atol=0.01)
    assert np.all(np.abs(acc.std(axis=0) - 0.1) < 0.01)
    s2 = Sensors(SensorsConfig(gyro_bias=1.0, gyro_noise=0.0), np.random.default_rng(3))
    g = s2.imu(np.zeros(3), np.zeros(3)).gyro
    assert np.allclose(g, s2.gyro_bias) and np.linalg.norm(g) > 0


def test_baro_offset_is_constant_per_run():
    s = Sensors(SensorsConfig(baro_noise=0.0, baro_bias=0.5), np.random.default_rng(4))
    a, b = s.baro_altitude(10.0), s.baro_altitude(20.0)
    assert math.isclose(b - a, 10.0) and a != 10.0


def test_wind_mean_and_gust_statistics():
    w = Wind(WindConfig(mean=[2.0, -1.0, 0.0], gust_std=1.5, gust_tau=0.5), np.random.default_rng(5))
    samples = np.array([w.step(0.05) for _ in range(40000)])
    assert np.allclose(samples.mean(axis=0), [2.0, -1.0, 0.0], atol=0.1)
    assert np.all(np.abs(samples.std(axis=0) - 1.5) < 0.1)
    calm = Wind(WindConfig(mean=[1.0, 0.0, 0.0]), np.random.default_rng(6))
    assert np.allclose(calm.step(0.1), [1.0, 0.0, 0.0])
