"""The simulated PX4's MAVLink wire: its UDP socket on 127.0.0.1, decoding what arrives, encoding telemetry.

``MavlinkWire`` turns datagrams into calls on the autopilot (companion/sim/px4/model.py) and the
autopilot's state into MAVLink 2 messages at PX4's rates, plus the PX4 events and STATUSTEXT the
model raises. Its methods run under the model's lock (companion/sim/px4/realtime.py takes it).
"""

from __future__ import annotations

import math
import socket
import struct
import time
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
from companion.sim.dynamics import G, matrix_to_quat, quat_to_matrix
from companion.sim.px4.model import HOME_ALT, HOME_LAT, HOME_LON, INT32, MODES, Px4Model, nan_to

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


def _mav2_frame(seq: int, sysid: int, compid: int, msgid: int, crc_extra: int, payload: bytes) -> bytes:
    """One MAVLink 2 frame (trailing zero bytes of the payload cut, as the protocol does)."""
    from pymavlink.generator.mavcrc import x25crc

    body = payload.rstrip(b"\0") or b"\0"
    hdr = struct.pack("<BBBBBBBHB", 0xFD, len(body), 0, 0, seq, sysid, compid, msgid & 0xFFFF, msgid >> 16)
    crc = x25crc(hdr[1:] + body)
    crc.accumulate([crc_extra])
    return hdr + body + struct.pack("<H", crc.crc)


class MavlinkWire:
    """MAVLink 2 over UDP for a ``Px4Model``: one socket on 127.0.0.1, the peers that spoke to it, a fixed remote."""

    SYSID, COMPID = 1, 1
    GCS_SYSID, GCS_COMPID = 255, 190  # QGroundControl's ids

    def __init__(self, model: Px4Model, *, remote_port: int | None, heartbeat_hz: float, telemetry_hz: float) -> None:
        self.model = model
        # Like PX4 SITL, which sends to 127.0.0.1:14540: a mavsdk that listens (udpin://127.0.0.1) finds it.
        if remote_port is not None and not 0 <= int(remote_port) <= 65535:
            raise ValueError(f"SimPX4: remote_port {remote_port} is not a UDP port (0-65535)")
        self._remote_req = remote_port
        self.remote: tuple[str, int] | None = None
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
            mavlink.MAVLINK_MSG_ID_RC_CHANNELS: 0.1,  # only while an RC is connected (set_rc)
            mavlink.MAVLINK_MSG_ID_ATTITUDE_TARGET: 0.1,  # PX4 1.15's onboard link: 10 Hz
        }
        self._rates: dict[int, float] = dict(self._default_rates)  # msg id -> interval s (0 = off)
        self._next_send: dict[int, float] = dict.fromkeys(self._rates, 0.0)

        self.sock: socket.socket | None = None
        self._peers: dict[tuple[str, int], float] = {}
        self._mav = mavlink.MAVLink(None, srcSystem=self.SYSID, srcComponent=self.COMPID)
        self._mav.robust_parsing = True
        self._dropped = False
        self._silenced = False
        self._nan_attitude = False
        self._event_seq = 0
        self._events_meta: Any = None
        self._rc: list[int] | None = None  # RC channels (test switch set_rc); None: no RC, no RC_CHANNELS
        # A ground station on PX4's GCS link, as PX4 forwards it to this (onboard) link: its HEARTBEAT at 1 Hz
        # while connected (set_gcs), its commands (gcs_command); the acks addressed to it are recorded.
        self._gcs_mav = mavlink.MAVLink(None, srcSystem=self.GCS_SYSID, srcComponent=self.GCS_COMPID)
        self._gcs_on = False
        self._gcs_next_hb = 0.0
        self.gcs_acks: list[tuple[int, int]] = []  # (command, result) of COMMAND_ACKs to the ground station

    # ---------------------------------------------------------------------------------- socket
    def open(self, port: int) -> None:
        """Bind 127.0.0.1:``port`` (0: a free one) and pick the remote port (0: a free one)."""
        if self._remote_req is not None:
            remote = int(self._remote_req) or free_udp_port()
            self.remote = ("127.0.0.1", remote)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        # No SO_REUSEADDR: the port is ours alone (MAVSDK's udpin listeners set it and could share).
        sock.bind(("127.0.0.1", port))
        sock.setblocking(False)
        self.sock = sock
        if self.remote is not None:
            self._peers[self.remote] = math.inf  # always sent to, never forgotten

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None

    # -------------------------------------------------------------------------------- switches
    def drop_link(self, on: bool) -> None:
        """On: every datagram in either direction is lost (radio out of range)."""
        if on != self._dropped:
            self._dropped = on
            self.model.event("link:dropped" if on else "link:restored")

    def silence_commands(self, on: bool) -> None:
        """On: COMMAND_LONG/COMMAND_INT are received but neither executed nor acknowledged."""
        self._silenced = on

    def corrupt_attitude(self, on: bool) -> None:
        """On: ATTITUDE_QUATERNION carries NaN (an estimator failure, or a corrupted link)."""
        self._nan_attitude = on

    def set_rc(self, channels_us: list[int] | None) -> None:
        """An RC transmitter's channels (PWM us, channel 1 first, up to 18), sent as RC_CHANNELS; None: no RC."""
        self._rc = None if channels_us is None else [int(c) for c in channels_us][:18]

    def set_gcs(self, on: bool) -> None:
        """On: a ground station is connected (its HEARTBEAT forwarded at 1 Hz); off: it went silent."""
        self._gcs_on = on

    def gcs_command(self, command: int, param1: float, target: tuple[int, int]) -> None:
        """The ground station's COMMAND_LONG to ``target`` (system, component), forwarded as PX4 does."""
        msg = self._gcs_mav.command_long_encode(target[0], target[1], command, 0, param1, 0, 0, 0, 0, 0, 0)
        self.model.event(f"gcs_command:{command}:{param1:g}")
        self._send_raw(msg.pack(self._gcs_mav))

    # --------------------------------------------------------------------------- MAVLink input
    def receive_all(self, sock: socket.socket) -> None:
        for _ in range(256):
            try:
                data, addr = sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            with self.model.lock:
                if self._dropped:
                    continue
                self._peers[addr] = self.model.t
                try:
                    msgs = self._mav.parse_buffer(data) or []
                except mavlink.MAVError:
                    continue
                for m in msgs:
                    self._handle(m, addr)

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
                for i in range(len(self.model.params)):
                    self._param_read("", i)
        elif mid == mavlink.MAVLINK_MSG_ID_COMMAND_ACK and (m.target_system, m.target_component) == (
                self.GCS_SYSID, self.GCS_COMPID):
            self.gcs_acks.append((int(m.command), int(m.result)))  # forwarded to the GCS link by PX4
            self.model.event(f"gcs_ack:{m.command}:{m.result}")
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
        self.model.accept_setpoint(matrix_to_quat(R_enu_flu), m.thrust, time.monotonic())

    def _ack(self, command: int, result: int, sysid: int, compid: int) -> None:
        self._send(self._mav.command_ack_encode(command, result, 0, 0, sysid, compid))

    def _command(self, cmd: int, p: list[float], sysid: int, compid: int) -> None:
        if self._silenced:
            self.model.event(f"silenced:{cmd}")
            return
        self.model.event(f"command:{cmd}")
        res = self._link_command(cmd, p)
        if res is None:
            res = self.model.execute(cmd, p)
        self._ack(cmd, res, sysid, compid)

    def _link_command(self, cmd: int, p: list[float]) -> int | None:
        """The commands about the link itself (message rates and requests): their MAV_RESULT, else None."""
        ok = mavlink.MAV_RESULT_ACCEPTED
        if cmd == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            msg_id, interval = int(nan_to(p[0], -1)), nan_to(p[1], 0.0)
            if msg_id not in self._default_rates:
                return mavlink.MAV_RESULT_UNSUPPORTED
            if interval < 0:
                self._rates[msg_id] = 0.0
            elif interval == 0:
                self._rates[msg_id] = self._default_rates[msg_id]
            else:
                self._rates[msg_id] = max(interval * 1e-6, 0.002)
            self._next_send[msg_id] = self.model.t
            return ok
        if cmd == mavlink.MAV_CMD_REQUEST_MESSAGE:
            msg_id = int(nan_to(p[0], -1))
            if msg_id == mavlink.MAVLINK_MSG_ID_HOME_POSITION:
                self._send_home()
                return ok
            if msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
                self._send_autopilot_version()
                return ok
            if msg_id in self._default_rates:
                self._next_send[msg_id] = self.model.t  # one now
                return ok
            return mavlink.MAV_RESULT_UNSUPPORTED
        if cmd == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self._send_autopilot_version()
            return ok
        return None

    def _param_read(self, name: str, index: int) -> None:
        names = list(self.model.params)
        if index is not None and 0 <= index < len(names) and not name:
            name = names[index]
        if name not in self.model.params:
            return  # PX4 stays silent on unknown names; MAVSDK times out
        self._send_param(name)

    def _param_set(self, name: str, raw: float, ptype: int) -> None:
        if name not in self.model.params:
            return
        if self.model.params[name][1] == INT32:
            raw = struct.unpack("<i", struct.pack("<f", raw))[0]  # PX4 encodes ints bytewise
        self.model.set_param(name, raw)
        self.model.event(f"param_set:{name}")
        self._send_param(name)

    def _send_param(self, name: str) -> None:
        names = list(self.model.params)
        value, ptype = self.model.params[name]
        wire = struct.unpack("<f", struct.pack("<i", int(value)))[0] if ptype == INT32 else float(value)
        self._send(self._mav.param_value_encode(name.encode(), wire, ptype, len(names), names.index(name)))

    # -------------------------------------------------------------------------- MAVLink output
    def _send(self, msg: Any) -> None:
        if self._dropped or self.sock is None or not self._peers:
            return
        self._send_raw(msg.pack(self._mav))

    def _send_raw(self, buf: bytes) -> None:
        if self._dropped or self.sock is None or not self._peers:
            return
        self._mav.seq = (self._mav.seq + 1) % 256
        for addr in list(self._peers):
            try:
                self.sock.sendto(buf, addr)
            except OSError:
                if addr != self.remote:  # the fixed port may simply have no listener yet
                    self._peers.pop(addr, None)

    def statustext(self, text: str, severity: int = mavlink.MAV_SEVERITY_WARNING) -> None:
        self._send(self._mav.statustext_encode(severity, text.encode()[:50]))

    def px4_event(self, name: str, level: int, *args: float) -> None:
        """A PX4 event with PX4's own id and argument layout (from the event metadata the app decodes)."""
        if self._events_meta is None:
            from companion.app.px4events import EventDecoder

            self._events_meta = EventDecoder.load()
        eid = self._events_meta.event_id(name)
        packed = self._events_meta.encode_args(name, *args).ljust(40, b"\0")
        self._event_seq = (self._event_seq + 1) % 65536
        payload = struct.pack("<IIHBBB", eid, int(self.model.t * 1000), self._event_seq, 0, 0,
                              (level << 4) | level) + packed
        self._send_raw(_mav2_frame(self._mav.seq, self.SYSID, self.COMPID, _EVENT_ID, _EVENT_CRC, payload))

    def _send_heartbeat(self) -> None:
        main, sub = MODES[self.model.mode]
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.model.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        state = mavlink.MAV_STATE_ACTIVE if self.model.armed else mavlink.MAV_STATE_STANDBY
        self._send(self._mav.heartbeat_encode(
            mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base, (sub << 24) | (main << 16), state, 3))

    def _send_home(self) -> None:
        self._send(self._mav.home_position_encode(
            int(HOME_LAT * 1e7), int(HOME_LON * 1e7), int(HOME_ALT * 1000), 0.0, 0.0, 0.0,
            [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, int(self.model.t * 1e6)))

    def _send_autopilot_version(self) -> None:
        caps = (mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
                | mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT)
        self._send(self._mav.autopilot_version_encode(
            caps, (1 << 24) | (15 << 16) | (0 << 8) | 255, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0))

    def _landed_state(self) -> int:
        s = self.model.quad.state
        if s.on_ground:
            return mavlink.MAV_LANDED_STATE_ON_GROUND
        if self.model.mode == "TAKEOFF":
            return mavlink.MAV_LANDED_STATE_TAKEOFF
        if self.model.mode == "LAND":
            return mavlink.MAV_LANDED_STATE_LANDING
        return mavlink.MAV_LANDED_STATE_IN_AIR

    def _latlon(self, p_enu: np.ndarray) -> tuple[int, int, float]:
        lat = HOME_LAT + math.degrees(p_enu[1] / _R_EARTH)
        lon = HOME_LON + math.degrees(p_enu[0] / (_R_EARTH * math.cos(math.radians(HOME_LAT))))
        return round(lat * 1e7), round(lon * 1e7), HOME_ALT + float(p_enu[2])

    def send_telemetry(self) -> None:
        if self._dropped or not self._peers:
            return
        model = self.model
        # Forget clients silent for 5 s (MAVSDK sends a heartbeat every second): no sends to dead ports.
        for addr, t_heard in list(self._peers.items()):
            if model.t - t_heard > 5.0 and addr != self.remote:
                del self._peers[addr]
        t = model.t
        due = [mid for mid, iv in self._rates.items() if iv > 0 and t >= self._next_send.get(mid, 0.0)]
        if not due:
            return
        for mid in due:
            self._next_send[mid] = max(self._next_send.get(mid, 0.0) + self._rates[mid], t)
        s = model.quad.state
        ms = int(t * 1000)
        R_true = quat_to_matrix(s.q)
        fast = {mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, mavlink.MAVLINK_MSG_ID_ATTITUDE}
        if fast.intersection(due):
            # PX4's attitude estimate: truth with a per-run bias and white noise (companion/sim/sensors.py).
            wq = model.sensors.attitude_wxyz_ned_frd(s.q)
            rates = flu_to_frd(s.omega)
            if mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION in due:
                q_out = (math.nan, math.nan, math.nan, math.nan) if self._nan_attitude else wq
                self._send(self._mav.attitude_quaternion_encode(ms, *q_out, *rates, [0.0, 0.0, 0.0, 0.0]))
            if mavlink.MAVLINK_MSG_ID_ATTITUDE in due:
                roll, pitch, yaw = (math.radians(a) for a in euler_ned_deg_from_R(R_from_quat_wxyz(wq)))
                self._send(self._mav.attitude_encode(ms, roll, pitch, yaw, *rates))
        alt_amsl = HOME_ALT + float(s.p[2])
        baro_alt = HOME_ALT + model.sensors.baro_altitude(float(s.p[2]))
        if mavlink.MAVLINK_MSG_ID_HIGHRES_IMU in due:
            imu = model.sensors.imu(model.quad.specific_force_body(), s.omega)
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
            a_ned = enu_to_ned(model.quad.acceleration_world())
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
            failing = model.fail_preflight or model.obl_landed
            health = _SENSORS_ALL & ~mavlink.MAV_SYS_STATUS_PREARM_CHECK if failing else _SENSORS_ALL
            self._send(self._mav.sys_status_encode(
                _SENSORS_ALL, _SENSORS_ALL, health, 200, 16200, 1000, 90, 0, 0, 0, 0, 0, 0, 0, 0, 0))
        if mavlink.MAVLINK_MSG_ID_HOME_POSITION in due:
            self._send_home()
        if self._gcs_on and self.model.t >= self._gcs_next_hb:
            self._gcs_next_hb = self.model.t + 1.0
            hb = self._gcs_mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            self._send_raw(hb.pack(self._gcs_mav))
        if mavlink.MAVLINK_MSG_ID_RC_CHANNELS in due and self._rc is not None:
            ch = self._rc + [65535] * (18 - len(self._rc))  # UINT16_MAX: channel not in use
            self._send(self._mav.rc_channels_encode(ms, len(self._rc), *ch, 255))
        if mavlink.MAVLINK_MSG_ID_ATTITUDE_TARGET in due and model.cmd_q_enu_flu is not None:
            # The commanded attitude and collective thrust (PX4: vehicle_attitude_setpoint; its own modes fly
            # the true hover thrust here, like PX4's converged hover-thrust estimator).
            x, y, z, w = matrix_to_quat(R_ned_frd_from_enu_flu(quat_to_matrix(model.cmd_q_enu_flu)))
            self._send(self._mav.attitude_target_encode(ms, 0, [w, x, y, z], 0.0, 0.0, 0.0,
                                                        float(model.cmd_thrust)))
        if mavlink.MAVLINK_MSG_ID_HEARTBEAT in due:
            self._send_heartbeat()
