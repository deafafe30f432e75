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
    link.position_for_log -> TruthForLog | None  (PX4's EKF position/velocity NED: ONLY for the log and scoring;
                                                  as a truth source: companion.app.telemetry.LinkPositionTruth)
    link.status_text -> str | None (last STATUSTEXT), link.hover_thrust_source ("autopilot"|"config")
    link.events -> list[(t_monotonic, kind, detail)]; on_event(kind, detail) is called for each
    link.px4_events -> decoded PX4 events (companion/app/px4events.py); link.mode_reports -> heartbeats seen
    link.own_ids -> (system id, component id) of the companion itself; link.mavsdk -> the mavsdk instance

Exceptions (companion/app/linkerrors.py): every one derives ``LinkError`` and carries a one-line message
saying what failed and where: ConnectFailed, NotHealthy, ArmDenied, TakeoffFailed, OffboardDenied,
OffboardLost, CommandDenied, CommandTimeout, LinkLost. Telemetry samples: companion/app/telemetry.py. The
declared interface (what the app may use): companion/vehicle.py VehicleTelemetry / VehicleControl.

Setpoints: anything with ``roll_deg, pitch_deg, yaw_deg`` (NED/FRD, absolute yaw) and ``thrust``
(0..1, e.g. ``companion.guidance.Setpoint``), through the last-line envelope (companion/app/envelope.py):
non-finite values raise SetpointRejected (nothing sent), the tilt is clamped to ``airframe.max_tilt`` and
the thrust to ``[thrust_min, 1]`` (never 0), each clamp an ``envelope`` event.

Exposure: URLs that make mavsdk listen on every interface are refused unless
``link.allow_all_interfaces``; only ``link.system_id`` is flown; the attitude is read raw and only from
``link.component_id``, and impossible samples (non-finite, non-unit, time running back, tilt jumps) are
rejected with ``telemetry_rejected`` events, ``telemetry_invalid`` when they persist. PX4 events (EVENT)
are decoded and emitted as ``px4_event``. While offboard is active (companion/app/offboard.py) the link
resends the latest setpoint at ``link.setpoint_rate`` and runs a watchdog: no fresh ``set_setpoint`` for
``safety.perception_stall_timeout`` -> offboard is stopped (PX4 -> HOLD). This matters because
MAVSDK itself resends the last setpoint at ~20 Hz for as long as the process lives, so PX4's own
offboard-loss failsafe never fires if the control task dies. When the vehicle leaves OFFBOARD on its
own (pilot takeover, PX4 failsafe) the link never re-enters it: it stops commanding, swaps the
setpoint MAVSDK keeps resending for a level hover one, and ``set_setpoint`` raises OffboardLost.
A guard thread backs the watchdog up when the event loop itself stalls (2x the limit + 0.2 s).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import math
import time
from collections.abc import Awaitable, Callable
from typing import Any

import numpy as np

from companion.app.linkerrors import (
    ArmDenied,
    CommandDenied,
    CommandTimeout,
    ConnectFailed,
    LinkError,
    LinkLost,
    NotHealthy,
    TakeoffFailed,
    WrongAutopilot,
)
from companion.app.offboard import OffboardStreaming
from companion.app.telemetry import AttitudeSample, BaroSample, ImuSample, TelemetryStreams, TruthForLog
from companion.config_app import LinkConfig


class VehicleLink(TelemetryStreams, OffboardStreaming):
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
        self._init_offboard(thrust_min=thrust_min, setpoint_timeout=setpoint_timeout, max_tilt_deg=max_tilt_deg)
        self._init_telemetry(reject_limit=reject_limit)
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
        self.own_ids: tuple[int, int] | None = None  # the companion's (system id, component id), once connected
        self._tasks: list[asyncio.Task] = []
        self._inflight: set[asyncio.Future] = set()
        self._closed = False

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
    def position_for_log(self) -> TruthForLog | None:
        """PX4's own position/velocity estimate (EKF, LOCAL_POSITION_NED): for the flight log and scoring ONLY.

        The controller never sees it. A caller that wants it as truth wraps it explicitly
        (companion.app.telemetry.LinkPositionTruth); a simulator's ground truth is a separate source.
        """
        return self._position

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
    def mavsdk(self) -> Any:
        """The mavsdk instance (None before connect): for the ground station's command (companion/app/gcsconfirm.py)."""
        return self._mavsdk

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
        mcfg = Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)
        self.own_ids = (int(mcfg.system_id), int(mcfg.component_id))  # ours on MAVLink: a GCS addresses these
        self._mavsdk = Mavsdk(mcfg)
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

        try:
            await self._wait_until(done, timeout, f"takeoff to {altitude_m:.1f} m not finished", TakeoffFailed)
        except TakeoffFailed as e:
            # Where it stopped tells a slow climb from one that never left the ground (PX4 SITL under load).
            alt = self.baro_altitude
            raise TakeoffFailed(f"{e}; {alt:.1f} m above the arming point by the barometer" if alt is not None
                                else str(e)) from None

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
            # PX4's auto-disarm, leaving command_timeout of the budget for our own disarm.
            await self._wait_until(lambda: self._armed is False, min(max(left - self.cfg.command_timeout, 0.0), 5.0),
                                   "auto-disarm")
        except CommandTimeout:
            try:
                await self._call("disarm", self._action.disarm)
            except ActionError as e:
                raise CommandDenied(f"disarm after landing refused: {e.result.name}{self._why()}") from None
            # The arming state comes in PX4's 1 Hz heartbeat: at least mode_timeout to see it, else a disarm that
            # worked is reported failed and the vehicle named ARMED (a 1 s floor missed it; issue #22 on SITL).
            await self._wait_until(lambda: self._armed is False,
                                   max(deadline - time.monotonic(), self.cfg.mode_timeout),
                                   "disarm: accepted but the vehicle is still armed")
        self._emit("landed_and_disarmed")

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
