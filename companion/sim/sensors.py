"""Simulated onboard sensors: IMU (noise + per-run bias), attitude estimate, barometer, and wind.

The attitude estimate is what PX4's EKF would report: the true attitude rotated by a small
per-run bias and white noise (rotation vectors, per axis). The controller sees only this
estimate, converted to NED/FRD wxyz at the MAVLink boundary (companion/frames.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from companion.sim.dynamics import qmul, quat_to_matrix, rotvec_to_matrix
from perception.fastinit import fast_init

# ENU -> NED and FLU -> FRD as quaternions (xyzw): both are half turns, so
# R_ned_frd = P R_enu_flu F  <=>  q_ned_frd = q_P * q * q_F.
_Q_P = (math.sqrt(0.5), math.sqrt(0.5), 0.0, 0.0)  # pi about (1, 1, 0) / sqrt(2)
_Q_F = (1.0, 0.0, 0.0, 0.0)  # pi about x


@fast_init  # one a frame: the slot-descriptor __init__ (perception/fastinit.py)
@dataclass(frozen=True, slots=True)
class ImuSample:
    accel: np.ndarray  # specific force, body FLU, m/s^2
    gyro: np.ndarray  # body FLU, rad/s


class Sensors:
    """Noise models; every random draw comes from the one ``rng`` so a seed fixes a run."""

    def __init__(self, cfg: object, rng: np.random.Generator) -> None:
        """``cfg`` is a ``SensorsConfig`` (units canonical: m/s^2, deg/s, deg, m)."""
        self.cfg = cfg
        self.rng = rng
        self.accel_bias = rng.normal(0.0, cfg.accel_bias, 3)
        self.gyro_bias = np.radians(rng.normal(0.0, cfg.gyro_bias, 3))
        bias = Rotation.from_rotvec(np.radians(rng.normal(0.0, cfg.attitude_bias, 3)))
        self.att_bias = bias.as_matrix()
        self._q_bias = tuple(float(c) for c in bias.as_quat())
        self.baro_bias = float(rng.normal(0.0, cfg.baro_bias))

    def imu(self, specific_force_flu: np.ndarray, omega_flu: np.ndarray) -> ImuSample:
        c = self.cfg
        acc = specific_force_flu + self.accel_bias + self.rng.normal(0.0, c.accel_noise, 3)
        gyr = omega_flu + self.gyro_bias + np.radians(self.rng.normal(0.0, c.gyro_noise, 3))
        return ImuSample(acc, gyr)

    def attitude_enu_flu(self, q_true_xyzw: np.ndarray) -> np.ndarray:
        """Estimated body FLU -> world ENU rotation matrix."""
        noise = rotvec_to_matrix(np.radians(self.rng.normal(0.0, self.cfg.attitude_noise, 3)))
        # Error applied in the body frame: R_est = R_true R_bias R_noise.
        return quat_to_matrix(q_true_xyzw) @ self.att_bias @ noise

    def attitude_wxyz_ned_frd(self, q_true_xyzw: np.ndarray) -> np.ndarray:
        """The estimate as PX4 reports it: scalar-first quaternion, body FRD -> world NED."""
        # Quaternion algebra on floats: this runs every frame (scipy costs ~30 us per call).
        sig = math.radians(self.cfg.attitude_noise)
        n0, n1, n2 = (self.rng.normal(0.0, 1.0, 3) * sig).tolist() if sig > 0 else (0.0, 0.0, 0.0)
        a = math.sqrt(n0 ** 2 + n1 ** 2 + n2 ** 2)
        k = math.sin(0.5 * a) / a if a > 1e-12 else 0.5
        q_noise = (n0 * k, n1 * k, n2 * k, math.cos(0.5 * a))
        q_true = q_true_xyzw.tolist() if isinstance(q_true_xyzw, np.ndarray) else [float(c) for c in q_true_xyzw]
        q = qmul(qmul(tuple(q_true), self._q_bias), q_noise)
        x, y, z, w = qmul(qmul(_Q_P, q), _Q_F)
        return np.array([w, x, y, z]) if w >= 0 else np.array([-w, -x, -y, -z])

    def baro_altitude(self, z_true: float, rng: np.random.Generator | None = None) -> float:
        """``rng``: another stream for the white noise (the run's bias stays), e.g. for a log only."""
        return z_true + self.baro_bias + float((self.rng if rng is None else rng).normal(0.0, self.cfg.baro_noise))


class Wind:
    """Constant mean + first-order Gauss-Markov gusts per axis (ENU, m/s)."""

    def __init__(self, cfg: object, rng: np.random.Generator) -> None:
        """``cfg`` is a ``WindConfig``."""
        self.mean = np.asarray(cfg.mean, dtype=float)
        self.std = float(cfg.gust_std)
        self.tau = float(cfg.gust_tau)
        self.rng = rng
        self.gust = rng.normal(0.0, self.std, 3) if self.std > 0 else np.zeros(3)

    def step(self, dt: float) -> np.ndarray:
        """Advance the gust state by dt; returns the wind for the next interval."""
        if self.std > 0:
            a = math.exp(-dt / self.tau)
            # Exact discretisation keeps the stationary std at gust_std whatever dt is.
            self.gust = a * self.gust + self.std * math.sqrt(1.0 - a * a) * self.rng.normal(0.0, 1.0, 3)
        return self.mean + self.gust
