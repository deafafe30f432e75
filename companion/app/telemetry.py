"""The vehicle link's telemetry: the samples it caches, the attitude check, the streams that fill the caches.

``AttitudeSample``, ``ImuSample``, ``BaroSample`` and ``TruthForLog`` are what ``VehicleLink``
(companion/app/link.py) hands out; ``attitude_problem`` judges each raw attitude before the link accepts
it; ``TelemetryStreams`` (the link's telemetry half) follows mavsdk's streams into the caches and watches
for link loss. ``LinkPositionTruth`` is the link's own position estimate seen as a truth source
(companion/vehicle.py ``TruthSource``), for the flight log and scoring where no simulator truth exists.
"""

from __future__ import annotations

import asyncio
import bisect
import contextlib
import json
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from companion.config_app import LinkConfig
from companion.frames import R_from_quat_wxyz


@dataclass(frozen=True)
class AttitudeSample:
    q_wxyz: np.ndarray  # body FRD -> world NED, scalar first (PX4's attitude estimate)
    t_vehicle: float  # s since autopilot boot
    t_rx: float  # time.monotonic() when it arrived

    @property
    def R_ned_frd(self) -> np.ndarray:
        return R_from_quat_wxyz(self.q_wxyz)


class AttitudeHistory:
    """The last second of attitude estimates, to pair a camera frame with the attitude at its capture time.

    Rotating the box's ray with the attitude of a later moment turns the vehicle's own rotation during
    the perception latency into apparent LOS motion (the simulator measured 1 m gate success 1.00 -> 0.33
    at 100 ms). Interpolation is a normalised lerp between the two samples around ``t`` (at 50 Hz
    neighbours differ by a degree or two, where nlerp and slerp agree to micro-radians).
    """

    def __init__(self, maxlen: int = 128) -> None:
        self._t: deque[float] = deque(maxlen=maxlen)
        self._q: deque[np.ndarray] = deque(maxlen=maxlen)

    def add(self, t: float, q_wxyz: np.ndarray) -> None:
        if self._t and t <= self._t[-1]:
            return  # out of order or duplicate: keep the series monotonic
        self._t.append(t)
        self._q.append(np.asarray(q_wxyz, dtype=float))

    def __len__(self) -> int:
        return len(self._t)

    def at(self, t: float) -> np.ndarray | None:
        """Attitude (wxyz, NED/FRD) at time ``t``; the nearest sample outside the stored span."""
        if not self._t:
            return None
        i = bisect.bisect_left(self._t, t)
        if i == 0:
            return self._q[0]
        if i == len(self._t):
            return self._q[-1]
        t0, t1 = self._t[i - 1], self._t[i]
        q0, q1 = self._q[i - 1], self._q[i]
        if float(q0 @ q1) < 0.0:  # same rotation, other hemisphere: interpolate the short way
            q1 = -q1
        a = (t - t0) / (t1 - t0)
        q = (1.0 - a) * q0 + a * q1
        return q / math.sqrt(float(q @ q))


@dataclass(frozen=True)
class ImuSample:
    accel_frd: np.ndarray  # specific force, m/s^2 (level at rest: [0, 0, -9.81])
    gyro_frd: np.ndarray  # rad/s
    t_vehicle: float
    t_rx: float


@dataclass(frozen=True)
class BaroSample:
    altitude_m: float  # barometric altitude above the reference (taken at arm(), else the first sample)
    altitude_raw_m: float  # PX4's barometric altitude (ALTITUDE.altitude_monotonic)
    t_rx: float


@dataclass(frozen=True)
class TruthForLog:
    """Position/velocity from the autopilot's estimator (GPS/EKF or simulator truth).

    For the flight log and for scoring ONLY. The controller must never see these: the method flies
    from the camera and the IMU alone.
    """

    position_ned: np.ndarray  # m
    velocity_ned: np.ndarray  # m/s
    t_rx: float


MAX_BODY_RATE = 15.0  # rad/s (860 deg/s): faster than any quad this app flies; a bigger jump is not a rotation
JUMP_MARGIN = 0.35  # rad: estimator resets, jitter of the sample times


def attitude_problem(q: list[Any], t_ms: int, prev_q: np.ndarray | None, prev_t_ms: int | None) -> str | None:
    """Why an attitude sample cannot be PX4's estimate (None: plausible).

    Non-finite or non-unit quaternions, vehicle time running backwards (a spoofer's clock, or an
    autopilot reboot in flight) and tilt changes faster than MAX_BODY_RATE since the last accepted sample.
    Only the tilt (the body z axis) is judged: PX4's EKF resets its yaw in flight (measured on SITL: a 47 deg
    step in 20 ms during take-off), which is a real estimate, not a spoof.
    """
    if len(q) != 4 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in q):
        return f"non-finite quaternion {q}"
    n = math.sqrt(sum(float(v) * float(v) for v in q))
    if not 0.9 <= n <= 1.1:
        return f"quaternion norm {n:.3f} (not a rotation)"
    if prev_t_ms is not None and t_ms < prev_t_ms:
        return f"vehicle time went back from {prev_t_ms} to {t_ms} ms"
    if prev_q is not None and prev_t_ms is not None:
        z_new = R_from_quat_wxyz(np.asarray(q, float) / n)[:, 2]
        z_old = R_from_quat_wxyz(prev_q)[:, 2]
        angle = math.acos(max(-1.0, min(1.0, float(z_new @ z_old))))
        dt = (t_ms - prev_t_ms) * 1e-3
        if angle > MAX_BODY_RATE * dt + JUMP_MARGIN:
            return f"tilt jumped {math.degrees(angle):.0f} deg in {dt * 1e3:.0f} ms"
    return None


class TelemetryStreams:
    """The telemetry half of ``VehicleLink`` (a mixin): mavsdk's streams into "latest value" caches.

    Each handler only stores the newest value. Impossible attitude samples are rejected (events, then
    ``telemetry_invalid`` when they persist); no attitude for ``link_lost_timeout`` marks the link lost.
    From the link it uses ``cfg``, the mavsdk plugins ``_telemetry`` and ``_direct``, ``_tasks`` and ``_emit``.
    """

    cfg: LinkConfig
    _telemetry: Any
    _direct: Any
    _tasks: list[asyncio.Task]
    _emit: Callable[..., None]

    def _init_telemetry(self, *, reject_limit: int) -> None:
        self._reject_limit = int(reject_limit)
        self._rejects: deque[float] = deque(maxlen=1000)  # monotonic times of rejected telemetry samples
        self._invalid_reported = False
        self._att_t_ms: int | None = None  # vehicle time of the last accepted attitude
        self._event_decoder: Any = None
        self._event_seq: int | None = None
        self.px4_events: list[Any] = []  # decoded PX4 events (companion.app.px4events.Px4Event)
        self._attitude: AttitudeSample | None = None
        self.attitude_history = AttitudeHistory()  # for frames: the attitude at capture time
        self._imu: ImuSample | None = None
        self._flight_mode: str | None = None
        self._armed: bool | None = None
        self._landed: str | None = None
        self._health: Any = None
        self._baro: BaroSample | None = None
        self._baro_ref: float | None = None
        self._baro_recent: deque[float] = deque(maxlen=10)
        self._position: TruthForLog | None = None  # PX4's EKF position/velocity: position_for_log
        self._status_text: str | None = None
        self._last_rx = -math.inf
        self._lost = False
        self._mode_reports = 0
        self.rc: Any = None  # the newest RC_CHANNELS (companion.confirm.RcReading): the engage switch
        # ATTITUDE_TARGET: the thrust PX4 commands, the hover it really needs after take-off (companion/vehiclematch.py)
        self.thrust_targets: deque[Any] = deque(maxlen=300)

    def _start_telemetry(self) -> None:
        tel = self._telemetry
        streams: list[tuple[str, Callable[[], Any], Callable[[Any], None]]] = [
            ("attitude", lambda: self._direct.subscribe_message("ATTITUDE_QUATERNION"), self._on_attitude_msg),
            ("events", lambda: self._direct.subscribe_message("EVENT"), self._on_event_msg),
            ("rc_channels", lambda: self._direct.subscribe_message("RC_CHANNELS"), self._on_rc_msg),
            ("attitude_target", lambda: self._direct.subscribe_message("ATTITUDE_TARGET"), self._on_att_target_msg),
            ("imu", tel.subscribe_imu, self._on_imu),
            ("flight_mode", tel.subscribe_flight_mode, self._on_mode),
            ("armed", tel.subscribe_armed, self._on_armed),
            ("landed_state", tel.subscribe_landed_state, self._on_landed),
            ("altitude", tel.subscribe_altitude, self._on_altitude),
            ("position_velocity_ned", tel.subscribe_position_velocity_ned, self._on_posvel),
            ("health", tel.subscribe_health, self._on_health),
            ("status_text", tel.subscribe_status_text, self._on_status_text),
        ]
        for name, sub, handler in streams:
            self._tasks.append(asyncio.create_task(self._follow(name, sub, handler), name=f"link:{name}"))
        self._tasks.append(asyncio.create_task(self._monitor(), name="link:monitor"))

    async def _follow(self, name: str, subscribe: Callable[[], Any], handle: Callable[[Any], None]) -> None:
        # Each handler only stores the newest value, so the stream's queue never builds a backlog.
        try:
            async with contextlib.aclosing(subscribe()) as gen:
                async for value in gen:
                    handle(value)
        except asyncio.CancelledError:
            raise
        except Exception as e:  # report, don't crash the app
            self._emit("telemetry_error", stream=name, error=f"{type(e).__name__}: {e}")

    def _from_autopilot(self, msg: Any) -> bool:
        """Only the configured autopilot component (mavsdk already keeps other system ids apart)."""
        return int(msg.component_id) == self.cfg.component_id

    def _on_attitude_msg(self, msg: Any) -> None:
        """ATTITUDE_QUATERNION as mavsdk received it (raw: mavsdk's telemetry takes it from any component)."""
        if not self._from_autopilot(msg):
            self._reject("attitude", f"from component {msg.component_id}, not {self.cfg.component_id}")
            return
        # From the autopilot's ids: the link is alive even if the sample is rejected below (that is
        # TELEMETRY_INVALID's business, not LINK_LOST's).
        self._last_rx = time.monotonic()
        try:
            f = json.loads(msg.fields_json)
            q = [f["q1"], f["q2"], f["q3"], f["q4"]]
            t_ms = int(f["time_boot_ms"])
        except (ValueError, KeyError, TypeError) as e:
            self._reject("attitude", f"unreadable ({type(e).__name__})")
            return
        self._on_attitude(q, t_ms)

    def _on_rc_msg(self, msg: Any) -> None:
        """RC_CHANNELS (PWM us per channel): the operator's engage switch (companion/confirm.py)."""
        from companion.confirm import RcReading

        if not self._from_autopilot(msg):
            return
        try:
            f = json.loads(msg.fields_json)
            n = int(f.get("chancount", 18))
            self.rc = RcReading(time.monotonic(), tuple(int(f[f"chan{i}_raw"]) for i in range(1, 19))[:max(n, 0)])
        except (ValueError, KeyError, TypeError):
            return  # unreadable: the reading goes stale, which withdraws a confirmation

    def _on_att_target_msg(self, msg: Any) -> None:
        """ATTITUDE_TARGET (10 Hz on PX4 1.15's onboard link): PX4's attitude setpoint and collective thrust."""
        from companion.vehiclematch import ThrustSample

        if not self._from_autopilot(msg):
            return
        try:
            f = json.loads(msg.fields_json)
            q = (float(f["q"][0]), float(f["q"][1]), float(f["q"][2]), float(f["q"][3]))
            thrust = float(f["thrust"])
        except (ValueError, KeyError, TypeError, IndexError):
            return  # unreadable: one sample fewer
        baro = self._baro
        self.thrust_targets.append(ThrustSample(time.monotonic(), thrust, q, self._flight_mode, self._landed,
                                                None if baro is None else baro.altitude_raw_m))

    def _on_attitude(self, q: list[Any], t_ms: int) -> None:
        prev = self._attitude
        why = attitude_problem(q, t_ms, None if prev is None else prev.q_wxyz, self._att_t_ms)
        if why is not None:
            self._reject("attitude", why)
            return
        now = time.monotonic()
        qa = np.array(q, dtype=float)
        self._attitude = AttitudeSample(qa / np.linalg.norm(qa), t_ms * 1e-3, now)
        self._att_t_ms = t_ms
        self.attitude_history.add(now, self._attitude.q_wxyz)
        self._last_rx = now

    def _reject(self, what: str, why: str) -> None:
        """A telemetry sample the controller must not see: an event; a named abort when it persists."""
        now = time.monotonic()
        self._rejects.append(now)
        recent = sum(1 for t in self._rejects if now - t <= 1.0)
        if recent == 1 or recent % 50 == 0:  # the first of a burst, then every 50th: the log stays readable
            self._emit("telemetry_rejected", what=what, why=why, recent=recent)
        if recent >= self._reject_limit and not self._invalid_reported:
            self._invalid_reported = True
            self._emit("telemetry_invalid", what=what, why=why, count=recent)

    def _on_event_msg(self, msg: Any) -> None:
        """A PX4 event (1.15 reports through events, not STATUSTEXT): decoded, logged, the severe ones kept."""
        if not self._from_autopilot(msg):
            return
        try:
            fields = json.loads(msg.fields_json)
        except ValueError:
            return
        seq = int(fields.get("sequence", -1))
        if seq == self._event_seq:  # a resend
            return
        self._event_seq = seq
        if self._event_decoder is None:
            self._emit("px4_event", id=fields.get("id"), level="unknown", text=f"event {fields.get('id')}")
            return
        ev = self._event_decoder.decode(fields)
        self.px4_events.append(ev)
        if ev.name == "commander_disarmed_by":
            # PX4 sends the event at once; its heartbeat shows the disarm up to 1 s later. A vehicle that
            # just lost its motors must not get that second of setpoints.
            self._on_armed(False)
        if ev.level == "debug":
            return
        if ev.severe:
            self._status_text = ev.text  # quoted by the next refused command ("autopilot says: ...")
        self._emit("px4_event", name=ev.name, level=ev.level, text=ev.text, severe=ev.severe)

    def _on_imu(self, m: Any) -> None:
        a, w = m.acceleration_frd, m.angular_velocity_frd
        self._imu = ImuSample(np.array([a.forward_m_s2, a.right_m_s2, a.down_m_s2]),
                              np.array([w.forward_rad_s, w.right_rad_s, w.down_rad_s]),
                              m.timestamp_us * 1e-6, time.monotonic())

    def _on_mode(self, mode: Any) -> None:
        self._mode_reports += 1  # one per HEARTBEAT: "seen after the command" means a later count
        name = getattr(mode, "name", str(mode))
        if name != self._flight_mode:
            old, self._flight_mode = self._flight_mode, name
            self._emit("mode", old=old, new=name)

    def _on_armed(self, armed: bool) -> None:
        if armed != self._armed:
            self._armed = bool(armed)
            self._emit("armed" if armed else "disarmed")

    def _on_landed(self, state: Any) -> None:
        name = getattr(state, "name", str(state))
        if name != self._landed:
            old, self._landed = self._landed, name
            self._emit("landed_state", old=old, new=name)

    def _on_altitude(self, a: Any) -> None:
        raw = float(a.altitude_monotonic_m)
        if not math.isfinite(raw):
            return
        self._baro_recent.append(raw)
        if self._baro_ref is None:
            self._baro_ref = raw
        self._baro = BaroSample(raw - self._baro_ref, raw, time.monotonic())

    def _on_posvel(self, pv: Any) -> None:
        p, v = pv.position, pv.velocity
        self._position = TruthForLog(np.array([p.north_m, p.east_m, p.down_m]),
                                     np.array([v.north_m_s, v.east_m_s, v.down_m_s]), time.monotonic())

    def _on_health(self, h: Any) -> None:
        self._health = h

    def _on_status_text(self, st: Any) -> None:
        self._status_text = str(st.text)
        self._emit("status_text", text=self._status_text, type=getattr(st.type, "name", str(st.type)))

    async def _monitor(self) -> None:
        """Link-loss detector: no attitude message for link_lost_timeout -> lost (and back)."""
        while True:
            age = time.monotonic() - self._last_rx
            if not self._lost and age > self.cfg.link_lost_timeout:
                self._lost = True
                self._emit("link_lost", age=age)
            elif self._lost and age <= self.cfg.link_lost_timeout:
                self._lost = False
                self._emit("link_restored")
            await asyncio.sleep(0.05)


class _LinkWithPosition(Protocol):
    @property
    def position_for_log(self) -> TruthForLog | None: ...
    @property
    def attitude(self) -> AttitudeSample | None: ...


@dataclass(frozen=True)
class LinkPose:
    """The link's position sample with PX4's attitude estimate (a companion.vehicle.TruePose)."""

    position_ned: np.ndarray
    velocity_ned: np.ndarray
    q_wxyz: np.ndarray
    t_rx: float


class LinkPositionTruth:
    """The link's own position/velocity (PX4's EKF, ``link.position_for_log``) as a truth source.

    The truth where no simulator truth exists (the simulated PX4 reports its true state as the estimate;
    in the field it is the EKF's): flight log and scoring only. It keeps no history, so ``at(t)`` is the
    newest position with the newest attitude estimate, stamped ``t``.
    """

    def __init__(self, link: _LinkWithPosition) -> None:
        self.link = link

    def latest(self) -> TruthForLog | None:
        return self.link.position_for_log

    def at(self, t: float) -> LinkPose | None:
        pos, att = self.link.position_for_log, self.link.attitude
        if pos is None or att is None:
            return None
        return LinkPose(pos.position_ned, pos.velocity_ned, att.q_wxyz, t)

    def close(self) -> None:
        """Nothing to release: the link is closed by its owner."""
