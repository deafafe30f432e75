"""The vehicle as the flight app sees it: declared interfaces only (typing Protocols, no behaviour).

``VehicleTelemetry`` is what may be read and waited for: PX4's attitude estimate, IMU, barometer, modes,
link health and parameters. ``VehicleControl`` adds the calls that command the vehicle (arm, take off,
offboard setpoints, hold, land). Shadow mode hands out a telemetry-only view; a flight gets control.
``TruthSource`` is where the vehicle really is, for the flight log, the gate score and the synthetic
camera ONLY: the controller never sees it (it flies from the camera, the attitude and the IMU).

The implementations are ``companion.app.link.VehicleLink`` (mavsdk; VehicleControl),
``companion.px4sitl.truth.SihTruth`` (PX4 SIH's ground truth) and
``companion.app.telemetry.LinkPositionTruth`` (the link's own EKF position; TruthSource). Frames: NED
world, FRD body, quaternions scalar first; times ``t_rx`` are host ``time.monotonic()`` at arrival.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import numpy as np


# ------------------------------------------------------------------------------------------ samples
class Attitude(Protocol):
    """PX4's attitude estimate (body FRD -> world NED)."""

    @property
    def q_wxyz(self) -> np.ndarray: ...
    @property
    def R_ned_frd(self) -> np.ndarray: ...
    @property
    def t_vehicle(self) -> float: ...  # s since autopilot boot
    @property
    def t_rx(self) -> float: ...


class AttitudeHistory(Protocol):
    """The recent attitude estimates: the attitude at a camera frame's capture time."""

    def at(self, t: float) -> np.ndarray | None: ...  # wxyz at host time t (nearest outside the span)
    def __len__(self) -> int: ...


class Imu(Protocol):
    @property
    def accel_frd(self) -> np.ndarray: ...  # specific force, m/s^2
    @property
    def gyro_frd(self) -> np.ndarray: ...  # rad/s
    @property
    def t_vehicle(self) -> float: ...
    @property
    def t_rx(self) -> float: ...


class Baro(Protocol):
    @property
    def altitude_m(self) -> float: ...  # above the reference taken at arm()
    @property
    def altitude_raw_m(self) -> float: ...  # PX4's barometric altitude
    @property
    def t_rx(self) -> float: ...


class PositionSample(Protocol):
    """Position/velocity NED: log and scoring only."""

    @property
    def position_ned(self) -> np.ndarray: ...  # m
    @property
    def velocity_ned(self) -> np.ndarray: ...  # m/s
    @property
    def t_rx(self) -> float: ...


class TruePose(PositionSample, Protocol):
    """A position sample with the attitude that goes with it (draws the synthetic camera's picture)."""

    @property
    def q_wxyz(self) -> np.ndarray: ...


class SetpointLike(Protocol):
    """An attitude setpoint: roll/pitch/yaw in degrees (NED/FRD, absolute yaw), thrust 0..1."""

    roll_deg: float
    pitch_deg: float
    yaw_deg: float
    thrust: float


# -------------------------------------------------------------------------------------- interfaces
class VehicleTelemetry(Protocol):
    """Reading the vehicle: telemetry caches (None until first received), waits and parameter reads.

    Nothing here commands the vehicle: shadow mode runs on exactly this.
    """

    @property
    def attitude(self) -> Attitude | None: ...
    @property
    def attitude_history(self) -> AttitudeHistory: ...
    @property
    def imu(self) -> Imu | None: ...
    @property
    def baro(self) -> Baro | None: ...
    @property
    def baro_altitude(self) -> float | None: ...
    @property
    def flight_mode(self) -> str | None: ...  # "HOLD", "OFFBOARD", "POSCTL", "TAKEOFF", "LAND", ...
    @property
    def armed(self) -> bool | None: ...
    @property
    def landed_state(self) -> str | None: ...  # "ON_GROUND", "IN_AIR", "TAKING_OFF", "LANDING", "UNKNOWN"
    @property
    def health(self) -> Any: ...  # the autopilot's health report (mavsdk Health), None before the first
    @property
    def link_ok(self) -> bool: ...
    @property
    def telemetry_age(self) -> float: ...  # s since the last attitude message
    @property
    def offboard_active(self) -> bool: ...
    @property
    def status_text(self) -> str | None: ...  # the autopilot's last words (STATUSTEXT, severe events)
    @property
    def mode_reports(self) -> int: ...  # heartbeats seen: ``wait_mode(after=)`` counts from one
    @property
    def hover_thrust_source(self) -> str: ...  # "autopilot" (MPC_THR_HOVER) or "config"

    async def connect(self, url: str | None = None, timeout: float | None = None) -> None: ...
    async def close(self, timeout: float | None = None) -> None: ...
    def check_link(self) -> None: ...  # raises LinkLost
    async def wait_link_ok(self, timeout: float) -> None: ...
    async def wait_until(self, pred: Callable[[], bool], timeout: float, what: str) -> None: ...
    async def wait_mode(self, mode: str, timeout: float, after: int | None = None) -> None: ...
    async def wait_healthy(self, timeout: float | None = None) -> None: ...
    async def read_param(self, name: str, timeout: float | None = None) -> float: ...
    async def read_param_int(self, name: str, timeout: float | None = None) -> int: ...
    async def failsafe_params(self, timeout: float | None = None) -> dict[str, float | None]: ...
    async def hover_thrust(self, timeout: float | None = None) -> float: ...


class VehicleControl(VehicleTelemetry, Protocol):
    """Commanding the vehicle: everything a flight needs beyond reading it."""

    async def arm(self, timeout: float | None = None) -> None: ...
    async def takeoff(self, altitude_m: float, timeout: float | None = None) -> None: ...
    async def hold(self, timeout: float | None = None) -> None: ...
    async def land(self, timeout: float | None = None) -> None: ...
    async def start_offboard(self, first_setpoint: SetpointLike, timeout: float | None = None) -> None: ...
    async def set_setpoint(self, sp: SetpointLike) -> None: ...
    async def stop_offboard(self, timeout: float | None = None) -> None: ...
    async def wait_landed_and_disarm(self, timeout: float | None = None) -> None: ...


class TruthSource(Protocol):
    """Where the vehicle is, for the flight log, the gate score and the synthetic camera; never control."""

    def latest(self) -> PositionSample | None: ...
    def at(self, t: float) -> TruePose | None: ...  # the state at host time t
    def close(self) -> None: ...
