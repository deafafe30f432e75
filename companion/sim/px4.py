"""A simulated PX4: a MAVLink 2 endpoint (pymavlink) around the quadrotor simulator.

It behaves like PX4 where this app depends on it, so the real ``mavsdk`` library can fly it over
UDP on localhost. Run in-process (``SimPX4``, a context manager with its own thread) or as a
separate process (``python -m companion.sim.px4 --port 0``: prints ``PORT <n>`` on stdout, reads
switch commands from stdin, stops on SIGTERM/SIGINT or ``quit``).

Public API (names are stable; the flight app and its tests rely on them)::

    SimPX4(config=None, *, port=0, remote_port=0, params=None, px4_params=None, initial_state=None,
           initial_mode="HOLD", heartbeat_hz=1.0, telemetry_hz=50.0, noise=True)
    (an initial_state in the air starts armed, holding in initial_mode: HOLD or POSCTL)
    .start() / .stop() / context manager
    .port, .remote_port, .url_for_mavsdk ("udpin://127.0.0.1:REMOTE", as with PX4 SITL on 14540;
    remote_port=None: "udpout://127.0.0.1:PORT", which makes mavsdk bind 0.0.0.0)
    .truth() -> QuadState copy (ground truth, ENU/FLU)
    .mode (str: POSCTL, HOLD, TAKEOFF, LAND, OFFBOARD), .armed, .landed, .time (sim s)
    .events -> list[(t, what)] copy; .wait_event(prefix, timeout, since=-inf) / .wait_for(pred, timeout)
    .param(name) / .set_param(name, value)
    .setpoint_count, .last_setpoint() -> (t, q_xyzw ENU/FLU, thrust), .stats(), .monotonic_of(t_sim)
    switches: .deny_arming, .deny_offboard, .fail_preflight (bool attributes), .drop_link(on), .silence_commands(on),
              .pilot_takeover(mode="POSCTL"), .force_disarm(), .corrupt_attitude(on)
    process stdin (one reply line each): deny_arming 0|1, deny_offboard 0|1, fail_preflight 0|1,
              drop 0|1, silence 0|1,
              takeover MODE, kill, nan_attitude 0|1, param NAME VALUE, state, events, wait_event PREFIX SECONDS, quit

Events (``what`` strings, ``kind:detail``): ``mode:<MODE>:<why>`` (why = command, failsafe,
takeoff_done, pilot, offboard_loss_landed), ``mode_denied:<main>.<sub>``, ``arm``, ``disarm:<why>`` (command,
force, auto_land, auto_preflight, failsafe), ``arm_denied:<why>`` (switch, preflight, in_air, health),
``offboard_denied:<why>`` (no_setpoints, switch), ``failsafe:offboard_loss``, ``takeoff``, ``land``, ``touchdown``,
``command:<id>``, ``silenced:<id>``, ``param_set:<NAME>``, ``link:dropped``, ``link:restored``.

Like PX4 v1.15 SITL (each point checked against the real build in ../shared/px4-sitl, SIH quad):
HEARTBEAT at 1 Hz and nothing extra on a change, so a mode or arming change is seen 0.2-1.0 s after
it happens (``heartbeat_hz`` is a test switch; the default is PX4's); PX4's failsafe defaults
(``COM_OF_LOSS_T`` 1 s, ``COM_OBL_RC_ACT`` 0 = Position mode, ``COM_RC_IN_MODE`` 1, no RC connected:
the offboard-loss fallback reports POSCTL in the heartbeat, descends at ``MPC_LAND_SPEED`` and lands,
auto-disarms, then shows OFFBOARD again and refuses to arm ("Resolve system health failures first")
until another mode is commanded); PX4 *events* (MAVLink EVENT with PX4's own event ids and
arguments, decoded by companion/app/px4events.py) for arming, disarming, take-off, landing,
failsafes and refusals, besides a few STATUSTEXT lines. Like PX4 SITL it sends to a fixed port on
127.0.0.1 (``remote_port``; 0 picks a free one) so mavsdk listens with ``udpin://127.0.0.1:PORT``
(``url_for_mavsdk``) and nothing binds all interfaces; its own socket binds 127.0.0.1 only.

Where it departs from PX4 (on purpose): its own modes (takeoff, hold, position, land) fly a
cascaded P (position) / PI (velocity) controller on ground truth with the true hover thrust (PX4
flies its EKF and a hover-thrust estimate); the attitude estimate, IMU and barometer come from
companion/sim/sensors.py (truth + per-run bias + noise). OFFBOARD needs an attitude setpoint
(SET_ATTITUDE_TARGET) in the last ``COM_OF_LOSS_T``; other setpoint types are ignored. Besides
``remote_port`` it answers whoever sent it a datagram in the last 5 s (MAVSDK heartbeats every
second); a client that stays silent longer is forgotten. No RC: ``NAV_RCL_ACT`` is never triggered.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import select
import signal
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from companion.frames import (
    R_enu_flu_from_ned_frd,
    R_from_quat_wxyz,
    R_ned_frd_from_enu_flu,
    enu_to_ned,
    euler_ned_deg_from_R,
    flu_to_frd,
)
from companion.netports import free_udp_port
from companion.sim.dynamics import G, QuadParams, Quadrotor, QuadState, matrix_to_quat, quat_to_matrix
from companion.sim.sensors import Sensors, Wind

# PX4 custom modes: custom_mode = (sub_mode << 24) | (main_mode << 16).
_MODES: dict[str, tuple[int, int]] = {
    "POSCTL": (3, 0),
    "TAKEOFF": (4, 2),
    "HOLD": (4, 3),
    "LAND": (4, 6),
    "OFFBOARD": (6, 0),
}
_MODE_BY_CODE = {v: k for k, v in _MODES.items()}
_POSITION_MODES = ("POSCTL", "HOLD")

# PX4 v1.15 SITL SIH's values (read from the real build). (value, MAV_PARAM_TYPE).
_REAL32, _INT32 = mavlink.MAV_PARAM_TYPE_REAL32, mavlink.MAV_PARAM_TYPE_INT32
DEFAULT_PX4_PARAMS: dict[str, tuple[float, int]] = {
    "MPC_THR_HOVER": (0.5, _REAL32),  # replaced by the vehicle's true hover thrust unless given
    "COM_OF_LOSS_T": (1.0, _REAL32),
    "COM_OBL_RC_ACT": (0, _INT32),  # 0 Position (no RC: descend and land), 3 Return, 4 Land, 5 Hold, 7 Disarm
    "COM_RC_IN_MODE": (1, _INT32),  # SITL: MAVLink joystick only (none connected here)
    "NAV_RCL_ACT": (2, _INT32),
    "COM_RCL_EXCEPT": (0, _INT32),
    "COM_RC_LOSS_T": (0.5, _REAL32),
    "NAV_DLL_ACT": (0, _INT32),
    "COM_DL_LOSS_T": (10, _INT32),
    "COM_FAIL_ACT_T": (5.0, _REAL32),
    "MIS_TAKEOFF_ALT": (2.5, _REAL32),
    "MPC_TKO_SPEED": (1.5, _REAL32),
    "MPC_LAND_SPEED": (0.7, _REAL32),
    "MPC_LAND_ALT2": (5.0, _REAL32),  # below this, descend at MPC_LAND_SPEED (above: MPC_Z_VEL_MAX_DN)
    "MPC_XY_VEL_MAX": (12.0, _REAL32),
    "MPC_Z_VEL_MAX_UP": (3.0, _REAL32),
    "MPC_Z_VEL_MAX_DN": (1.5, _REAL32),
    "MPC_TILTMAX_AIR": (45.0, _REAL32),
    "MPC_THR_MIN": (0.12, _REAL32),
    "COM_DISARM_LAND": (2.0, _REAL32),
    "COM_DISARM_PRFLT": (10.0, _REAL32),
}

# Home: PX4 SITL's default origin (Zurich); lat/lon from the local position by a flat-earth map.
HOME_LAT, HOME_LON, HOME_ALT = 47.397742, 8.545594, 488.0
_R_EARTH = 6_378_137.0
_P0 = 101_325.0  # Pa at sea level (ISA)

_SENSORS_ALL = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG
    | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mavlink.MAV_SYS_STATUS_SENSOR_GPS
    | mavlink.MAV_SYS_STATUS_AHRS
    | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | mavlink.MAV_SYS_STATUS_PREARM_CHECK
)


def pressure_pa(alt_amsl_m: float) -> float:
    """ISA troposphere pressure at an altitude (the inverse of PX4's baro altitude formula)."""
    return _P0 * (1.0 - 2.25577e-5 * alt_amsl_m) ** 5.25588


# MAVLink EVENT (410) and CURRENT_EVENT_SEQUENCE (411): not in this pymavlink's dialects, packed by hand.
_EVENT_ID, _EVENT_CRC = 410, 160
_EVENT_SEQ_ID, _EVENT_SEQ_CRC = 411, 106
_LOG_INFO, _LOG_WARNING, _LOG_CRITICAL = 6, 4, 2  # external log level (low nibble; PX4 sends it twice)


def _mav2_frame(seq: int, sysid: int, compid: int, msgid: int, crc_extra: int, payload: bytes) -> bytes:
    """One MAVLink 2 frame (trailing zero bytes of the payload cut, as the protocol does)."""
    from pymavlink.generator.mavcrc import x25crc

    body = payload.rstrip(b"\0") or b"\0"
    hdr = struct.pack("<BBBBBBBHB", 0xFD, len(body), 0, 0, seq, sysid, compid, msgid & 0xFFFF, msgid >> 16)
    crc = x25crc(hdr[1:] + body)
    crc.accumulate([crc_extra])
    return hdr + body + struct.pack("<H", crc.crc)


def _nan_to(x: float, default: float) -> float:
    return default if (x is None or not math.isfinite(x)) else float(x)


class _PositionController:
    """PX4-like cascaded controller for the autopilot's own modes: position P -> velocity PI -> accel.

    Output: attitude (xyzw, body FLU -> ENU) and normalised thrust, from ground truth.
    """

    K_POS_XY, K_POS_Z = 0.95, 1.0  # 1/s (PX4 MPC_XY_P, MPC_Z_P)
    K_VEL_XY, K_VEL_Z = 1.8, 4.0  # 1/s (PX4 MPC_XY_VEL_P_ACC, MPC_Z_VEL_P_ACC)
    K_I_XY, K_I_Z = 0.4, 2.0  # 1/s^2 (PX4 MPC_XY_VEL_I_ACC, MPC_Z_VEL_I_ACC): wind, hover-thrust error
    I_MAX = 3.0  # m/s^2, anti-windup

    def __init__(self) -> None:
        self._i = np.zeros(3)

    def command(
        self, s: QuadState, p_ref: np.ndarray, yaw: float, hover_thrust: float, params: Mapping[str, float],
        vz_override: float | None = None, dt: float = 0.0,
    ) -> tuple[np.ndarray, float]:
        v_xy_max = params["MPC_XY_VEL_MAX"]
        v_ref = np.empty(3)
        v_ref[:2] = self.K_POS_XY * (p_ref[:2] - s.p[:2])
        n = float(np.linalg.norm(v_ref[:2]))
        if n > v_xy_max:
            v_ref[:2] *= v_xy_max / n
        if vz_override is not None:
            v_ref[2] = vz_override
        else:
            v_ref[2] = float(np.clip(self.K_POS_Z * (p_ref[2] - s.p[2]),
                                     -params["MPC_Z_VEL_MAX_DN"], params["MPC_Z_VEL_MAX_UP"]))
        e = v_ref - s.v
        if not s.on_ground:
            self._i = np.clip(self._i + dt * e * (self.K_I_XY, self.K_I_XY, self.K_I_Z), -self.I_MAX, self.I_MAX)
        a = np.empty(3)
        a[:2] = self.K_VEL_XY * e[:2] + self._i[:2]
        a[2] = self.K_VEL_Z * e[2] + self._i[2] + G
        a[2] = max(a[2], 0.3 * G)  # never command a free fall
        # Tilt limit: scale the horizontal part so the thrust axis stays within MPC_TILTMAX_AIR.
        max_h = a[2] * math.tan(math.radians(params["MPC_TILTMAX_AIR"]))
        h = float(np.linalg.norm(a[:2]))
        if h > max_h:
            a[:2] *= max_h / h
        # Thrust axis along a, heading kept: body y = z_b x (cos yaw, sin yaw, 0), body x = y_b x z_b.
        # Plain floats: this runs at the physics rate and numpy's cross/scipy cost ~0.4 ms per call here.
        ax, ay, az = float(a[0]), float(a[1]), float(a[2])
        n = math.sqrt(ax * ax + ay * ay + az * az)
        zx, zy, zz = ax / n, ay / n, az / n
        cx, cy = math.cos(yaw), math.sin(yaw)
        yx, yy, yz = -zz * cy, zz * cx, zx * cy - zy * cx
        m = math.sqrt(yx * yx + yy * yy + yz * yz)
        yx, yy, yz = yx / m, yy / m, yz / m
        xx, xy, xz = yy * zz - yz * zy, yz * zx - yx * zz, yx * zy - yy * zx
        q = matrix_to_quat(np.array([[xx, yx, zx], [xy, yy, zy], [xz, yz, zz]]))
        thrust = n * hover_thrust / G
        return q, min(max(thrust, params["MPC_THR_MIN"]), 1.0)


class SimPX4:
    """Simulated PX4 autopilot + quadrotor, real time, own thread; MAVLink 2 over UDP on 127.0.0.1."""

    SYSID, COMPID = 1, 1

    def __init__(
        self,
        config: Any = None,
        *,
        port: int = 0,
        remote_port: int | None = 0,
        params: QuadParams | None = None,
        px4_params: Mapping[str, float] | None = None,
        initial_state: QuadState | None = None,
        initial_mode: str = "HOLD",
        heartbeat_hz: float = 1.0,
        telemetry_hz: float = 50.0,
        noise: bool = True,
    ) -> None:
        if config is None:
            from companion.config import Config

            config = Config()
        self._cfg = config
        self.quad_params = params if params is not None else QuadParams.from_config(config)
        self._quad = Quadrotor(self.quad_params, initial_state)
        # Thread tick: at most 250 Hz (Python's budget); Quadrotor.step substeps to sim.rate inside a tick.
        self._dt = 1.0 / min(float(config.sim.rate), 250.0)
        self._rng = np.random.default_rng(int(config.sim.seed) + 4242)  # own stream: sim's other users
        sens = config.sim.sensors
        if not noise:  # perfect sensors: every noise and bias std zero
            sens = sens.model_copy(update=dict.fromkeys(type(sens).model_fields, 0.0))
        self._sensors = Sensors(sens, self._rng)
        self._wind = Wind(config.sim.wind, self._rng)

        self._params: dict[str, tuple[float, int]] = dict(DEFAULT_PX4_PARAMS)
        self._params["MPC_THR_HOVER"] = (self.quad_params.hover_thrust, _REAL32)
        for name, value in (px4_params or {}).items():
            if name not in self._params:
                raise ValueError(f"SimPX4: unknown PX4 parameter {name!r} (known: {', '.join(self._params)})")
            self._params[name] = (float(value), self._params[name][1])

        self._port_req = int(port)
        # Like PX4 SITL, which sends to 127.0.0.1:14540: a mavsdk that listens (udpin://127.0.0.1) finds it.
        if remote_port is not None and not 0 <= int(remote_port) <= 65535:
            raise ValueError(f"SimPX4: remote_port {remote_port} is not a UDP port (0-65535)")
        self._remote_req = remote_port
        self._remote: tuple[str, int] | None = None
        self._heartbeat_dt = 1.0 / heartbeat_hz
        self._default_rates = {
            mavlink.MAVLINK_MSG_ID_HEARTBEAT: self._heartbeat_dt,
            mavlink.MAVLINK_MSG_ID_SYS_STATUS: 0.2,
            mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 0.2,
            mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 1.0 / telemetry_hz,
            mavlink.MAVLINK_MSG_ID_ATTITUDE: 1.0 / telemetry_hz,
            mavlink.MAVLINK_MSG_ID_HIGHRES_IMU: 1.0 / telemetry_hz,
            mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 1.0 / telemetry_hz,
            mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION: 1.0 / telemetry_hz,
            mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 0.1,
            mavlink.MAVLINK_MSG_ID_ALTITUDE: 0.05,
            mavlink.MAVLINK_MSG_ID_HOME_POSITION: 2.0,
        }
        self._rates: dict[int, float] = dict(self._default_rates)  # msg id -> interval s (0 = off)
        self._next_send: dict[int, float] = dict.fromkeys(self._rates, 0.0)

        self._lock = threading.RLock()
        self._cond = threading.Condition(self._lock)
        self._events: list[tuple[float, str]] = []
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._sock: socket.socket | None = None
        self._peers: dict[tuple[str, int], float] = {}
        self._mav = mavlink.MAVLink(None, srcSystem=self.SYSID, srcComponent=self.COMPID)
        self._mav.robust_parsing = True

        # Autopilot state (under _lock).
        self._t = 0.0
        self._mode = "HOLD"
        self._armed = False
        self._armed_at = 0.0
        self._was_airborne = False
        self._landed_since: float | None = None
        self._sp_q_enu_flu: np.ndarray | None = None
        self._sp_thrust = 0.0
        self._sp_time = -math.inf
        self._sp_count = 0
        s = self._quad.state
        self._hold_p = np.array(s.p, float)
        self._hold_yaw = self._yaw_of(s.q)
        self._takeoff_alt = 0.0
        if initial_mode not in _POSITION_MODES:
            raise ValueError(f"SimPX4: initial_mode must be one of {', '.join(_POSITION_MODES)} (got {initial_mode!r})")
        self._mode = initial_mode
        if not s.on_ground:  # a scenario that starts in the air starts armed and flying (else it would drop)
            self._armed = True
            self._was_airborne = True
        self._pos_ctrl = _PositionController()
        self._dropped = False
        self._silenced = False
        self.deny_arming = False
        self.deny_offboard = False
        self.fail_preflight = False  # SYS_STATUS reports the preflight checks failed; arming is refused
        self._obl_landed = False  # landed and disarmed by the offboard-loss fallback: refuses to arm (PX4 1.15)
        self._nan_attitude = False
        self._was_tko_detected = False
        self._obl_fallback = False  # flying the no-RC offboard-loss fallback (descend and land, shown as POSCTL)
        self._event_seq = 0
        self._events_meta: Any = None
        self.overruns = 0  # physics steps skipped because the thread fell behind real time
        self._busy = 0.0  # s of CPU-bound work in the sim thread (for stats())
        self._t0_mono = math.nan
        self._sp_rx_mono = math.nan

    # ---------------------------------------------------------------------------------- lifecycle
    def start(self) -> SimPX4:
        if self._thread is not None:
            return self
        if not 0 <= self._port_req <= 65535:
            raise ValueError(f"SimPX4: port {self._port_req} is not a UDP port (0-65535)")
        if self._remote_req is not None:
            port = int(self._remote_req) or free_udp_port()
            self._remote = ("127.0.0.1", port)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        # No SO_REUSEADDR: the port is ours alone (MAVSDK's udpin listeners set it and could share).
        sock.bind(("127.0.0.1", self._port_req))
        sock.setblocking(False)
        self._sock = sock
        self._stop.clear()
        if self._remote is not None:
            self._peers[self._remote] = math.inf  # always sent to, never forgotten
        self._thread = threading.Thread(target=self._run, name=f"SimPX4:{self.port}", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> SimPX4:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def port(self) -> int:
        if self._sock is None:
            raise RuntimeError("SimPX4.port: not started")
        return self._sock.getsockname()[1]

    @property
    def remote_port(self) -> int | None:
        """The port on 127.0.0.1 the sim sends to (mavsdk listens there), None without one."""
        return None if self._remote is None else self._remote[1]

    @property
    def url_for_mavsdk(self) -> str:
        if self._remote is not None:
            return f"udpin://127.0.0.1:{self._remote[1]}"
        return f"udpout://127.0.0.1:{self.port}"

    # ------------------------------------------------------------------------------- observation
    def truth(self) -> QuadState:
        with self._lock:
            return copy.deepcopy(self._quad.state)

    @property
    def mode(self) -> str:
        with self._lock:
            return self._mode

    @property
    def armed(self) -> bool:
        with self._lock:
            return self._armed

    @property
    def landed(self) -> bool:
        with self._lock:
            return self._quad.state.on_ground

    @property
    def time(self) -> float:
        with self._lock:
            return self._t

    @property
    def events(self) -> list[tuple[float, str]]:
        with self._lock:
            return list(self._events)

    @property
    def setpoint_count(self) -> int:
        """Attitude setpoints received so far."""
        with self._lock:
            return self._sp_count

    def last_setpoint(self) -> tuple[float, np.ndarray | None, float]:
        """(sim time received, commanded attitude xyzw body FLU -> ENU, normalised thrust)."""
        with self._lock:
            q = None if self._sp_q_enu_flu is None else self._sp_q_enu_flu.copy()
            return self._sp_time, q, self._sp_thrust

    def stats(self) -> dict[str, float]:
        """Load of the sim thread: wall and sim time, busy fraction, skipped physics steps."""
        with self._lock:
            wall = time.monotonic() - self._t0_mono if math.isfinite(self._t0_mono) else 0.0
            return {"wall_s": wall, "sim_s": self._t, "busy_fraction": self._busy / wall if wall > 0 else 0.0,
                    "overruns": float(self.overruns), "physics_hz": 1.0 / self._dt}

    def monotonic_of(self, t_sim: float) -> float:
        """time.monotonic() at which the sim clock read ``t_sim`` (same host: for latency measurements)."""
        return self._t0_mono + t_sim

    def last_setpoint_rx_monotonic(self) -> float:
        """time.monotonic() when the last attitude setpoint arrived (NaN before the first)."""
        with self._lock:
            return self._sp_rx_mono

    def wait_for(self, predicate: Callable[[], bool], timeout: float) -> bool:
        """Block until predicate() (evaluated under the sim's lock after each physics tick) or timeout."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while not predicate():
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(min(left, 0.05))
        return True

    def wait_event(self, prefix: str, timeout: float, since: float = -math.inf) -> tuple[float, str] | None:
        """The first event at or after ``since`` whose text starts with ``prefix``, or None at timeout."""
        found: list[tuple[float, str]] = []

        def pred() -> bool:
            for ev in self._events:
                if ev[0] >= since and ev[1].startswith(prefix):
                    found.append(ev)
                    return True
            return False

        return found[0] if self.wait_for(pred, timeout) else None

    def param(self, name: str) -> float:
        with self._lock:
            return self._params[name][0]

    def set_param(self, name: str, value: float) -> None:
        with self._lock:
            if name not in self._params:
                raise KeyError(f"SimPX4: unknown PX4 parameter {name!r}")
            self._params[name] = (float(value), self._params[name][1])

    # ------------------------------------------------------------------------------------ switches
    def drop_link(self, on: bool) -> None:
        """On: every datagram in either direction is lost (radio out of range)."""
        with self._lock:
            if on != self._dropped:
                self._dropped = on
                self._event("link:dropped" if on else "link:restored")

    def silence_commands(self, on: bool) -> None:
        """On: COMMAND_LONG/COMMAND_INT are received but neither executed nor acknowledged."""
        with self._lock:
            self._silenced = on

    def corrupt_attitude(self, on: bool) -> None:
        """On: ATTITUDE_QUATERNION carries NaN (an estimator failure, or a corrupted link)."""
        with self._lock:
            self._nan_attitude = on

    def force_disarm(self) -> None:
        """The kill switch (or a forced disarm from a ground station): motors off wherever the vehicle is."""
        with self._lock:
            if self._armed:
                self._disarm("force")

    def pilot_takeover(self, mode: str = "POSCTL") -> None:
        """The pilot flips the mode switch: PX4 leaves OFFBOARD and holds position (POSCTL/HOLD) or lands."""
        if mode not in ("POSCTL", "HOLD", "LAND"):
            raise ValueError(f"SimPX4.pilot_takeover: mode must be POSCTL, HOLD or LAND (got {mode!r})")
        with self._lock:
            self._set_mode(mode, "pilot")

    # --------------------------------------------------------------------------- internal: state
    def _event(self, what: str) -> None:
        self._events.append((self._t, what))
        self._cond.notify_all()

    @staticmethod
    def _yaw_of(q_xyzw: np.ndarray) -> float:
        R = quat_to_matrix(q_xyzw)
        return math.atan2(R[1, 0], R[0, 0])  # heading of body x in ENU

    def _p(self, name: str) -> float:
        return self._params[name][0]

    def _set_mode(self, mode: str, why: str) -> None:
        if mode == self._mode:
            return
        s = self._quad.state
        if mode in _POSITION_MODES or mode == "LAND":
            self._hold_p = np.array(s.p, float)
            self._hold_yaw = self._yaw_of(s.q)
        self._mode = mode
        self._event(f"mode:{mode}:{why}")
        if why in ("command", "pilot"):
            self._obl_landed = False  # another mode set: PX4's checks pass again
        # No heartbeat here: like PX4, the change shows at the next 1 Hz tick.

    def _arm(self) -> None:
        self._armed = True
        self._armed_at = self._t
        self._pos_ctrl = _PositionController()  # no integrator left over from the last flight
        self._was_airborne = False
        self._was_tko_detected = False
        self._landed_since = None
        self._event("arm")
        self._px4_event("commander_armed_by", _LOG_INFO, 4)  # external command

    def _disarm(self, why: str) -> None:
        self._armed = False
        self._event(f"disarm:{why}")
        reason = {"auto_land": 6, "auto_preflight": 7, "failsafe": 14}.get(why, 4)
        self._px4_event("commander_disarmed_by", _LOG_INFO, reason)
        if self._mode == "POSCTL" and self._obl_fallback:
            # PX4 1.15 after the offboard-loss landing: shows the user's mode (Offboard) again, refuses to arm.
            self._obl_fallback = False
            self._obl_landed = True
            self._mode = "OFFBOARD"
            self._event("mode:OFFBOARD:offboard_loss_landed")

    def _px4_event(self, name: str, level: int, *args: float) -> None:
        """A PX4 event with PX4's own id and argument layout (from the event metadata the app decodes)."""
        if self._events_meta is None:
            from companion.app.px4events import EventDecoder

            self._events_meta = EventDecoder.load()
        eid = self._events_meta.event_id(name)
        packed = self._events_meta.encode_args(name, *args).ljust(40, b"\0")
        self._event_seq = (self._event_seq + 1) % 65536
        payload = struct.pack("<IIHBBB", eid, int(self._t * 1000), self._event_seq, 0, 0,
                              (level << 4) | level) + packed
        self._send_raw(_mav2_frame(self._mav.seq, self.SYSID, self.COMPID, _EVENT_ID, _EVENT_CRC, payload))

    def _offboard_signal_ok(self) -> bool:
        return self._t - self._sp_time <= self._p("COM_OF_LOSS_T")

    # ------------------------------------------------------------------------------ thread loop
    def _run(self) -> None:
        t0 = self._t0_mono = time.monotonic()
        steps = 0
        assert self._sock is not None
        sock = self._sock
        while not self._stop.is_set():
            now = time.monotonic() - t0
            due = int(now / self._dt)
            if due - steps > 50:  # fell far behind (machine busy): skip rather than spiral
                self.overruns += due - steps - 1
                steps = due - 1
            busy0 = time.perf_counter()
            with self._lock:
                while steps < due:
                    self._physics_step()
                    steps += 1
                self._send_telemetry()
                self._cond.notify_all()
            busy1 = time.perf_counter()
            wait = (steps + 1) * self._dt - (time.monotonic() - t0)
            try:
                ready, _, _ = select.select([sock], [], [], max(0.0, wait))
            except (OSError, ValueError):
                break
            busy2 = time.perf_counter()
            if ready:
                self._receive_all(sock)
            self._busy += (busy1 - busy0) + (time.perf_counter() - busy2)

    def _receive_all(self, sock: socket.socket) -> None:
        for _ in range(256):
            try:
                data, addr = sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            with self._lock:
                if self._dropped:
                    continue
                self._peers[addr] = self._t
                try:
                    msgs = self._mav.parse_buffer(data) or []
                except mavlink.MAVError:
                    continue
                for m in msgs:
                    self._handle(m, addr)

    # ---------------------------------------------------------------------------- physics + FSM
    def _physics_step(self) -> None:
        q_cmd, thrust = self._control()
        self._quad.step(self._dt, q_cmd, thrust, self._wind.step(self._dt))
        self._t += self._dt
        self._supervise()

    def _control(self) -> tuple[np.ndarray, float]:
        s = self._quad.state
        if not self._armed:
            return self._level_q(self._yaw_of(s.q)), 0.0
        mode = self._mode
        if mode == "OFFBOARD" and self._sp_q_enu_flu is not None:
            return self._sp_q_enu_flu, self._sp_thrust
        hover = self.quad_params.hover_thrust  # the converged hover-thrust estimate of a real PX4
        if s.on_ground and mode in ("HOLD", "POSCTL", "LAND"):
            return self._level_q(self._hold_yaw), self._p("MPC_THR_MIN")  # idle on the ground
        if mode == "TAKEOFF":
            ref = np.array([self._hold_p[0], self._hold_p[1], self._takeoff_alt])
            vz = min(self._pos_ctrl.K_POS_Z * (self._takeoff_alt - s.p[2]), self._p("MPC_TKO_SPEED"))
            return self._pos_ctrl.command(s, ref, self._hold_yaw, hover, self._param_values(), vz, self._dt)
        if mode == "LAND" or (mode == "POSCTL" and self._obl_fallback):
            ref = np.array([self._hold_p[0], self._hold_p[1], 0.0])
            slow = s.p[2] <= self._p("MPC_LAND_ALT2")
            vz = -self._p("MPC_LAND_SPEED") if slow else -self._p("MPC_Z_VEL_MAX_DN")
            return self._pos_ctrl.command(s, ref, self._hold_yaw, hover, self._param_values(), vz, self._dt)
        return self._pos_ctrl.command(s, self._hold_p, self._hold_yaw, hover, self._param_values(), None, self._dt)

    def _param_values(self) -> dict[str, float]:
        return {k: v[0] for k, v in self._params.items()}

    @staticmethod
    def _level_q(yaw: float) -> np.ndarray:
        return np.array([0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw)])

    def _supervise(self) -> None:
        """PX4's commander: failsafes, takeoff completion, landing detection, auto-disarm."""
        s = self._quad.state
        if self._armed and not s.on_ground:
            if not self._was_airborne:
                self._was_airborne = True
            self._landed_since = None
        if self._mode == "OFFBOARD" and self._armed and not self._offboard_signal_ok():
            self._event("failsafe:offboard_loss")
            act = int(self._p("COM_OBL_RC_ACT"))
            if act in (0, 1, 2):  # a manual-control mode, but no RC here: PX4 descends and lands
                self._set_mode("POSCTL", "failsafe")
                self._obl_fallback = True
                self._px4_event("commander_failsafe_enter_generic", _LOG_CRITICAL, 0, 2 + act)
            elif act in (6, 7):
                self._set_mode("HOLD", "failsafe")
                self._px4_event("commander_failsafe_enter_generic", _LOG_CRITICAL, 0, 10 if act == 6 else 9)
                self._disarm("failsafe")
            else:
                self._set_mode({3: "LAND", 4: "LAND"}.get(act, "HOLD"), "failsafe")
                self._px4_event("commander_failsafe_enter_generic", _LOG_CRITICAL, 0, {3: 6, 4: 7}.get(act, 5))
        if self._mode == "TAKEOFF" and self._armed and not s.on_ground and not self._was_tko_detected:
            self._was_tko_detected = True
            self._px4_event("commander_takeoff_detected", _LOG_INFO)
        if self._mode == "TAKEOFF" and s.p[2] >= self._takeoff_alt - 0.1:
            self._set_mode("HOLD", "takeoff_done")
            self._hold_p[2] = self._takeoff_alt  # PX4 loiters at the take-off altitude, not where it switched
        if self._armed and s.on_ground:
            if self._landed_since is None:
                self._landed_since = self._t
                if self._was_airborne:
                    self._event("touchdown")
                    self._px4_event("commander_landing_detected", _LOG_INFO)
            if self._was_airborne and self._t - self._landed_since >= self._p("COM_DISARM_LAND"):
                self._disarm("auto_land")
            elif not self._was_airborne and self._t - self._armed_at >= self._p("COM_DISARM_PRFLT"):
                self._disarm("auto_preflight")

    # --------------------------------------------------------------------------- MAVLink input
    def _handle(self, m: Any, addr: tuple[str, int]) -> None:
        mid = m.get_msgId()
        if mid == mavlink.MAVLINK_MSG_ID_COMMAND_LONG:
            if m.target_system in (0, self.SYSID):
                self._command(m.command, [m.param1, m.param2, m.param3, m.param4, m.param5, m.param6,
                                          m.param7], m.get_srcSystem(), m.get_srcComponent())
        elif mid == mavlink.MAVLINK_MSG_ID_COMMAND_INT:
            if m.target_system in (0, self.SYSID):
                self._command(m.command, [m.param1, m.param2, m.param3, m.param4, m.x, m.y, m.z],
                              m.get_srcSystem(), m.get_srcComponent())
        elif mid == mavlink.MAVLINK_MSG_ID_SET_ATTITUDE_TARGET:
            if m.target_system in (0, self.SYSID):
                self._attitude_setpoint(m)
        elif mid == mavlink.MAVLINK_MSG_ID_PARAM_REQUEST_READ:
            if m.target_system in (0, self.SYSID):
                self._param_read(m.param_id, m.param_index)
        elif mid == mavlink.MAVLINK_MSG_ID_PARAM_REQUEST_LIST:
            if m.target_system in (0, self.SYSID):
                for i in range(len(self._params)):
                    self._param_read("", i)
        elif mid == mavlink.MAVLINK_MSG_ID_PARAM_SET and m.target_system in (0, self.SYSID):
            self._param_set(m.param_id, m.param_value, m.param_type)

    def _attitude_setpoint(self, m: Any) -> None:
        mask = m.type_mask
        ignore = mavlink.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE | mavlink.ATTITUDE_TARGET_TYPEMASK_THROTTLE_IGNORE
        if mask & ignore:
            return  # rate setpoints / missing thrust: not a setpoint this sim flies
        q = np.asarray(m.q, float)
        if not np.all(np.isfinite(q)) or np.linalg.norm(q) < 0.5 or not math.isfinite(m.thrust):
            return
        R_enu_flu = R_enu_flu_from_ned_frd(R_from_quat_wxyz(q))
        self._sp_q_enu_flu = matrix_to_quat(R_enu_flu)
        self._sp_thrust = min(max(float(m.thrust), 0.0), 1.0)
        self._sp_time = self._t
        self._sp_rx_mono = time.monotonic()
        self._sp_count += 1

    def _ack(self, command: int, result: int, sysid: int, compid: int) -> None:
        self._send(self._mav.command_ack_encode(command, result, 0, 0, sysid, compid))

    def _command(self, cmd: int, p: list[float], sysid: int, compid: int) -> None:
        if self._silenced:
            self._event(f"silenced:{cmd}")
            return
        self._event(f"command:{cmd}")
        res = self._execute(cmd, p)
        self._ack(cmd, res, sysid, compid)

    def _execute(self, cmd: int, p: list[float]) -> int:
        ok, denied = mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_DENIED
        s = self._quad.state
        if cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            force = _nan_to(p[1], 0.0) == 21196.0
            if _nan_to(p[0], 0.0) >= 0.5:
                if self._armed:
                    return ok
                if self.fail_preflight or self._obl_landed:
                    self._event("arm_denied:health" if self._obl_landed else "arm_denied:preflight")
                    self._px4_event("commander_arm_denied_resolve_failures", _LOG_CRITICAL)  # no STATUSTEXT (PX4)
                    return denied
                if self.deny_arming:
                    self._event("arm_denied:switch")
                    self._statustext("Arming denied: preflight checks failed (simulated)")
                    return denied
                if not s.on_ground and not force:
                    self._event("arm_denied:in_air")
                    return denied
                self._arm()
                return ok
            if not self._armed:
                return ok
            if not s.on_ground and not force:
                self._px4_event("commander_disarm_denied_not_landed", _LOG_CRITICAL)
                return denied
            self._disarm("force" if force else "command")
            return ok
        if cmd == mavlink.MAV_CMD_DO_SET_MODE:
            code = (int(_nan_to(p[1], 0.0)), int(_nan_to(p[2], 0.0)))
            mode = _MODE_BY_CODE.get(code)
            if mode is None and code[0] == 4 and code[1] == 0:
                mode = "HOLD"  # AUTO without a sub mode: PX4 picks its default (loiter here)
            if mode is None:
                self._event(f"mode_denied:{code[0]}.{code[1]}")
                return mavlink.MAV_RESULT_UNSUPPORTED
            return self._request_mode(mode)
        if cmd == mavlink.MAV_CMD_NAV_TAKEOFF:
            if not self._armed:
                self._statustext("Takeoff denied: disarmed")
                return denied
            alt_amsl = _nan_to(p[6], math.nan)
            rel = alt_amsl - HOME_ALT if math.isfinite(alt_amsl) else self._p("MIS_TAKEOFF_ALT")
            self._takeoff_alt = max(rel, 0.5)
            self._event("takeoff")
            self._set_mode("TAKEOFF", "command")
            return ok
        if cmd == mavlink.MAV_CMD_NAV_LAND:
            self._event("land")
            self._px4_event("commander_landing_current_pos", _LOG_INFO)
            return self._request_mode("LAND")
        if cmd == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            msg_id, interval = int(_nan_to(p[0], -1)), _nan_to(p[1], 0.0)
            if msg_id not in self._default_rates:
                return mavlink.MAV_RESULT_UNSUPPORTED
            if interval < 0:
                self._rates[msg_id] = 0.0
            elif interval == 0:
                self._rates[msg_id] = self._default_rates[msg_id]
            else:
                self._rates[msg_id] = max(interval * 1e-6, 0.002)
            self._next_send[msg_id] = self._t
            return ok
        if cmd == mavlink.MAV_CMD_REQUEST_MESSAGE:
            msg_id = int(_nan_to(p[0], -1))
            if msg_id == mavlink.MAVLINK_MSG_ID_HOME_POSITION:
                self._send_home()
                return ok
            if msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
                self._send_autopilot_version()
                return ok
            if msg_id in self._default_rates:
                self._next_send[msg_id] = self._t  # one now
                return ok
            return mavlink.MAV_RESULT_UNSUPPORTED
        if cmd == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self._send_autopilot_version()
            return ok
        return mavlink.MAV_RESULT_UNSUPPORTED

    def _request_mode(self, mode: str) -> int:
        s = self._quad.state
        if mode == "OFFBOARD":
            if self.deny_offboard:
                self._event("offboard_denied:switch")
                return mavlink.MAV_RESULT_DENIED
            if not self._offboard_signal_ok():
                self._event("offboard_denied:no_setpoints")
                self._statustext("Switching to Offboard is currently not available: no setpoints")
                return mavlink.MAV_RESULT_DENIED
        if mode == "TAKEOFF":
            if not self._armed:
                return mavlink.MAV_RESULT_DENIED
            self._takeoff_alt = self._p("MIS_TAKEOFF_ALT")
        if mode == "LAND" and s.on_ground and not self._armed:
            pass  # PX4 accepts LAND on the ground; nothing to do
        self._set_mode(mode, "command")
        return mavlink.MAV_RESULT_ACCEPTED

    def _param_read(self, name: str, index: int) -> None:
        names = list(self._params)
        if index is not None and 0 <= index < len(names) and not name:
            name = names[index]
        if name not in self._params:
            return  # PX4 stays silent on unknown names; MAVSDK times out
        self._send_param(name)

    def _param_set(self, name: str, raw: float, ptype: int) -> None:
        if name not in self._params:
            return
        own_type = self._params[name][1]
        if own_type == _INT32:
            raw = struct.unpack("<i", struct.pack("<f", raw))[0]  # PX4 encodes ints bytewise
        self._params[name] = (float(raw), own_type)
        self._event(f"param_set:{name}")
        self._send_param(name)

    def _send_param(self, name: str) -> None:
        names = list(self._params)
        value, ptype = self._params[name]
        wire = struct.unpack("<f", struct.pack("<i", int(value)))[0] if ptype == _INT32 else float(value)
        self._send(self._mav.param_value_encode(name.encode(), wire, ptype, len(names), names.index(name)))

    # -------------------------------------------------------------------------- MAVLink output
    def _send(self, msg: Any) -> None:
        if self._dropped or self._sock is None or not self._peers:
            return
        self._send_raw(msg.pack(self._mav))

    def _send_raw(self, buf: bytes) -> None:
        if self._dropped or self._sock is None or not self._peers:
            return
        self._mav.seq = (self._mav.seq + 1) % 256
        for addr in list(self._peers):
            try:
                self._sock.sendto(buf, addr)
            except OSError:
                if addr != self._remote:  # the fixed port may simply have no listener yet
                    self._peers.pop(addr, None)

    def _statustext(self, text: str, severity: int = mavlink.MAV_SEVERITY_WARNING) -> None:
        self._send(self._mav.statustext_encode(severity, text.encode()[:50]))

    def _send_heartbeat(self) -> None:
        main, sub = _MODES[self._mode]
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self._armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        state = mavlink.MAV_STATE_ACTIVE if self._armed else mavlink.MAV_STATE_STANDBY
        self._send(self._mav.heartbeat_encode(
            mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base, (sub << 24) | (main << 16), state, 3))

    def _send_home(self) -> None:
        self._send(self._mav.home_position_encode(
            int(HOME_LAT * 1e7), int(HOME_LON * 1e7), int(HOME_ALT * 1000), 0.0, 0.0, 0.0,
            [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, int(self._t * 1e6)))

    def _send_autopilot_version(self) -> None:
        caps = (mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
                | mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT)
        self._send(self._mav.autopilot_version_encode(
            caps, (1 << 24) | (15 << 16) | (0 << 8) | 255, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0))

    def _landed_state(self) -> int:
        s = self._quad.state
        if s.on_ground:
            return mavlink.MAV_LANDED_STATE_ON_GROUND
        if self._mode == "TAKEOFF":
            return mavlink.MAV_LANDED_STATE_TAKEOFF
        if self._mode == "LAND":
            return mavlink.MAV_LANDED_STATE_LANDING
        return mavlink.MAV_LANDED_STATE_IN_AIR

    def _latlon(self, p_enu: np.ndarray) -> tuple[int, int, float]:
        lat = HOME_LAT + math.degrees(p_enu[1] / _R_EARTH)
        lon = HOME_LON + math.degrees(p_enu[0] / (_R_EARTH * math.cos(math.radians(HOME_LAT))))
        return round(lat * 1e7), round(lon * 1e7), HOME_ALT + float(p_enu[2])

    def _send_telemetry(self) -> None:
        if self._dropped or not self._peers:
            return
        # Forget clients silent for 5 s (MAVSDK sends a heartbeat every second): no sends to dead ports.
        for addr, t_heard in list(self._peers.items()):
            if self._t - t_heard > 5.0 and addr != self._remote:
                del self._peers[addr]
        t = self._t
        due = [mid for mid, iv in self._rates.items() if iv > 0 and t >= self._next_send.get(mid, 0.0)]
        if not due:
            return
        for mid in due:
            self._next_send[mid] = max(self._next_send.get(mid, 0.0) + self._rates[mid], t)
        s = self._quad.state
        ms = int(t * 1000)
        R_true = quat_to_matrix(s.q)
        fast = {mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, mavlink.MAVLINK_MSG_ID_ATTITUDE}
        if fast.intersection(due):
            # PX4's attitude estimate: truth with a per-run bias and white noise (companion/sim/sensors.py).
            wq = self._sensors.attitude_wxyz_ned_frd(s.q)
            rates = flu_to_frd(s.omega)
            if mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION in due:
                q_out = (math.nan, math.nan, math.nan, math.nan) if self._nan_attitude else wq
                self._send(self._mav.attitude_quaternion_encode(ms, *q_out, *rates, [0.0, 0.0, 0.0, 0.0]))
            if mavlink.MAVLINK_MSG_ID_ATTITUDE in due:
                roll, pitch, yaw = (math.radians(a) for a in euler_ned_deg_from_R(R_from_quat_wxyz(wq)))
                self._send(self._mav.attitude_encode(ms, roll, pitch, yaw, *rates))
        alt_amsl = HOME_ALT + float(s.p[2])
        baro_alt = HOME_ALT + self._sensors.baro_altitude(float(s.p[2]))
        if mavlink.MAVLINK_MSG_ID_HIGHRES_IMU in due:
            imu = self._sensors.imu(self._quad.specific_force_body(), s.omega)
            acc, gyro = flu_to_frd(imu.accel), flu_to_frd(imu.gyro)
            self._send(self._mav.highres_imu_encode(
                int(t * 1e6), *acc, *gyro, 0.21, 0.0, 0.42, pressure_pa(baro_alt) / 100.0, 0.0,
                baro_alt, 25.0, 0x1FFF, 0))
        p_ned, v_ned = enu_to_ned(s.p), enu_to_ned(s.v)
        if mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED in due:
            self._send(self._mav.local_position_ned_encode(ms, *p_ned, *v_ned))
        if mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION in due:
            lat, lon, alt = self._latlon(s.p)
            x, y, z, w = matrix_to_quat(R_ned_frd_from_enu_flu(R_true))
            a_ned = enu_to_ned(self._quad.acceleration_world())
            cm = [int(np.clip(round(c * 100), -32767, 32767)) for c in v_ned]
            mg = [int(np.clip(round(c / G * 1000), -32767, 32767)) for c in a_ned]
            self._send(self._mav.hil_state_quaternion_encode(
                int(t * 1e6), [w, x, y, z], *flu_to_frd(s.omega), lat, lon, int(alt * 1000), *cm, 0, 0, *mg))
        if mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT in due:
            lat, lon, alt = self._latlon(s.p)
            yaw_ned = math.degrees(math.atan2(R_true[0, 0], R_true[1, 0])) % 360.0  # heading from north
            cm = [int(np.clip(round(c * 100), -32767, 32767)) for c in v_ned]
            self._send(self._mav.global_position_int_encode(
                ms, lat, lon, int(alt * 1000), int(s.p[2] * 1000), *cm, int(yaw_ned * 100) % 36000))
        if mavlink.MAVLINK_MSG_ID_ALTITUDE in due:
            # PX4: altitude_monotonic is the barometric altitude; the others come from the EKF (truth here).
            self._send(self._mav.altitude_encode(
                int(t * 1e6), baro_alt, alt_amsl, float(s.p[2]), float(s.p[2]), math.nan, float(s.p[2])))
        if mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE in due:
            self._send(self._mav.extended_sys_state_encode(mavlink.MAV_VTOL_STATE_UNDEFINED, self._landed_state()))
        if mavlink.MAVLINK_MSG_ID_SYS_STATUS in due:
            failing = self.fail_preflight or self._obl_landed
            health = _SENSORS_ALL & ~mavlink.MAV_SYS_STATUS_PREARM_CHECK if failing else _SENSORS_ALL
            self._send(self._mav.sys_status_encode(
                _SENSORS_ALL, _SENSORS_ALL, health, 200, 16200, 1000, 90, 0, 0, 0, 0, 0, 0, 0, 0, 0))
        if mavlink.MAVLINK_MSG_ID_HOME_POSITION in due:
            self._send_home()
        if mavlink.MAVLINK_MSG_ID_HEARTBEAT in due:
            self._send_heartbeat()


# ------------------------------------------------------------------------------ process entry point
_SWITCH_HELP = (
    "stdin commands: deny_arming 0|1, deny_offboard 0|1, fail_preflight 0|1, drop 0|1, silence 0|1, "
    "takeover [POSCTL|HOLD|LAND], kill, nan_attitude 0|1, param NAME VALUE, state, events, "
    "wait_event PREFIX SECONDS, quit"
)


def _stdin_command(sim: SimPX4, line: str) -> str:
    parts = line.split()
    if not parts:
        return ""
    cmd, args = parts[0], parts[1:]
    try:
        if cmd == "deny_arming":
            sim.deny_arming = args[0] == "1"
        elif cmd == "deny_offboard":
            sim.deny_offboard = args[0] == "1"
        elif cmd == "fail_preflight":
            sim.fail_preflight = args[0] == "1"
        elif cmd == "drop":
            sim.drop_link(args[0] == "1")
        elif cmd == "silence":
            sim.silence_commands(args[0] == "1")
        elif cmd == "nan_attitude":
            sim.corrupt_attitude(args[0] == "1")
        elif cmd == "kill":
            sim.force_disarm()
        elif cmd == "takeover":
            sim.pilot_takeover(args[0] if args else "POSCTL")
        elif cmd == "param":
            sim.set_param(args[0], float(args[1]))
        elif cmd == "state":
            s = sim.truth()
            return (f"STATE t={sim.time:.3f} mode={sim.mode} armed={int(sim.armed)} "
                    f"p={s.p[0]:.3f},{s.p[1]:.3f},{s.p[2]:.3f} v={s.v[0]:.3f},{s.v[1]:.3f},{s.v[2]:.3f}")
        elif cmd == "events":
            return "EVENTS " + json.dumps([[round(t, 4), what] for t, what in sim.events])
        elif cmd == "wait_event":
            ev = sim.wait_event(args[0], float(args[1]))
            return "TIMEOUT" if ev is None else f"EVENT {ev[0]:.4f} {ev[1]}"
        elif cmd == "quit":
            return "BYE"
        else:
            return f"ERROR unknown command {cmd!r} ({_SWITCH_HELP})"
    except (IndexError, ValueError, KeyError) as e:
        return f"ERROR {line.strip()!r}: {e}"
    return "OK"


def main(argv: list[str] | None = None) -> int:
    from companion.config import add_config_arguments, config_from_args
    from companion.configbase import ConfigError

    ap = argparse.ArgumentParser(
        prog="python -m companion.sim.px4",
        description="Simulated PX4 on 127.0.0.1 (MAVLink 2/UDP). Prints 'PORT <n>'; " + _SWITCH_HELP,
    )
    ap.add_argument("--port", type=int, default=0, help="UDP port on 127.0.0.1 (0: a free one)")
    ap.add_argument("--remote-port", type=int, default=0, metavar="PORT",
                    help="send to 127.0.0.1:PORT, where mavsdk listens with udpin:// (PX4 SITL uses 14540; "
                         "0: a free one, printed as 'REMOTE <n>')")
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                    help="PX4 parameter, e.g. --param MPC_THR_HOVER=0.42 (repeatable)")
    ap.add_argument("--no-noise", action="store_true", help="perfect sensors")
    add_config_arguments(ap)
    args = ap.parse_args(argv)
    for opt, port in (("--port", args.port), ("--remote-port", args.remote_port)):
        if port is not None and not 0 <= port <= 65535:
            print(f"companion.sim.px4: {opt} {port}: not a UDP port (0..65535)", file=sys.stderr)
            return 2
    try:
        cfg = config_from_args(args)
        px4_params = {}
        for item in args.param:
            name, _, value = item.partition("=")
            try:
                px4_params[name.strip()] = float(value)
            except ValueError:
                raise ConfigError(f"--param {item!r}: expected NAME=NUMBER") from None
        sim = SimPX4(cfg, port=args.port, remote_port=args.remote_port, px4_params=px4_params,
                     noise=not args.no_noise)
    except (ConfigError, ValueError) as e:
        print(f"companion.sim.px4: {e}", file=sys.stderr)
        return 2
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    try:
        sim.start()
    except OSError as e:
        print(f"companion.sim.px4: cannot bind 127.0.0.1:{args.port} ({e.strerror})", file=sys.stderr)
        return 1
    print(f"PORT {sim.port} REMOTE {sim.remote_port}", flush=True)

    def read_stdin() -> None:
        for line in sys.stdin:  # EOF (e.g. stdin is /dev/null) only ends the reader, not the sim
            reply = _stdin_command(sim, line)
            if reply:
                print(reply, flush=True)
            if reply == "BYE":
                stop.set()
                return

    if sys.stdin is not None:
        threading.Thread(target=read_stdin, daemon=True).start()
    try:
        while not stop.wait(0.2):
            pass
    finally:
        sim.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
