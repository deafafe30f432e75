"""What every fault does: bring the vehicle to one named safe state that is TRUE of it.

A part of the flight app (companion/app/flight.py ``FlightApp``): HOLD only when PX4 reports HOLD, landed only when
landed and disarmed; otherwise the state names what the autopilot reports. Any exception the sequence raises is
classified into a ``Reason`` (the exit code) here too.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from typing import TYPE_CHECKING, Any

from companion.app import linkerrors as linkmod
from companion.app.atrest import wait_at_rest
from companion.app.camera import CameraFailed
from companion.app.offboard import STALE_DRAIN_S
from companion.app.states import GROUND_STATES, PILOT_MODES, TRANSITIONS, Reason, State
from companion.limits import Abort

if TYPE_CHECKING:
    from companion.app.states import StateMachine
    from companion.config import Config


class SafeEnds:
    """The safe-end half of ``FlightApp`` (a mixin: it works on the app's state machine, link and config)."""

    cfg: Config
    link: Any
    sm: StateMachine
    _last_setpoint: float
    _recent_stall: Any  # Monitors (the other mixin)
    _who_changed_mode: Any
    log: Any

    async def _at_rest(self) -> str:
        """Until PX4's Hold has stopped the vehicle (companion/app/atrest.py); what happened, also an event."""
        a = self.cfg.app
        level, said = await wait_at_rest(self.link, a.land_rest_tilt, a.land_rest_time, a.land_rest_timeout)
        self.log.event(f"landing: {said}", "info" if level else "warn")
        return said

    async def _safe_end(self, fault: Abort) -> None:
        """Bring the vehicle to one named state that is TRUE of it: HOLD only when PX4 reports HOLD, landed
        only when landed and disarmed; otherwise the state names what the autopilot reports."""
        st, r, d = self.sm.state, fault.reason, fault.detail
        self._last_setpoint = math.inf  # the watchdog has nothing more to guard
        if r is Reason.VEHICLE_BUSY and st in GROUND_STATES:
            self.sm.go(State.REFUSED, d, r)
            return
        if st in GROUND_STATES:
            await self._ground_end(d, r)
            return
        if r is Reason.LINK_LOST:
            await self.link.close()
            self.sm.go(State.SAFE_FAILSAFE_LINK, d + "; streaming stopped, PX4's own failsafe acts", r)
            return
        if r in (Reason.PILOT_TAKEOVER, Reason.AUTOPILOT_MODE, Reason.DISARMED):
            # Someone else has the vehicle: no mode change of ours, never offboard again; closing the link
            # ends MAVSDK's resending too.
            await self.link.close()
            self._go_seen(d + "; we stopped commanding", r)
            return
        pilot_start = self.cfg.app.start == "pilot"
        if st.offboard and await self._taken_while_we_stalled(d):
            return
        if st.offboard:
            self.sm.go(State.HANDBACK, d)
            try:
                await self.link.stop_offboard()  # waits until PX4 reports HOLD
            except Exception as e:
                # PX4 did not confirm HOLD: stop MAVSDK's resending so PX4's offboard-loss failsafe acts.
                await self.link.close()
                self.sm.go(State.SAFE_FAILSAFE_LINK, f"{d}; offboard stop failed ({e}): streaming stopped", r)
                return
            st = State.HANDBACK
        elif st in (State.TAKEOFF, State.LAND) or (st is State.ACQUIRE and not pilot_start):
            # PX4 is flying its own take-off, landing or hold for us: command Hold and see it confirmed.
            with contextlib.suppress(Exception):  # after the app itself stalled, telemetry takes a moment to flow
                await self.link.wait_link_ok(self.cfg.link.link_lost_timeout)
            try:
                await self.link.hold()
            except Exception as e:
                await self.link.close()
                self._go_seen(f"{d}; Hold not confirmed ({e}); we stopped commanding", r)
                return
        elif pilot_start:  # ACQUIRE or WAIT_PILOT with the pilot flying: the pilot keeps the vehicle
            await self.link.close()
            self._go_seen(d + "; we never commanded", r)
            return
        if self.cfg.safety.land_after_abort and self.link.flight_mode == "HOLD":
            if st is not State.HANDBACK:
                self.sm.go(State.HANDBACK, d)
            self.sm.go(State.LAND, f"{d}; land_after_abort; {await self._at_rest()}")
            await self.link.land()
            await self.link.wait_landed_and_disarm()
            self._go_seen(d, r)
            return
        self._go_seen(d, r)

    async def _taken_while_we_stalled(self, d: str) -> bool:
        """The app did not run for a while (a stopped process, a stalled loop) just before this fault: PX4's
        offboard-loss failsafe may have the vehicle. Read a fresh heartbeat before commanding anything: a mode
        other than OFFBOARD is named (PX4's failsafe or a pilot) and left alone (True); else False (hand over)."""
        stall = self._recent_stall()
        if stall <= self.cfg.safety.perception_stall_timeout:
            return False
        link, lc = self.link, self.cfg.link
        with contextlib.suppress(Exception):
            await link.wait_link_ok(lc.link_lost_timeout)
            await asyncio.sleep(STALE_DRAIN_S)  # datagrams queued while we did not run are old news
            n0 = link.mode_reports
            await link.wait_until(lambda: link.mode_reports > n0, lc.mode_timeout, "a heartbeat after the stall")
        mode = link.flight_mode
        if mode == "OFFBOARD" or mode is None:
            return False
        who, why = self._who_changed_mode(str(mode))
        await link.close()
        self._go_seen(f"the app did not run for {stall:.1f} s ({d}); the vehicle is in {mode}"
                      + (f": {why}" if why else ""), who)
        return True

    async def _ground_end(self, d: str, r: Reason) -> None:
        """A fault before take-off. "Not armed" only when live telemetry shows it: an ARM command sent into a
        link outage reaches PX4 when the link returns, so after an arm command the app waits for the link and a
        fresh heartbeat, and disarms a vehicle that armed on the ground (PX4 would hold it armed until
        COM_DISARM_PRFLT)."""
        link, lc = self.link, self.cfg.link
        arm_sent = any(h.dst is State.ARM for h in self.sm.history)
        if not arm_sent:
            if link.armed is True:  # armed by someone else meanwhile: say so, never "not armed"
                await link.close()
                self._go_seen(d + "; the vehicle is armed (not by us)", r)
                return
            if not link.link_ok:
                await link.close()
                self.sm.go(State.ABORT_NOT_ARMED, d + "; no arm command was sent", r)
                return
            self.sm.go(State.ABORT_NOT_ARMED, d, r)
            return
        try:
            await link.wait_link_ok(lc.command_timeout + lc.link_lost_timeout)
            n0 = link.mode_reports  # only a heartbeat sent after now shows PX4's arming state after the outage
            await link.wait_until(lambda: link.mode_reports > n0, lc.mode_timeout,
                                  "no heartbeat from the autopilot after the fault")
        except Exception as e:
            await link.close()
            self.sm.go(State.SAFE_FAILSAFE_LINK, (
                f"{d}; link not back ({e}): an arm command was sent, PX4's arming state is unknown (last reported "
                f"armed {link.armed}); an armed vehicle left on the ground is disarmed by PX4 after "
                "COM_DISARM_PRFLT"), r)
            return
        if link.armed is not True:
            self.sm.go(State.ABORT_NOT_ARMED, d + "; PX4 reports not armed", r)
            return
        if link.landed_state not in ("ON_GROUND", "UNKNOWN", None):
            self._go_seen(d + "; the vehicle is armed", r)
            return
        try:
            # PX4's auto-disarm first (1 s), else our disarm command; confirmed by telemetry.
            await link.wait_landed_and_disarm(timeout=1.0 + lc.command_timeout)
        except Exception as e:
            await link.close()
            self._go_seen(f"{d}; PX4 armed on the ground after all and our disarm failed ({e}): the vehicle is "
                          "ARMED; PX4 disarms it by itself after COM_DISARM_PRFLT", r)
            return
        self.sm.go(State.SAFE_LANDED, f"{d}; PX4 armed on the ground after all (the arm command got through); "
                   "disarmed by the app: PX4 reports disarmed, on the ground", r)

    def _go_seen(self, detail: str, reason: Reason) -> None:
        """The terminal state that names what the autopilot last reported."""
        link = self.link
        mode, armed, landed = link.flight_mode, link.armed, link.landed_state
        if armed is False and landed == "ON_GROUND":
            self.sm.go(State.SAFE_LANDED, f"{detail}; landed and disarmed", reason)
        elif armed is False:
            self.sm.go(State.DISARMED, f"{detail}; vehicle disarmed in the air (landed state {landed})", reason)
        elif mode == "HOLD":
            self.sm.go(State.SAFE_HOLD, f"{detail}; PX4 holds", reason)
        elif mode in PILOT_MODES and not getattr(self, "_px4_failsafe", None):
            self.sm.go(State.SAFE_PILOT, f"{detail}; the pilot has the vehicle in {mode}", reason)
        else:
            self.sm.go(State.AUTOPILOT, f"{detail}; PX4 flies in {mode} (armed {armed}, landed state {landed})",
                       reason)

    async def _last_resort(self, fault: Abort, err: BaseException) -> None:
        """The safe end itself failed: stop streaming (PX4's failsafe acts) and name that state."""
        with contextlib.suppress(Exception):
            await asyncio.wait_for(self.link.close(), 10.0)
        detail = f"{fault.detail}; safe end failed ({type(err).__name__}: {err}): streaming stopped"
        if not self.sm.done:
            name_last_resort(self.sm, self.link, detail, fault.reason)

    def _classify(self, e: BaseException) -> Abort:
        text = f"{type(e).__name__}: {e}"
        table: list[tuple[str, Reason]] = [
            ("ArmDenied", Reason.ARM_DENIED), ("OffboardDenied", Reason.OFFBOARD_DENIED),
            ("CommandTimeout", Reason.COMMAND_TIMEOUT), ("LinkLost", Reason.LINK_LOST),
            ("ConnectFailed", Reason.CONNECT_FAILED), ("PreflightFailed", Reason.PREFLIGHT_FAILED),
            ("NotHealthy", Reason.PREFLIGHT_FAILED), ("TakeoffFailed", Reason.COMMAND_TIMEOUT),
            ("OffboardLost", Reason.PILOT_TAKEOVER), ("CommandDenied", Reason.COMMAND_TIMEOUT),
            ("SetpointRejected", Reason.SETPOINT_INVALID),
        ]
        for name, reason in table:
            exc = getattr(linkmod, name, None)
            if isinstance(exc, type) and isinstance(e, exc):
                stall = self._recent_stall()
                if reason is Reason.LINK_LOST and stall > 0.3 and (self.link.link_ok
                                                                   or stall >= self.link.telemetry_age - 0.5):
                    # The telemetry was old because the app did not run (a stopped process), not the link.
                    return Abort(Reason.PERCEPTION_STALL, f"the app stalled: it did not run for {stall:.1f} s "
                                 f"({text}: the app's own pause, not a link loss)")
                return Abort(reason, text)
        if isinstance(e, CameraFailed):
            return Abort(Reason.CAMERA_FAILED, text)
        if isinstance(e, (TimeoutError, ConnectionError)) and self.sm.state is State.CONNECT:
            return Abort(Reason.CONNECT_FAILED, text)
        if isinstance(e, TimeoutError):
            return Abort(Reason.COMMAND_TIMEOUT, text)
        return Abort(Reason.EXCEPTION, text)


def name_last_resort(sm: StateMachine, link: Any, detail: str, reason: Reason) -> None:
    """The safe end itself failed (or an exception escaped the machine): name the first state that the state
    machine accepts as true of the vehicle, from the most to the least specific."""
    from companion.app.states import IllegalTransition

    if sm.state in GROUND_STATES:
        armed = link.armed
        cands = [State.ABORT_NOT_ARMED] if armed is not True else []
        cands += [State.SAFE_FAILSAFE_LINK, State.SAFE_HOLD, State.AUTOPILOT]
        if armed is True:
            detail += f"; the vehicle is ARMED (mode {link.flight_mode}); PX4 disarms it on the ground after " \
                      "COM_DISARM_PRFLT"
    else:
        cands = [State.SAFE_FAILSAFE_LINK]
    for dst in cands:
        if dst in TRANSITIONS[sm.state]:
            with contextlib.suppress(IllegalTransition):
                sm.go(dst, detail, reason)
                return
