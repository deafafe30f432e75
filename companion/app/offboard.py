"""Offboard attitude streaming for the vehicle link: the envelope, the resends, the watchdog, the loop guard.

``VehicleLink`` (companion/app/link.py) gets ``start_offboard``, ``set_setpoint`` and ``stop_offboard`` from
``OffboardStreaming``. Every setpoint passes the last-line envelope (companion/app/envelope.py) first. While
offboard is active the latest setpoint is resent at ``link.setpoint_rate`` and a watchdog stops offboard
(PX4 -> HOLD) when no fresh ``set_setpoint`` came for ``safety.perception_stall_timeout``: MAVSDK itself
resends the last setpoint at ~20 Hz for as long as the process lives, so PX4's own offboard-loss failsafe
never fires if the control task dies. A guard thread backs the watchdog up when the event loop itself
stalls (2x the limit + 0.2 s). When the vehicle leaves OFFBOARD on its own (pilot takeover, PX4 failsafe)
the link never re-enters it.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import math
import threading
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

from companion.app.envelope import SetpointEnvelope
from companion.app.linkerrors import CommandDenied, LinkError, OffboardDenied, OffboardLost, SetpointRejected
from companion.config_app import LinkConfig
from companion.vehicle import SetpointLike

# s after the app resumes from a stall during which the datagrams queued in the socket (an old mode, old
# attitudes) are read: only a heartbeat after that shows what PX4 does now.
STALE_DRAIN_S = 0.25


@dataclass(frozen=True)
class _Sp:
    roll_deg: float
    pitch_deg: float
    yaw_deg: float
    thrust: float



class OffboardStreaming:
    """The offboard half of ``VehicleLink`` (a mixin: it runs on the link's own state and calls).

    From the link it uses ``cfg``, the mavsdk Offboard plugin ``_offboard``, the telemetry caches
    ``_flight_mode``, ``_mode_reports``, ``_status_text``, ``_hover_value``, and ``_emit``, ``_call``,
    ``_mapped_call``, ``_wait_until``, ``check_link``, ``wait_mode``.
    """

    cfg: LinkConfig
    _offboard: Any
    _flight_mode: str | None
    _mode_reports: int
    _status_text: str | None
    _hover_value: float
    _emit: Callable[..., None]
    _call: Callable[..., Awaitable[Any]]
    _mapped_call: Callable[..., Awaitable[None]]
    _wait_until: Callable[..., Awaitable[None]]
    check_link: Callable[[], None]
    wait_mode: Callable[..., Awaitable[None]]

    def _init_offboard(self, *, thrust_min: float, setpoint_timeout: float, max_tilt_deg: float) -> None:
        self._thrust_min = float(thrust_min)
        self._setpoint_timeout = float(setpoint_timeout)
        self.envelope = SetpointEnvelope(max_tilt_deg, thrust_min)
        self._clamps = 0
        self._last_clamp_event = -math.inf
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

        tick = min(0.05, self._setpoint_timeout / 4)
        last = time.monotonic()
        resumed: tuple[int, float] | None = None
        while self._offboard_active:
            if self._flight_mode != "OFFBOARD":
                await self._left_offboard(f"vehicle left OFFBOARD, now {self._flight_mode}")
                return
            now = time.monotonic()
            if now - last > self._setpoint_timeout + tick:
                # We did not run (a stopped process, a stalled loop): PX4's offboard-loss failsafe may have taken
                # the vehicle meanwhile. A fresh heartbeat first, never a Hold over that failsafe blind.
                resumed = (-1, now)
            last = now
            if resumed is not None:
                n0, t0 = resumed
                if now - t0 < STALE_DRAIN_S:  # what waited in the socket meanwhile is old news: let it pass first
                    await asyncio.sleep(tick)
                    continue
                if n0 < 0:
                    resumed = n0, t0 = (self._mode_reports, t0)
                if self._mode_reports <= n0 and now - t0 < STALE_DRAIN_S + self.cfg.mode_timeout:
                    await asyncio.sleep(tick)
                    continue
            resumed = None
            age = now - self._last_fresh
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
            await asyncio.sleep(tick)

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
            last = woke = time.monotonic()
            while not stop.wait(0.05):
                now = time.monotonic()
                if now - last > limit / 2:
                    # This thread did not run either: the process was stopped, not only its loop. The loop gets
                    # the full limit from now to see (a fresh heartbeat) what PX4 did meanwhile.
                    woke = now
                last = now
                if self._offboard_active:
                    age = now - max(self._last_fresh, woke)
                elif self._switch_pending:  # no fresh setpoint is due yet: the loop's own beat
                    age = now - max(self._last_fresh, self._switch_beat, woke)
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
