"""Ground truth from PX4's simulator (SIH), not from PX4's estimator.

PX4's LOCAL_POSITION_NED is EKF2's estimate (1-3 m off on the ground, leading the truth by the assumed GPS
delay). SIH's own MAVLink link (PX4 sends from 19450+N to 127.0.0.1:19410+N) carries HIL_STATE_QUATERNION:
the simulated vehicle's true position (lat/lon/alt), velocity and attitude. ``SihTruth`` listens there
and converts to local NED with SIH's flat earth (../shared/px4-sitl/README.md).

SCORING AND SENSOR SIMULATION ONLY: the synthetic camera draws the virtual gate from this pose and the
scorer measures the gate pass with it. The controller never sees it (it gets the box, PX4's attitude
estimate and time).
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

EARTH_RADIUS = 6371000.0  # m, SIH's flat-earth radius


@dataclass(frozen=True)
class TrueState:
    """The simulator's true state (a companion.vehicle.TruePose: the link's TruthForLog plus the attitude)."""

    position_ned: np.ndarray  # m, from the origin
    velocity_ned: np.ndarray  # m/s
    q_wxyz: np.ndarray  # attitude NED <- FRD, scalar first
    t_rx: float  # host monotonic time of arrival


def hil_to_ned(lat_e7: float, lon_e7: float, alt_mm: float, origin: Sequence[float]) -> np.ndarray:
    """HIL_STATE_QUATERNION position -> local NED (m) about origin (lat0 1e-7 deg, lon0 1e-7 deg, h0 m).

    SIH's flat earth: n = rad(lat - lat0) R, e = rad(lon - lon0) R cos(lat0), d = -(alt - h0).
    """
    lat0, lon0, h0 = origin
    n = math.radians((lat_e7 - lat0) * 1e-7) * EARTH_RADIUS
    e = math.radians((lon_e7 - lon0) * 1e-7) * EARTH_RADIUS * math.cos(math.radians(lat0 * 1e-7))
    return np.array([n, e, -(alt_mm / 1000.0 - h0)])


def state_from_message(msg: Any, origin: Sequence[float], t_rx: float) -> TrueState:
    q = np.asarray(msg.attitude_quaternion, dtype=float)
    return TrueState(hil_to_ned(msg.lat, msg.lon, msg.alt, origin),
                     np.array([msg.vx, msg.vy, msg.vz], dtype=float) / 100.0, q / np.linalg.norm(q), t_rx)


class SihTruth:
    """A thread that reads HIL_STATE_QUATERNION from SIH's link and keeps the recent true states.

    ``latest()`` is the newest state; ``at(t)`` the state at host time ``t`` (attitude interpolated on
    the sphere, position interpolated, or extrapolated with the velocity past the newest sample). A
    companion.vehicle.TruthSource.
    """

    def __init__(self, url: str, origin: Sequence[float] | None = None, history: int = 200) -> None:
        from pymavlink import mavutil

        self.url = url
        self.origin: tuple[float, float, float] | None = tuple(origin) if origin is not None else None  # type: ignore[assignment]
        self._conn = mavutil.mavlink_connection(url, source_system=254, source_component=191)
        self._hist: deque[TrueState] = deque(maxlen=history)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.received = 0
        self._thread = threading.Thread(target=self._run, name="sih-truth", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self._conn.recv_match(type="HIL_STATE_QUATERNION", blocking=True, timeout=0.2)
            except Exception:  # a closed socket on stop, or a garbled datagram
                if self._stop.is_set():
                    return
                continue
            if msg is None:
                continue
            t = time.monotonic()
            if self.origin is None:  # the first message after a fresh start is SIH_LOC_*
                self.origin = (float(msg.lat), float(msg.lon), msg.alt / 1000.0)
            st = state_from_message(msg, self.origin, t)
            with self._lock:
                self._hist.append(st)
            self.received += 1

    def latest(self) -> TrueState | None:
        with self._lock:
            return self._hist[-1] if self._hist else None

    def wait(self, timeout: float = 5.0) -> TrueState:
        """The first state (raises TimeoutError when SIH's link is silent)."""
        deadline = time.monotonic() + timeout
        while (s := self.latest()) is None:
            if time.monotonic() > deadline:
                raise TimeoutError(f"no HIL_STATE_QUATERNION on {self.url} within {timeout:.0f} s")
            time.sleep(0.02)
        return s

    def at(self, t: float) -> TrueState | None:
        with self._lock:
            hist = list(self._hist)
        if not hist:
            return None
        last = hist[-1]
        if t >= last.t_rx or len(hist) < 2:
            # Past the newest sample (at most one period, 20 ms at 50 Hz): constant velocity, same attitude.
            dt = min(max(t - last.t_rx, 0.0), 0.1)
            return TrueState(last.position_ned + last.velocity_ned * dt, last.velocity_ned, last.q_wxyz, t)
        ts = np.array([s.t_rx for s in hist])
        i = int(np.searchsorted(ts, t))
        if i == 0:
            return hist[0]
        a, b = hist[i - 1], hist[i]
        w = (t - a.t_rx) / max(b.t_rx - a.t_rx, 1e-9)
        quats = Rotation.from_quat([np.roll(a.q_wxyz, -1), np.roll(b.q_wxyz, -1)])  # scipy: scalar last
        q = np.roll(Slerp([0.0, 1.0], quats)([w]).as_quat()[0], 1)
        return TrueState(a.position_ned + w * (b.position_ned - a.position_ned),
                         a.velocity_ned + w * (b.velocity_ned - a.velocity_ned), q, t)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        with contextlib.suppress(Exception):
            self._conn.close()


def open_truth(cfg: Any) -> SihTruth | None:
    """SIH's ground truth when px4.truth_url is set (None otherwise), for the caller to pass to the synthetic
    camera and the flight log explicitly (a companion.vehicle.TruthSource); close() it when done."""
    if not cfg.px4.truth_url:
        return None
    return SihTruth(cfg.px4.truth_url, cfg.px4.truth_origin)
