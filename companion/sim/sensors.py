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

from companion.sim.draws import NormalReadAhead
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
        self._accel_bias = tuple(self.accel_bias.tolist())  # frame()'s floats
        self.gyro_bias = np.radians(rng.normal(0.0, cfg.gyro_bias, 3))
        bias = Rotation.from_rotvec(np.radians(rng.normal(0.0, cfg.attitude_bias, 3)))
        self.att_bias = bias.as_matrix()
        self._q_bias = tuple(float(c) for c in bias.as_quat())
        self.baro_bias = float(rng.normal(0.0, cfg.baro_bias))
        self._ahead: NormalReadAhead | None = None  # read_ahead(): frame() draws from it

    def read_ahead(self, block: int = 288) -> None:
        """From now on :meth:`frame` takes its normals from blocks drawn ahead (the same values; one numpy call a
        block, not a frame). Only for a stream nothing else draws from: the other draws here then raise."""
        self._ahead = NormalReadAhead(self.rng, block)

    def _own_stream(self) -> np.random.Generator:
        if self._ahead is not None:
            raise RuntimeError("Sensors: read_ahead() is on; only frame() may draw from the stream")
        return self.rng

    def imu(self, specific_force_flu: np.ndarray, omega_flu: np.ndarray) -> ImuSample:
        c = self.cfg
        rng = self._own_stream()
        acc = specific_force_flu + self.accel_bias + rng.normal(0.0, c.accel_noise, 3)
        gyr = omega_flu + self.gyro_bias + np.radians(rng.normal(0.0, c.gyro_noise, 3))
        return ImuSample(acc, gyr)

    def attitude_enu_flu(self, q_true_xyzw: np.ndarray) -> np.ndarray:
        """Estimated body FLU -> world ENU rotation matrix."""
        noise = rotvec_to_matrix(np.radians(self._own_stream().normal(0.0, self.cfg.attitude_noise, 3)))
        # Error applied in the body frame: R_est = R_true R_bias R_noise.
        return quat_to_matrix(q_true_xyzw) @ self.att_bias @ noise

    def attitude_wxyz_ned_frd(self, q_true_xyzw: np.ndarray) -> np.ndarray:
        """The estimate as PX4 reports it: scalar-first quaternion, body FRD -> world NED."""
        # Quaternion algebra on floats: this runs every frame (scipy costs ~30 us per call).
        sig = math.radians(self.cfg.attitude_noise)
        n = (self._own_stream().normal(0.0, 1.0, 3) * sig).tolist() if sig > 0 else (0.0, 0.0, 0.0)
        return self._attitude(q_true_xyzw, n)

    def _attitude(self, q_true_xyzw: np.ndarray, n: tuple[float, float, float] | list[float]) -> np.ndarray:
        """The estimate of q_true_xyzw with the rotation-vector noise n (rad), NED/FRD wxyz."""
        n0, n1, n2 = n
        a = math.sqrt(n0 ** 2 + n1 ** 2 + n2 ** 2)
        k = math.sin(0.5 * a) / a if a > 1e-12 else 0.5
        q_noise = (n0 * k, n1 * k, n2 * k, math.cos(0.5 * a))
        if type(q_true_xyzw) is tuple:  # Quadrotor.q_xyzw's floats (every frame)
            q_true = q_true_xyzw
        else:
            q_true = tuple(q_true_xyzw.tolist() if isinstance(q_true_xyzw, np.ndarray) else
                           [float(c) for c in q_true_xyzw])
        q = qmul(qmul(q_true, self._q_bias), q_noise)
        x, y, z, w = qmul(qmul(_Q_P, q), _Q_F)
        return np.array([w, x, y, z]) if w >= 0 else np.array([-w, -x, -y, -z])

    def frame(self, q_true_xyzw: np.ndarray, specific_force_flu: tuple[float, float, float],
              ) -> tuple[np.ndarray, tuple[float, float, float]]:
        """One simulator frame's draws: ``attitude_wxyz_ned_frd(q_true_xyzw)`` and the accelerometer of
        ``imu(specific_force_flu, omega).accel`` (body FLU, as floats), the same values from the same stream.

        One ``standard_normal`` of 9 in place of three ``normal`` calls of 3 (attitude, accelerometer, gyro): a
        Generator's normals come one after the other whatever the call size, and ``normal(0, s)`` is
        ``0.0 + s * z`` element by element (tested bit for bit over 200k frames); the gyro's draw is taken and
        dropped (the runner reads no gyro), which keeps the stream. Floats, not 3-vectors: each numpy operation
        on a 3-vector costs more than its arithmetic (every frame).
        """
        c = self.cfg
        sig = math.radians(c.attitude_noise)
        k = 9 if sig > 0 else 6  # no attitude noise: no attitude draw (as attitude_wxyz_ned_frd)
        z = self._ahead.take(k) if self._ahead is not None else self.rng.standard_normal(k).tolist()
        if sig > 0:
            z0, z1, z2, a0, a1, a2, _, _, _ = z
            n = ((0.0 + z0) * sig, (0.0 + z1) * sig, (0.0 + z2) * sig)
        else:
            a0, a1, a2, _, _, _ = z
            n = (0.0, 0.0, 0.0)
        q_est = self._attitude(q_true_xyzw, n)
        s = c.accel_noise
        b0, b1, b2 = self._accel_bias
        f0, f1, f2 = specific_force_flu
        return q_est, ((f0 + b0) + (0.0 + s * a0), (f1 + b1) + (0.0 + s * a1), (f2 + b2) + (0.0 + s * a2))

    def baro_altitude(self, z_true: float, rng: np.random.Generator | None = None) -> float:
        """``rng``: another stream for the white noise (the run's bias stays), e.g. for a log only."""
        noise = (self._own_stream() if rng is None else rng).normal(0.0, self.cfg.baro_noise)
        return z_true + self.baro_bias + float(noise)


class Wind:
    """Constant mean + first-order Gauss-Markov gusts per axis (ENU, m/s)."""

    def __init__(self, cfg: object, rng: np.random.Generator) -> None:
        """``cfg`` is a ``WindConfig``."""
        self.mean = np.asarray(cfg.mean, dtype=float)
        self.std = float(cfg.gust_std)
        self.tau = float(cfg.gust_tau)
        self.rng = rng
        gust = rng.normal(0.0, self.std, 3) if self.std > 0 else np.zeros(3)
        self._gust = tuple(gust.tolist())
        self._mean = tuple(self.mean.tolist())
        self._decay: tuple[float, float, float] | None = None  # (dt, a, gain) of the last dt
        m, g = self._mean, self._gust
        self._calm = (m[0] + g[0], m[1] + g[1], m[2] + g[2])  # step() without gusts

    @property
    def gust(self) -> np.ndarray:
        """The gust state, ENU m/s."""
        return np.array(self._gust)

    def step(self, dt: float) -> tuple[float, float, float]:
        """Advance the gust state by dt; returns the wind for the next interval (ENU m/s, floats).

        On floats: the same element-wise arithmetic as on 3-vectors (``normal(0, 1)`` is ``0.0 + 1.0 * z``), without
        numpy's per-operation cost (every frame)."""
        if not self.std > 0:
            return self._calm  # no gusts: the mean, the same floats every frame
        if self._decay is None or self._decay[0] != dt:
            a = math.exp(-dt / self.tau)
            # Exact discretisation keeps the stationary std at gust_std whatever dt is.
            self._decay = (dt, a, self.std * math.sqrt(1.0 - a * a))
        _, a, k = self._decay
        g0, g1, g2 = self._gust
        z0, z1, z2 = self.rng.standard_normal(3).tolist()
        g0, g1, g2 = a * g0 + k * (0.0 + z0), a * g1 + k * (0.0 + z1), a * g2 + k * (0.0 + z2)
        self._gust = (g0, g1, g2)
        m0, m1, m2 = self._mean
        return m0 + g0, m1 + g1, m2 + g2
