"""Vehicle link: the app's one door to the autopilot, on mavsdk 4 (native binding, asyncio API).

Public API (names are stable; the state machine and its tests rely on them)::

    link = VehicleLink.from_config(cfg, on_event=None)       # or VehicleLink(cfg.link, ...)
    await link.connect(url=None, timeout=None)                 # ConnectFailed, WrongAutopilot (link.system_id)
    await link.wait_healthy(timeout=None)                      # NotHealthy
    await link.hover_thrust(timeout=None) -> float             # MPC_THR_HOVER, else config (never raises)
    await link.read_param(name, timeout=None) -> float         # CommandTimeout, CommandDenied
    await link.read_param_int(name, timeout=None) -> int
    await link.failsafe_params(timeout=None) -> {name: value|None}   # companion/app/failsafe.py
    await link.arm(timeout=None)                               # ArmDenied, CommandTimeout
    await link.takeoff(altitude_m, timeout=None)               # TakeoffFailed, CommandTimeout (waits for HOLD)
    await link.start_offboard(first_setpoint, timeout=None)    # OffboardDenied, CommandTimeout
    await link.set_setpoint(sp)                                # OffboardLost, LinkLost, ValueError
    await link.stop_offboard(timeout=None)                     # -> HOLD; CommandDenied, CommandTimeout
    await link.hold(timeout=None); await link.land(timeout=None)
    await link.wait_landed_and_disarm(timeout=None)            # CommandTimeout
    await link.wait_mode(mode, timeout, after=None)            # CommandTimeout, LinkLost; after: a mode_reports
                                                               # count (only a later heartbeat confirms)
    await link.wait_link_ok(timeout)                           # LinkLost (telemetry back after a loss)
    await link.close()                                         # safe teardown; also ``async with``
    Telemetry ("latest value" caches, None until first received):
    link.attitude -> AttitudeSample (q_wxyz NED/FRD, R_ned_frd, t_vehicle, t_rx)
    link.imu -> ImuSample (accel_frd m/s^2 specific force, gyro_frd rad/s)
    link.flight_mode -> str ("HOLD", "OFFBOARD", "POSCTL", "TAKEOFF", "LAND", ...), link.armed -> bool|None
    link.landed_state -> str ("ON_GROUND", "IN_AIR", "TAKING_OFF", "LANDING", "UNKNOWN")
    link.baro -> BaroSample (altitude_m above the reference taken at arm()), link.baro_altitude -> float|None
    link.link_ok -> bool, link.check_link() (raises LinkLost), link.offboard_active -> bool
    link.truth_for_log -> TruthForLog | None  (position/velocity NED: ONLY for the flight log)
    link.status_text -> str | None (last STATUSTEXT), link.hover_thrust_source ("autopilot"|"config")
    link.events -> list[(t_monotonic, kind, detail)]; on_event(kind, detail) is called for each
    link.px4_events -> decoded PX4 events (companion/app/px4events.py); link.mode_reports -> heartbeats seen

Exceptions: every one derives ``LinkError`` and carries a one-line message saying what failed and
where: ConnectFailed, NotHealthy, ArmDenied, TakeoffFailed, OffboardDenied, OffboardLost,
CommandDenied, CommandTimeout, LinkLost.

Setpoints: anything with ``roll_deg, pitch_deg, yaw_deg`` (NED/FRD, absolute yaw) and ``thrust``
(0..1, e.g. ``companion.guidance.Setpoint``), through the last-line envelope (companion/app/envelope.py):
non-finite values raise SetpointRejected (nothing sent), the tilt is clamped to ``airframe.max_tilt`` and
the thrust to ``[thrust_min, 1]`` (never 0), each clamp an ``envelope`` event.

Exposure: URLs that make mavsdk listen on every interface are refused unless
``link.allow_all_interfaces``; only ``link.system_id`` is flown; the attitude is read raw and only from
``link.component_id``, and impossible samples (non-finite, non-unit, time running back, tilt jumps) are
rejected with ``telemetry_rejected`` events, ``telemetry_invalid`` when they persist. PX4 events (EVENT)
are decoded and emitted as ``px4_event``. While offboard is active the link resends the latest setpoint at
``link.setpoint_rate`` and runs a watchdog: no fresh ``set_setpoint`` for
``safety.perception_stall_timeout`` -> offboard is stopped (PX4 -> HOLD). This matters because
MAVSDK itself resends the last setpoint at ~20 Hz for as long as the process lives, so PX4's own
offboard-loss failsafe never fires if the control task dies. When the vehicle leaves OFFBOARD on its
own (pilot takeover, PX4 failsafe) the link never re-enters it: it stops commanding, swaps the
setpoint MAVSDK keeps resending for a level hover one, and ``set_setpoint`` raises OffboardLost.
A guard thread backs the watchdog up when the event loop itself stalls (2x the limit + 0.2 s).
"""

from __future__ import annotations

import asyncio
import bisect
import contextlib
import functools
import json
import math
import threading
import time
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from companion.app.envelope import SetpointEnvelope
from companion.config_app import LinkConfig
from companion.frames import R_from_quat_wxyz


# ------------------------------------------------------------------------------------- exceptions
class LinkError(RuntimeError):
    """Base of every link failure; ``str(e)`` is one line: what failed and why."""


class ConnectFailed(LinkError):
    pass


class NotHealthy(LinkError):
    pass


class ArmDenied(LinkError):
    pass


class TakeoffFailed(LinkError):
    pass


class OffboardDenied(LinkError):
    pass


class OffboardLost(LinkError):
    """Offboard ended without the app asking: pilot takeover, PX4 failsafe or the link's watchdog."""


class CommandDenied(LinkError):
    pass


class CommandTimeout(LinkError):
    pass


class LinkLost(LinkError):
    pass


class SetpointRejected(LinkError, ValueError):
    """Upstream produced a setpoint that must never leave the app (non-finite): nothing was sent."""


class WrongAutopilot(ConnectFailed):
    """Heard an autopilot, but not the configured system (link.system_id)."""


# -------------------------------------------------------------------------------------- samples
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


class SetpointLike(Protocol):
    roll_deg: float
    pitch_deg: float
    yaw_deg: float
    thrust: float


@dataclass(frozen=True)
class _Sp:
    roll_deg: float
    pitch_deg: float
    yaw_deg: float
    thrust: float


# ------------------------------------------------------------------------------------------ link
class VehicleLink:
    """Async link to PX4 through mavsdk: connect, health, arm, takeoff, offboard attitude, land."""

    POLL = 0.02  # s between checks in the wait helpers

    def __init__(
        self,
        link: LinkConfig | None = None,
        *,
        hover_thrust_fallback: float = 0.5,
        thrust_min: float = 0.1,
        setpoint_timeout: float = 0.5,
        max_tilt_deg: float = 50.0,
        reject_limit: int = 5,
        on_event: Callable[[str, dict[str, Any]], None] | None = None,
    ) -> None:
        self.cfg = link if link is not None else LinkConfig()
        self._hover_fallback = float(hover_thrust_fallback)
        self._thrust_min = float(thrust_min)
        self._setpoint_timeout = float(setpoint_timeout)
        self.envelope = SetpointEnvelope(max_tilt_deg, thrust_min)
        self._clamps = 0
        self._last_clamp_event = -math.inf
        self._reject_limit = int(reject_limit)
        self._rejects: deque[float] = deque(maxlen=1000)  # monotonic times of rejected telemetry samples
        self._invalid_reported = False
        self._att_t_ms: int | None = None  # vehicle time of the last accepted attitude
        self._event_decoder: Any = None
        self._event_seq: int | None = None
        self.px4_events: list[Any] = []  # decoded PX4 events (companion.app.px4events.Px4Event)
        self._on_event = on_event
        self.events: list[tuple[float, str, dict[str, Any]]] = []
        self.hover_thrust_source = "config"
        self._hover_value = self._hover_fallback

        self._mavsdk: Any = None
        self._system: Any = None
        self._action: Any = None
        self._offboard: Any = None
        self._telemetry: Any = None
        self._param: Any = None
        self._direct: Any = None
        self._tasks: list[asyncio.Task] = []
        self._inflight: set[asyncio.Future] = set()
        self._closed = False

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
        self._truth: TruthForLog | None = None
        # Simulator ground truth (companion/px4sitl/truth.py), when there is one: replaces the EKF's
        # position in truth_for_log. Scoring and the synthetic camera only.
        self.truth_source: Any = None
        self._status_text: str | None = None
        self._last_rx = -math.inf
        self._lost = False

        self._mode_reports = 0
        self._offboard_requested = False  # OFFBOARD asked for and not stopped since (PX4 may be in it unseen)
        self._offboard_active = False
        self._offboard_end_reason: str | None = None
        self._latest_sp: _Sp | None = None
        self._last_fresh = -math.inf
        self._last_sent = -math.inf
        self._switch_pending = False  # start_offboard under way: PX4 may fly our first setpoint, unconfirmed
        self._switch_beat = -math.inf  # the event loop's beat meanwhile
        self._offboard_tasks: list[asyncio.Task] = []
        self._guard_stop = threading.Event()
        self._guard_busy = False

    @classmethod
    def from_config(cls, cfg: Any, on_event: Callable[[str, dict[str, Any]], None] | None = None) -> VehicleLink:
        return cls(
            cfg.link,
            hover_thrust_fallback=cfg.airframe.hover_thrust,
            thrust_min=cfg.airframe.thrust_min,
            setpoint_timeout=cfg.safety.perception_stall_timeout,
            max_tilt_deg=cfg.airframe.max_tilt,
            reject_limit=cfg.safety.telemetry_reject_limit,
            on_event=on_event,
        )

    async def __aenter__(self) -> VehicleLink:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # ------------------------------------------------------------------------------ telemetry
    @property
    def attitude(self) -> AttitudeSample | None:
        return self._attitude

    @property
    def imu(self) -> ImuSample | None:
        return self._imu

    @property
    def flight_mode(self) -> str | None:
        return self._flight_mode

    @property
    def armed(self) -> bool | None:
        return self._armed

    @property
    def landed_state(self) -> str | None:
        return self._landed

    @property
    def baro(self) -> BaroSample | None:
        return self._baro

    @property
    def baro_altitude(self) -> float | None:
        return None if self._baro is None else self._baro.altitude_m

    @property
    def truth_for_log(self) -> TruthForLog | None:
        if self.truth_source is not None:
            return self.truth_source.latest()
        return self._truth

    @property
    def status_text(self) -> str | None:
        return self._status_text

    @property
    def health(self) -> Any:
        return self._health

    @property
    def link_ok(self) -> bool:
        return self._system is not None and not self._lost

    @property
    def offboard_active(self) -> bool:
        return self._offboard_active

    @property
    def telemetry_age(self) -> float:
        """Seconds since the last attitude message (inf before the first)."""
        return time.monotonic() - self._last_rx

    def check_link(self) -> None:
        if self._system is None:
            raise LinkLost("vehicle link: not connected")
        if self._lost:
            raise LinkLost(f"vehicle link lost: no telemetry for {self.telemetry_age:.1f} s "
                           f"(limit link.link_lost_timeout = {self.cfg.link_lost_timeout:.1f} s)")

    def set_baro_reference(self) -> None:
        """Zero the barometric altitude here (called by arm(): altitude above take-off)."""
        if self._baro_recent:
            self._baro_ref = float(np.median(self._baro_recent))

    # ----------------------------------------------------------------------------- internals
    def _emit(self, kind: str, **detail: Any) -> None:
        self.events.append((time.monotonic(), kind, detail))
        if self._on_event is not None:
            with contextlib.suppress(Exception):  # a logging callback must never break the link
                self._on_event(kind, detail)

    async def _call(self, what: str, fn: Callable[[], Awaitable[Any]], timeout: float | None = None) -> Any:
        """Run one mavsdk call with a timeout; remember it until it ends so close() never destroys under it."""
        timeout = self.cfg.command_timeout if timeout is None else timeout
        task = asyncio.ensure_future(fn())
        self._inflight.add(task)

        def done(t: asyncio.Future) -> None:
            self._inflight.discard(t)
            if not t.cancelled():
                t.exception()  # retrieved: a late failure after our timeout is not an error to report

        task.add_done_callback(done)
        try:
            return await asyncio.wait_for(asyncio.shield(task), timeout)
        except TimeoutError:
            raise CommandTimeout(f"{what}: no answer within {timeout:.1f} s") from None

    async def _reason_soon(self, wait: float = 0.5) -> None:
        """A refusal's reason comes as an event or STATUSTEXT beside the ACK, not always before it."""
        deadline = time.monotonic() + wait
        while self._status_text is None and time.monotonic() < deadline:
            await asyncio.sleep(self.POLL)

    def _why(self) -> str:
        return f" (autopilot says: {self._status_text})" if self._status_text else ""

    async def _wait_until(self, pred: Callable[[], bool], timeout: float, what: str,
                          exc: type[LinkError] = CommandTimeout) -> None:
        deadline = time.monotonic() + timeout
        while not pred():
            self.check_link()
            if time.monotonic() >= deadline:
                raise exc(f"{what} (waited {timeout:.1f} s; mode {self._flight_mode}, armed {self._armed}, "
                          f"landed {self._landed})")
            await asyncio.sleep(self.POLL)

    async def wait_until(self, pred: Callable[[], bool], timeout: float, what: str) -> None:
        """Until ``pred()`` holds on the link's telemetry (CommandTimeout naming ``what``, LinkLost)."""
        await self._wait_until(pred, timeout, what)

    async def wait_link_ok(self, timeout: float) -> None:
        """Wait until telemetry flows again after a loss (LinkLost at timeout)."""
        deadline = time.monotonic() + timeout
        while not self.link_ok:
            if time.monotonic() >= deadline:
                self.check_link()
            await asyncio.sleep(self.POLL)

    async def wait_mode(self, mode: str, timeout: float, after: int | None = None) -> None:
        """Until PX4's heartbeat shows ``mode``; with ``after`` (a ``mode_reports`` count taken when the
        command was sent) only a heartbeat sent after the command counts: a stale one is no confirmation."""
        n0 = -1 if after is None else after
        await self._wait_until(lambda: self._mode_reports > n0 and self._flight_mode == mode, timeout,
                               f"vehicle did not enter {mode}")

    @property
    def mode_reports(self) -> int:
        """Heartbeats (mode reports) received so far."""
        return self._mode_reports

    # ---------------------------------------------------------------------------- connection
    async def connect(self, url: str | None = None, timeout: float | None = None) -> None:
        from mavsdk.asyncio import ComponentType, Configuration, Mavsdk, MavsdkConnectionError
        from mavsdk.asyncio.plugins.action import ActionAsync
        from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync
        from mavsdk.asyncio.plugins.offboard import OffboardAsync
        from mavsdk.asyncio.plugins.param import ParamAsync
        from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

        from companion.app.px4events import EventDecoder
        from companion.config_app import all_interfaces_reason

        url = url or self.cfg.url
        timeout = self.cfg.connect_timeout if timeout is None else timeout
        if self._mavsdk is not None:
            raise ConnectFailed(f"connect {url}: this link is already connected (make a new VehicleLink)")
        exposure = all_interfaces_reason(url)
        if exposure is not None:
            if not self.cfg.allow_all_interfaces:
                raise ConnectFailed(f"connect {url}: refused, the URL {exposure} "
                                    "(link.allow_all_interfaces is false; use udpin://127.0.0.1:PORT)")
            self._emit("exposed", url=url, why=exposure)
        try:
            self._event_decoder = EventDecoder.load(self.cfg.events_metadata or None)
        except (OSError, ValueError) as e:  # events are then logged by id only
            self._emit("events_metadata_unreadable", path=self.cfg.events_metadata, error=str(e))
        self._mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER))
        try:
            await self._call(f"open {url}", lambda: self._mavsdk.add_any_connection(url), timeout)
        except MavsdkConnectionError as e:
            raise ConnectFailed(f"cannot open connection {url!r}: {e}") from None
        system = await self._find_autopilot(url, timeout)
        self._system = system
        self._direct = MavlinkDirectAsync(system)
        self._action = ActionAsync(system)
        self._offboard = OffboardAsync(system)
        self._telemetry = TelemetryAsync(system)
        self._param = ParamAsync(system)
        self._last_rx = time.monotonic()  # the link counts as alive from discovery on
        self._start_telemetry()
        self._emit("connected", url=url)
        # Ask for the streams the control loop needs at a useful rate (best effort: PX4 may refuse).
        for name, rate in (("attitude_quaternion", 50.0), ("imu", 50.0), ("altitude", 20.0),
                           ("landed_state", 5.0), ("position_velocity_ned", 50.0)):
            try:
                await self._call(f"set {name} rate", lambda n=name, r=rate: getattr(self._telemetry,
                                                                                    f"set_rate_{n}")(r), 2.0)
            except Exception as e:  # a refused rate is not fatal
                self._emit("rate_refused", stream=name, error=str(e))

    async def _find_autopilot(self, url: str, timeout: float) -> Any:
        """The autopilot with MAVLink system id ``link.system_id``; any other system is ignored."""
        want = self.cfg.system_id
        deadline = time.monotonic() + timeout
        heard: set[int] = set()
        while True:
            left = deadline - time.monotonic()
            first = await self._call(f"find an autopilot on {url}",
                                     functools.partial(self._mavsdk.first_autopilot, max(min(left, 1.0), 0.0)),
                                     left + 2.0)
            if first is not None:
                for sys_ in await self._mavsdk.get_systems():
                    sid = await sys_.get_system_id()
                    if sid == want and await sys_.has_autopilot():
                        return sys_
                    heard.add(sid)
            if time.monotonic() >= deadline:
                if heard:
                    raise WrongAutopilot(f"no autopilot with system id {want} (link.system_id) on {url} within "
                                         f"{timeout:.1f} s; heard system(s) {sorted(heard)}")
                raise ConnectFailed(f"no autopilot heard on {url} within {timeout:.1f} s")
            await asyncio.sleep(self.POLL if first is not None else 0.0)

    def _start_telemetry(self) -> None:
        tel = self._telemetry
        streams: list[tuple[str, Callable[[], Any], Callable[[Any], None]]] = [
            ("attitude", lambda: self._direct.subscribe_message("ATTITUDE_QUATERNION"), self._on_attitude_msg),
            ("events", lambda: self._direct.subscribe_message("EVENT"), self._on_event_msg),
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
        self._truth = TruthForLog(np.array([p.north_m, p.east_m, p.down_m]),
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

    # ------------------------------------------------------------------------ health, params
    def _health_problems(self) -> list[str]:
        h = self._health
        if h is None:
            return ["no health report yet"]
        checks = {
            "gyro calibration": h.is_gyrometer_calibration_ok,
            "accelerometer calibration": h.is_accelerometer_calibration_ok,
            "local position": h.is_local_position_ok,  # PX4 needs it for take-off and HOLD
            "armable (preflight checks)": h.is_armable,
        }
        return [k for k, ok in checks.items() if not ok]

    async def wait_healthy(self, timeout: float | None = None) -> None:
        timeout = self.cfg.health_timeout if timeout is None else timeout
        deadline = time.monotonic() + timeout
        while self._health_problems():
            self.check_link()
            if time.monotonic() >= deadline:
                raise NotHealthy(f"autopilot not ready after {timeout:.1f} s: "
                                 f"{', '.join(self._health_problems())}{self._why()}")
            await asyncio.sleep(self.POLL)
        self._emit("healthy")

    async def read_param(self, name: str, timeout: float | None = None) -> float:
        return float(await self._read_param(name, "get_param_float", timeout))

    async def read_param_int(self, name: str, timeout: float | None = None) -> int:
        return int(await self._read_param(name, "get_param_int", timeout))

    async def _read_param(self, name: str, getter: str, timeout: float | None) -> Any:
        """One parameter through mavsdk's param plugin (``getter``: its method); its errors as our command errors."""
        from mavsdk.asyncio.plugins.param import ParamError

        self.check_link()
        try:
            return await self._call(f"read parameter {name}", lambda: getattr(self._param, getter)(name), timeout)
        except ParamError as e:
            if e.result.name == "TIMEOUT":
                raise CommandTimeout(f"read parameter {name}: no answer from the autopilot") from None
            raise CommandDenied(f"read parameter {name}: {e.result.name}") from None

    async def failsafe_params(self, timeout: float | None = None) -> dict[str, float | None]:
        """PX4's failsafe parameters (companion/app/failsafe.py FAILSAFE_PARAMS); None for one it did not give."""
        from companion.app.failsafe import FAILSAFE_PARAMS

        out: dict[str, float | None] = {}
        for name, kind in FAILSAFE_PARAMS.items():
            try:
                out[name] = float(await (self.read_param_int(name, timeout) if kind == "int"
                                         else self.read_param(name, timeout)))
            except LinkError as e:
                self._emit("param_unread", name=name, error=str(e))
                out[name] = None
        return out

    async def hover_thrust(self, timeout: float | None = None) -> float:
        """PX4's MPC_THR_HOVER when the autopilot has it and it is plausible, else the config value."""
        try:
            value = await self.read_param("MPC_THR_HOVER", timeout)
        except LinkError as e:
            self.hover_thrust_source = "config"
            self._emit("hover_thrust", value=self._hover_fallback, source="config", why=str(e))
            return self._hover_fallback
        if not (math.isfinite(value) and 0.05 < value < 0.95):
            self.hover_thrust_source = "config"
            self._emit("hover_thrust", value=self._hover_fallback, source="config",
                       why=f"MPC_THR_HOVER = {value} is implausible")
            return self._hover_fallback
        self.hover_thrust_source = "autopilot"
        self._hover_value = value
        self._emit("hover_thrust", value=value, source="autopilot")
        return value

    # ----------------------------------------------------------------------- arm, takeoff, land
    async def arm(self, timeout: float | None = None) -> None:
        from mavsdk.asyncio.plugins.action import ActionError

        self.check_link()
        timeout = self.cfg.command_timeout if timeout is None else timeout
        self._status_text = None
        try:
            await self._call("arm", self._action.arm, timeout)
        except ActionError as e:
            if e.result.name == "TIMEOUT":
                raise CommandTimeout(f"arm: no answer from the autopilot{self._why()}") from None
            await self._reason_soon()
            raise ArmDenied(f"arm refused by the autopilot: {e.result.name}{self._why()}") from None
        await self._wait_until(lambda: self._armed is True, timeout, "arm: accepted but the vehicle is not armed",
                               ArmDenied)
        self.set_baro_reference()

    async def takeoff(self, altitude_m: float, timeout: float | None = None) -> None:
        """Take off in PX4's own mode to ``altitude_m`` above ground; returns once PX4 holds there."""
        from mavsdk.asyncio.plugins.action import ActionError

        self.check_link()
        timeout = self.cfg.takeoff_timeout if timeout is None else timeout
        if not (math.isfinite(altitude_m) and altitude_m > 0):
            raise ValueError(f"takeoff: altitude must be a positive number of metres (got {altitude_m})")
        try:
            await self._call("set take-off altitude", lambda: self._action.set_takeoff_altitude(altitude_m))
            n0 = self._mode_reports
            await self._call("takeoff", self._action.takeoff)
        except ActionError as e:
            if e.result.name == "TIMEOUT":
                raise CommandTimeout(f"takeoff: no answer from the autopilot{self._why()}") from None
            raise TakeoffFailed(f"takeoff refused by the autopilot: {e.result.name}{self._why()}") from None
        self._emit("takeoff", altitude=altitude_m)
        # PX4 switches TAKEOFF -> HOLD at the target altitude; anything else means it gave up.
        # Judged only on heartbeats sent after the command (PX4: 1 Hz), never on the HOLD it showed before.
        await self._wait_until(lambda: self._mode_reports > n0 and (self._flight_mode == "TAKEOFF"
                                                                    or self._landed == "IN_AIR"),
                               min(timeout, 5.0), "takeoff: vehicle never entered TAKEOFF", TakeoffFailed)

        def done() -> bool:
            if self._flight_mode not in ("TAKEOFF", "HOLD"):
                raise TakeoffFailed(f"takeoff interrupted: vehicle switched to {self._flight_mode}{self._why()}")
            return self._flight_mode == "HOLD" and self._landed == "IN_AIR"

        await self._wait_until(done, timeout, f"takeoff to {altitude_m:.1f} m not finished", TakeoffFailed)

    async def hold(self, timeout: float | None = None) -> None:
        await self._action_then_mode("hold", "HOLD", lambda: self._action.hold(), timeout)

    async def land(self, timeout: float | None = None) -> None:
        await self._action_then_mode("land", "LAND", lambda: self._action.land(), timeout)

    async def _action_then_mode(self, what: str, mode: str, fn: Callable[[], Awaitable[Any]],
                                timeout: float | None) -> None:
        from mavsdk.asyncio.plugins.action import ActionError

        self.check_link()
        timeout = self.cfg.command_timeout if timeout is None else timeout
        self._stop_offboard_tasks(f"{what} requested")
        self._offboard_requested = False
        n0 = self._mode_reports
        await self._mapped_call(what, fn, timeout, ActionError, CommandDenied, f"{what} refused by the autopilot")
        self._emit(what)
        await self.wait_mode(mode, max(timeout, self.cfg.mode_timeout), after=n0)

    async def wait_landed_and_disarm(self, timeout: float | None = None) -> None:
        """Wait for touchdown and PX4's auto-disarm (COM_DISARM_LAND); disarm ourselves if it doesn't."""
        from mavsdk.asyncio.plugins.action import ActionError

        timeout = self.cfg.land_timeout if timeout is None else timeout
        deadline = time.monotonic() + timeout
        await self._wait_until(lambda: self._landed == "ON_GROUND" or self._armed is False, timeout,
                               "landing: vehicle not on the ground")
        left = max(deadline - time.monotonic(), 0.0)
        try:
            await self._wait_until(lambda: self._armed is False, min(left, 5.0), "auto-disarm")
        except CommandTimeout:
            try:
                await self._call("disarm", self._action.disarm)
            except ActionError as e:
                raise CommandDenied(f"disarm after landing refused: {e.result.name}{self._why()}") from None
            await self._wait_until(lambda: self._armed is False, max(deadline - time.monotonic(), 1.0),
                                   "disarm: accepted but the vehicle is still armed")
        self._emit("landed_and_disarmed")

    # ---------------------------------------------------------------------------------- offboard
    def _validated(self, sp: SetpointLike) -> _Sp:
        """The last-line envelope (companion/app/envelope.py): non-finite -> SetpointRejected, else clamped."""
        try:
            vals = (float(sp.roll_deg), float(sp.pitch_deg), float(sp.yaw_deg), float(sp.thrust))
        except (AttributeError, TypeError, ValueError):
            raise SetpointRejected(f"setpoint: need roll_deg, pitch_deg, yaw_deg, thrust numbers (got {sp!r})"
                                   ) from None
        try:
            c = self.envelope.check(*vals)
        except ValueError as e:
            self._emit("envelope", action="refused", why=str(e))
            raise SetpointRejected(str(e)) from None
        if c.clamped:
            now = time.monotonic()
            self._clamps += 1
            if now - self._last_clamp_event >= 1.0:  # one event a second at most, with the count since the last
                self._emit("envelope", action="clamped", why=c.clamped, count=self._clamps)
                self._clamps = 0
                self._last_clamp_event = now
        return _Sp(c.roll_deg, c.pitch_deg, c.yaw_deg, c.thrust)

    async def _send(self, sp: _Sp) -> None:
        from mavsdk.asyncio.plugins.offboard import Attitude

        att = Attitude(sp.roll_deg, sp.pitch_deg, sp.yaw_deg, sp.thrust)
        await self._call("send setpoint", lambda: self._offboard.set_attitude(att), 1.0)
        self._last_sent = time.monotonic()

    async def start_offboard(self, first_setpoint: SetpointLike, timeout: float | None = None) -> None:
        """Stream ``first_setpoint``, switch PX4 to OFFBOARD and wait until the vehicle reports it."""
        from mavsdk.asyncio.plugins.offboard import OffboardError

        self.check_link()
        timeout = self.cfg.command_timeout if timeout is None else timeout
        sp = self._validated(first_setpoint)
        self._latest_sp = sp
        self._last_fresh = self._switch_beat = time.monotonic()
        self._offboard_requested = True
        self._offboard_end_reason = None  # set by the loop guard if it hands over before the switch is seen
        # From the first setpoint on, MAVSDK resends it by itself: the loop guard watches from here, not from
        # the confirmation (PX4's 1 Hz heartbeat, up to ~1 s later), so a loop stalled meanwhile is caught too.
        self._switch_pending = True
        self._start_loop_guard()
        beat = asyncio.create_task(self._beat_while_switching(), name="link:switch_beat")
        try:
            await self._send(sp)
            await asyncio.sleep(0.2)  # PX4 wants a setpoint stream before it accepts OFFBOARD
            self._status_text = None
            n0 = self._mode_reports
            await self._mapped_call("start offboard", self._offboard.start, timeout, OffboardError, OffboardDenied,
                                    "offboard refused")
            await self._wait_until(lambda: (self._mode_reports > n0 and self._flight_mode == "OFFBOARD")
                                   or self._offboard_end_reason is not None,
                                   max(timeout, self.cfg.mode_timeout),
                                   "offboard accepted but the vehicle is not in OFFBOARD", OffboardDenied)
            if self._offboard_end_reason is not None:  # the loop guard handed over to HOLD while we waited
                raise OffboardLost(f"offboard start abandoned: {self._offboard_end_reason}")
            self._last_fresh = time.monotonic()
            self._offboard_active = True  # before the switch stops pending: the guard never sees neither
        except BaseException:
            self._guard_stop.set()
            raise
        finally:
            self._switch_pending = False
            beat.cancel()
        self._offboard_tasks = [asyncio.create_task(self._stream(), name="link:setpoint_stream"),
                                asyncio.create_task(self._watchdog(), name="link:watchdog")]
        self._emit("offboard_started")

    async def _mapped_call(self, what: str, fn: Callable[[], Awaitable[Any]], timeout: float,
                           error: type[Exception], refused: type[LinkError], refused_what: str) -> None:
        """One mavsdk plugin call whose failure is ``error`` (ActionError, OffboardError): its TIMEOUT result is
        CommandTimeout, any other result ``refused`` with the autopilot's reason."""
        try:
            await self._call(what, fn, timeout)
        except error as e:
            result = e.result.name  # type: ignore[attr-defined]
            if result == "TIMEOUT":
                raise CommandTimeout(f"{what}: no answer from the autopilot{self._why()}") from None
            raise refused(f"{refused_what}: {result}{self._why()}") from None

    async def _beat_while_switching(self) -> None:
        """While the switch is pending no fresh setpoint is due; the guard then watches the loop itself."""
        while True:
            self._switch_beat = time.monotonic()
            await asyncio.sleep(0.05)

    async def set_setpoint(self, sp: SetpointLike) -> None:
        """Send a fresh setpoint (the control loop calls this every frame)."""
        checked = self._validated(sp)
        if not self._offboard_active:
            why = self._offboard_end_reason or "not started"
            raise OffboardLost(f"setpoint refused: offboard is not active ({why})")
        self.check_link()
        if self._flight_mode != "OFFBOARD":
            await self._left_offboard(f"vehicle left OFFBOARD, now {self._flight_mode}")
            raise OffboardLost(f"setpoint refused: {self._offboard_end_reason}")
        self._latest_sp = checked
        self._last_fresh = time.monotonic()
        await self._send(checked)

    async def _stream(self) -> None:
        period = 1.0 / self.cfg.setpoint_rate
        while self._offboard_active:
            if self._latest_sp is not None and time.monotonic() - self._last_sent >= period:
                with contextlib.suppress(LinkError):
                    await self._send(self._latest_sp)
            await asyncio.sleep(period / 2)

    async def _watchdog(self) -> None:
        from mavsdk.asyncio.plugins.offboard import OffboardError

        while self._offboard_active:
            if self._flight_mode != "OFFBOARD":
                await self._left_offboard(f"vehicle left OFFBOARD, now {self._flight_mode}")
                return
            age = time.monotonic() - self._last_fresh
            if age > self._setpoint_timeout:
                reason = (f"setpoint watchdog: no fresh setpoint for {age:.2f} s "
                          f"(limit {self._setpoint_timeout:.2f} s), handed over to HOLD")
                self._offboard_active = False
                self._offboard_end_reason = reason
                self._emit("watchdog", age=age)
                try:
                    await self._call("stop offboard (watchdog)", self._offboard.stop)
                except (OffboardError, LinkError) as e:
                    self._emit("watchdog_stop_failed", error=str(e))
                return
            await asyncio.sleep(min(0.05, self._setpoint_timeout / 4))

    def _start_loop_guard(self) -> None:
        """Second line behind ``_watchdog``, in a thread: it still works when the event loop itself is stuck.

        A stalled loop (sync code that never returns) runs no asyncio task, while MAVSDK's own thread
        keeps resending the last setpoint. After twice the watchdog limit without a fresh setpoint this
        thread stops offboard through mavsdk's blocking API (PX4 -> HOLD).
        """
        plugin = getattr(self._offboard, "_plugin", None)  # the blocking Offboard behind mavsdk's async wrapper
        if plugin is None:
            return
        loop = asyncio.get_running_loop()
        self._guard_stop = stop = threading.Event()
        limit = 2.0 * self._setpoint_timeout + 0.2

        def run() -> None:
            while not stop.wait(0.05):
                if self._offboard_active:
                    age = time.monotonic() - self._last_fresh
                elif self._switch_pending:  # no fresh setpoint is due yet: the loop's own beat
                    age = time.monotonic() - max(self._last_fresh, self._switch_beat)
                else:
                    return
                if age <= limit:
                    continue
                self._offboard_active = False
                self._offboard_end_reason = (f"loop guard: no fresh setpoint for {age:.2f} s and the event loop "
                                             "is stalled, handed over to HOLD")
                self._guard_busy = True
                # Reported before the blocking stop: a loop that wakes meanwhile learns the cause first.
                with contextlib.suppress(RuntimeError):  # loop already closed
                    loop.call_soon_threadsafe(functools.partial(self._emit, "loop_guard", age=age))
                try:
                    result: object = plugin.stop()
                except Exception as e:  # reported below; the thread must end either way
                    result = e
                finally:
                    self._guard_busy = False
                with contextlib.suppress(RuntimeError):
                    loop.call_soon_threadsafe(functools.partial(self._emit, "loop_guard_stop", result=str(result)))
                return

        threading.Thread(target=run, name="link:loop_guard", daemon=True).start()

    async def _left_offboard(self, reason: str) -> None:
        """The vehicle left OFFBOARD on its own: stop commanding, never re-enter, defuse MAVSDK's resends."""
        if not self._offboard_active:
            return
        self._offboard_active = False
        self._offboard_end_reason = reason
        self._emit("offboard_lost", reason=reason, mode=self._flight_mode)
        # MAVSDK keeps resending the last setpoint; make it a level hover in case OFFBOARD is ever re-engaged.
        # (offboard.stop() would also end the resends, but it commands HOLD over the pilot's choice.)
        yaw = self._latest_sp.yaw_deg if self._latest_sp is not None else 0.0
        with contextlib.suppress(Exception):
            await self._send(_Sp(0.0, 0.0, yaw, min(max(self._hover_value, self._thrust_min), 1.0)))

    def _stop_offboard_tasks(self, reason: str) -> None:
        self._guard_stop.set()
        if self._offboard_active:
            self._offboard_active = False
            self._offboard_end_reason = reason
        for t in self._offboard_tasks:
            if t is not asyncio.current_task():
                t.cancel()
        self._offboard_tasks = []

    async def stop_offboard(self, timeout: float | None = None) -> None:
        """Leave OFFBOARD for HOLD (only if the vehicle is still in OFFBOARD: never override the pilot)."""
        from mavsdk.asyncio.plugins.offboard import OffboardError

        timeout = self.cfg.command_timeout if timeout is None else timeout
        self._stop_offboard_tasks("stopped by the app")
        requested, self._offboard_requested = self._offboard_requested, False
        # PX4 may be in OFFBOARD before its 1 Hz heartbeat says so: stop whenever we asked for it, unless the
        # vehicle is seen in a mode that is not ours (the pilot's: never override it).
        if self._flight_mode != "OFFBOARD" and not (requested and self._flight_mode in ("HOLD", "TAKEOFF", None)):
            return
        self.check_link()
        n0 = self._mode_reports
        await self._mapped_call("stop offboard", self._offboard.stop, timeout, OffboardError, CommandDenied,
                                "stop offboard refused")
        self._emit("offboard_stopped")
        await self.wait_mode("HOLD", max(timeout, self.cfg.mode_timeout), after=n0)

    # ------------------------------------------------------------------------------- teardown
    async def close(self, timeout: float | None = None) -> None:
        """Hand over (OFFBOARD -> HOLD), stop the tasks, let in-flight commands end, then destroy mavsdk.

        mavsdk's destroy() while a command still waits for its ACK can hang the process for good,
        so if commands are still in flight after ``timeout`` the instance is leaked instead.
        """
        if self._closed:
            return
        self._closed = True
        timeout = self.cfg.command_timeout + 2.0 if timeout is None else timeout
        if (self._offboard_active or self._offboard_requested) and self.link_ok:
            with contextlib.suppress(Exception):
                await self.stop_offboard(min(timeout, 3.0))
        self._stop_offboard_tasks("link closed")
        for t in self._tasks:
            t.cancel()
        if self._tasks:
            await asyncio.wait(self._tasks, timeout=2.0)
        self._tasks = []
        if self._inflight:
            await asyncio.wait(set(self._inflight), timeout=timeout)
        deadline = time.monotonic() + timeout
        while self._guard_busy and time.monotonic() < deadline:  # the loop guard's blocking stop()
            await asyncio.sleep(self.POLL)
        if self._mavsdk is not None:
            if self._inflight or self._guard_busy:
                self._emit("close_leaked", inflight=len(self._inflight))
            else:
                self._mavsdk.destroy()
        self._system = None
        self._emit("closed")
