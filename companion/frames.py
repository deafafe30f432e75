"""The one boundary between the paper's frames and PX4's.

Paper / internal: world ENU (x east, y north, z up; g = [0, 0, -9.81]),
body FLU (x forward = camera optical axis, y left, z up = thrust axis).
PX4 / MAVSDK: world NED, body FRD, Euler angles in degrees (ZYX: yaw, pitch, roll;
positive pitch = nose up), quaternions scalar-first (w, x, y, z).
scipy's Rotation is scalar-last (x, y, z, w); every quaternion in this code base is
scalar-last unless its name says ``wxyz``.

A rotation ``R_a_b`` maps vectors from frame b to frame a (``v_a = R_a_b @ v_b``).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

# ENU <-> NED: swap x and y, negate z. Self-inverse.
P_NED_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
# FLU <-> FRD: negate y and z. Self-inverse.
F_FRD_FLU = np.diag([1.0, -1.0, -1.0])


def enu_to_ned(v: np.ndarray) -> np.ndarray:
    return np.asarray(v, dtype=float) @ P_NED_ENU.T


def ned_to_enu(v: np.ndarray) -> np.ndarray:
    return np.asarray(v, dtype=float) @ P_NED_ENU.T


def flu_to_frd(v: np.ndarray) -> np.ndarray:
    return np.asarray(v, dtype=float) @ F_FRD_FLU.T


def frd_to_flu(v: np.ndarray) -> np.ndarray:
    return np.asarray(v, dtype=float) @ F_FRD_FLU.T


def cross_xyz(a: Sequence[float], b: Sequence[float]) -> tuple[float, float, float]:
    """``np.cross`` of two 3-vectors on floats: its element-wise formula (a1 b2 - a2 b1, ...), the same bits,
    without its ~15 us of overhead."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def swap_ned_enu(v: np.ndarray) -> np.ndarray:
    """``P_NED_ENU.dot(v)`` for a 3-vector (either way: P is its own inverse), bit for bit: every product is by
    0 or +-1 and exact, so their sum is exact in any order; BLAS adds them to a +0 accumulator, which the
    leading ``0.0 +`` repeats for the sign of a zero. Without a matrix product's cost (every frame)."""
    return np.array(swap_ned_enu_xyz(*v.tolist()))


def swap_ned_enu_xyz(x: float, y: float, z: float) -> tuple[float, float, float]:
    """:func:`swap_ned_enu` on three floats, the same values (the controller's per-frame path: no array)."""
    return 0.0 + 0.0 * x + y + 0.0 * z, 0.0 + x + 0.0 * y + 0.0 * z, 0.0 + 0.0 * x + 0.0 * y - z


def R_ned_frd_from_enu_flu(R_enu_flu: np.ndarray) -> np.ndarray:
    """Body-to-world rotation, re-expressed from ENU/FLU to NED/FRD."""
    return P_NED_ENU.dot(R_enu_flu).dot(F_FRD_FLU)


def R_enu_flu_from_ned_frd(R_ned_frd: np.ndarray) -> np.ndarray:
    """Body-to-world rotation, re-expressed from NED/FRD to ENU/FLU."""
    return P_NED_ENU.dot(R_ned_frd).dot(F_FRD_FLU)


def euler_ned_deg_from_R(R_ned_frd: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in degrees, ZYX convention, from a body FRD -> world NED rotation.

    Closed form (the same as scipy's ``as_euler('ZYX')`` away from gimbal lock) because this is on
    the 30 Hz hot path and scipy's object construction costs tens of microseconds.
    """
    return euler_ned_deg_from_rows(np.asarray(R_ned_frd, dtype=float).tolist())


def euler_ned_deg_from_rows(R: Sequence[Sequence[float]]) -> tuple[float, float, float]:
    """:func:`euler_ned_deg_from_R` of a rotation given as nested lists of floats (``R.tolist()``)."""
    (r00, r01, _), (r10, r11, _), (r20, r21, r22) = R
    return euler_ned_deg_of(r00, r01, r10, r11, r20, r21, r22)


def euler_ned_deg_of(r00: float, r01: float, r10: float, r11: float, r20: float, r21: float,
                     r22: float) -> tuple[float, float, float]:
    """:func:`euler_ned_deg_from_rows` of the rotation's entries it reads (guidance.to_setpoint: no rows built)."""
    s = r20 if r20 > -1.0 else -1.0  # min(1.0, max(-1.0, r20)) without the builtins' cost (every frame)
    pitch = -math.asin(s if s < 1.0 else 1.0)
    if math.hypot(r21, r22) < 1e-7:
        # Gimbal lock (nose straight up or down): only yaw - roll is defined; take roll = 0,
        # then body y = Rz(yaw) e_y gives the yaw.
        roll = 0.0
        yaw = math.atan2(-r01, r11)
    else:
        roll = math.atan2(r21, r22)
        yaw = math.atan2(r10, r00)
    return math.degrees(roll), math.degrees(pitch), math.degrees(yaw)


def R_from_euler_ned_deg(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Body FRD -> world NED rotation from (roll, pitch, yaw) degrees, ZYX."""
    return Rotation.from_euler("ZYX", [yaw, pitch, roll], degrees=True).as_matrix()


def quat_wxyz_from_R(R: np.ndarray) -> np.ndarray:
    """Scalar-first quaternion (MAVSDK / MAVLink order) of a rotation matrix, w >= 0."""
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    q = np.array([w, x, y, z])
    return -q if q[0] < 0 else q


def R_from_quat_wxyz(q_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrix of a scalar-first quaternion (normalised here).

    Closed form rather than scipy: it runs once per camera frame in the controller, and
    building a Rotation costs more than the whole guidance solve. Tested against scipy.
    """
    R, shared = _R_from_quat_wxyz(q_wxyz)
    return R.copy() if shared else R


def R_from_quat_wxyz_shared(q_wxyz: np.ndarray) -> np.ndarray:
    """:func:`R_from_quat_wxyz` for a caller that only reads it: possibly the cached matrix itself, immutable (a
    write raises), without the copy (the controller's step)."""
    return _R_from_quat_wxyz(q_wxyz)[0]


def _R_from_quat_wxyz(q_wxyz: np.ndarray) -> tuple[np.ndarray, bool]:
    """The matrix, and whether it is the cache's own (immutable: hand out copies)."""
    global _LAST_R
    key = None
    if type(q_wxyz) is np.ndarray and q_wxyz.dtype is _F64 and q_wxyz.shape == (4,):
        # The same frame's attitude is turned into a matrix several times (controller, engagement, hover
        # estimate): the last one is kept, keyed on the quaternion's exact bits, and handed out as a copy.
        key = q_wxyz.tobytes()
        last_key, last_R = _LAST_R
        if key == last_key:
            return last_R, True
        w, x, y, z = q_wxyz.tolist()  # the same floats as float() of each element
    else:
        w, x, y, z = map(float, q_wxyz)  # the same floats as a generator of float(c), cheaper (the simulator's path)
    ww, xx, yy, zz = w * w, x * x, y * y, z * z  # each product once (the same floats as written out twice)
    n = ww + xx + yy + zz
    if not (n > 1e-12 and math.isfinite(n)):
        raise ValueError(f"attitude quaternion is not a rotation: {tuple(q_wxyz)}")
    s = 2.0 / n
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    entries = (
        1.0 - s * (yy + zz), s * (xy - zw), s * (xz + yw),
        s * (xy + zw), 1.0 - s * (xx + zz), s * (yz - xw),
        s * (xz - yw), s * (yz + xw), 1.0 - s * (xx + yy),
    )
    if key is None:
        return np.array(entries).reshape(3, 3), False  # flat, then reshaped: a third cheaper than nested lists
    # The cached matrix is handed out only as copies or to readers: an immutable array on the packed floats (the
    # same bits) costs less than np.array's parsing of the tuple and saves a copy (every frame).
    R = np.ndarray((3, 3), _F64, _PACK_3X3.pack(*entries))
    _LAST_R = (key, R)  # one tuple rebinding: a reader on another thread sees a matching pair
    return R, True


_LAST_R: tuple[bytes | None, np.ndarray] = (None, np.eye(3))
# The native float64 dtype is a singleton: an identity test is half the cost of ``dtype == np.float64`` (a
# non-native byte order fails it and takes the general path, with the same values).
_F64 = np.dtype(np.float64)
_PACK_3X3 = struct.Struct("9d")  # nine native doubles: the float64 array's bytes
