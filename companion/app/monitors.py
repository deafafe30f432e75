"""The monitors around a flight's sequence: telemetry (logs it; link loss, disarm, a mode nobody asked for),
the setpoint watchdog, the status line and systemd notifications, and the link's events.

A part of the flight app (companion/app/flight.py ``FlightApp``): each finding calls ``trip(reason, detail)``, and
the first one wins.
"""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.app.notify import Notifier
from companion.app.states import EXPECTED_MODES, GROUND_STATES, PILOT_MODES, Reason, State

if TYPE_CHECKING:
    from companion.app.deadman import LoopDeadman
    from companion.app.states import StateMachine
    from companion.config import Config
    from companion.flightlog import FlightLog


# s a gap in the link or in our loop is remembered: PX4's heartbeat (1 Hz) shows its failsafe mode up to 1 s after the
# failsafe, which acts COM_OF_LOSS_T after the gap began.
GAP_MEMORY_S = 5.0


class Monitors:
    """The monitor half of ``FlightApp`` (a mixin: it works on the app's state machine, link, log and config)."""

    cfg: Config
    link: Any
    log: FlightLog
    sm: StateMachine
    notifier: Notifier
    stderr: Any
    status_line: bool
    _tty: bool
    _connected: bool
    _fault: Any
    _deadman: LoopDeadman | None
    _last_setpoint: float
    _offboard_start: asyncio.Task | None

    def on_link_event(self, kind: str, detail: dict[str, Any]) -> None:
        """Every link event goes to the log; the ones that end a flight trip the state machine.

        PX4's own words (events, STATUSTEXT) of warning level or worse go to stderr too.
        """
        if kind in ("px4_event", "status_text"):
            level = str(detail.get("level", detail.get("type", "")))
            severe = bool(detail.get("severe", level.lower() in ("emergency", "alert", "critical", "error",
                                                                 "warning")))
            self.log.event(f"PX4 {level}: {detail.get('text')}", "warn" if severe else "info")
            if severe and self.stderr is not None:
                print(f"companion: PX4 {level}: {detail.get('text')}", file=self.stderr, flush=True)
            if str(detail.get("name", "")).startswith("commander_failsafe"):
                self._px4_failsafe_said = str(detail.get("text"))  # PX4's own word that a failsafe acted
            return
        self.log.event(f"link {kind} {detail}" if detail else f"link {kind}", "warn" if kind in (
            "watchdog", "loop_guard", "loop_guard_stop", "offboard_lost", "link_lost", "close_leaked",
            "telemetry_error", "telemetry_rejected", "telemetry_invalid", "envelope", "exposed") else "info")
        if kind in ("watchdog", "loop_guard"):  # the link's setpoint watchdog / loop guard: our output stopped
            self.trip(Reason.PERCEPTION_STALL, f"link watchdog: no fresh setpoint for {detail.get('age', 0):.2f} s")
        elif kind == "offboard_lost":  # PX4 left OFFBOARD by itself: the pilot or a PX4 failsafe has it
            mode = str(detail.get("mode"))
            who, why = self._who_changed_mode(mode)
            self.trip(who, f"vehicle left OFFBOARD for {mode}" + (f": {why}" if why else ""))
        elif kind == "link_lost":
            self.trip(Reason.LINK_LOST, f"no telemetry for {detail.get('age', 0):.1f} s")
        elif kind == "telemetry_invalid":
            self.trip(Reason.TELEMETRY_INVALID, f"{detail.get('count')} {detail.get('what')} samples rejected "
                      f"within 1 s (last: {detail.get('why')})")
        elif kind == "envelope" and detail.get("action") == "clamped" and self.stderr is not None:
            print(f"companion: setpoint envelope: {detail.get('why')}", file=self.stderr, flush=True)

    async def _monitor(self) -> None:
        """Telemetry to the log at 20 Hz; pilot takeover while PX4 flies its own modes for us.

        Link loss, the link's setpoint watchdog and PX4 leaving OFFBOARD arrive as link events
        (``on_link_event``); the link also refuses setpoints after any of them.
        """
        while not self.sm.done:
            await asyncio.sleep(0.05)
            self._note_gap()
            if not self._connected:
                continue
            self._log_telemetry()
            self._check_vehicle()

    def _check_vehicle(self) -> None:
        """What telemetry shows, in every state: link loss, disarm in the air, a mode nobody here asked for.

        Runs every 50 ms (the monitor) and before an exception is classified, so a takeover that made a
        command fail is named as the takeover. PX4 reports mode and arming at 1 Hz; the 0.5 s budget
        counts from the heartbeat that shows them.
        """
        if not self._connected or self.sm.done or self._fault is not None:
            return
        st, link = self.sm.state, self.link
        mode, armed = link.flight_mode, link.armed
        if not link.link_ok:
            self.trip(Reason.LINK_LOST, f"no telemetry for {link.telemetry_age:.1f} s")
            return
        pilot_start = self.cfg.app.start == "pilot"
        airborne_state = st not in GROUND_STATES and st not in (State.WAIT_PILOT, State.LAND)
        if airborne_state and armed is False:
            self.trip(Reason.DISARMED, f"vehicle disarmed during {st.value} (mode {mode}, landed state "
                      f"{link.landed_state})")
            return
        expected = EXPECTED_MODES.get(st)
        if expected is None or mode is None or mode in expected or armed is False:
            return
        if pilot_start and (st is State.ACQUIRE or (st is State.ENGAGE and not link.offboard_active)):
            return  # the pilot flies in a mode of the pilot's choosing until PX4 confirms OFFBOARD
        if st.offboard and self._offboard_start is not None and not self._offboard_start.done():
            return  # PX4 is switching to OFFBOARD (the frame loop runs on); a refusal ends the start with its error
        if st.offboard and link.offboard_active:
            return  # the link's own offboard watchdog reports it (offboard_lost) and stops commanding first
        who, why = self._who_changed_mode(mode) if st.offboard else (
            Reason.PILOT_TAKEOVER if mode in PILOT_MODES else Reason.AUTOPILOT_MODE, "")
        self.trip(who, f"flight mode changed to {mode} during {st.value}" + (f": {why}" if why else ""))

    def _who_changed_mode(self, mode: str) -> tuple[Reason, str]:
        """A mode we did not command while we flew offboard: the pilot's, or PX4's offboard-loss failsafe after a
        gap in our setpoints (a link drop, our own loop stalled) or PX4's failsafe event. The failsafe's mode may be
        a pilot mode (Position) with no pilot at all; naming it "pilot" would tell the operator someone flies."""
        from companion.app.failsafe import offboard_loss_explains

        if mode not in PILOT_MODES:
            return Reason.AUTOPILOT_MODE, ""
        why = offboard_loss_explains(mode, self._recent_gap(), getattr(self, "_failsafe_values", {}),
                                     getattr(self, "_px4_failsafe_said", None))
        if why is None:
            return Reason.PILOT_TAKEOVER, ""
        self._px4_failsafe = why
        return Reason.AUTOPILOT_MODE, why

    def _note_gap(self) -> None:
        """One monitor tick: remember gaps in telemetry (the link) and in our own loop (nothing sent meanwhile)."""
        now = self.clock()
        last = getattr(self, "_last_tick", None)
        self._last_tick = now
        gap = max(self.link.telemetry_age if self._connected else 0.0, (now - last - 0.05) if last else 0.0)
        if gap > 0.3:
            self._gaps = [(t, g) for t, g in getattr(self, "_gaps", []) if now - t < GAP_MEMORY_S] + [(now, gap)]

    def _recent_gap(self) -> float:
        """The longest gap of the last GAP_MEMORY_S, counting a loop stall still under way (now)."""
        now = self.clock()
        last = getattr(self, "_last_tick", None)
        gaps = [g for t, g in getattr(self, "_gaps", []) if now - t < GAP_MEMORY_S]
        return max([*gaps, (now - last - 0.05) if last else 0.0, 0.0])

    async def _watchdog(self) -> None:
        """No fresh setpoint while we own the vehicle -> hand over (MAVSDK keeps resending the old one)."""
        limit = self.cfg.safety.perception_stall_timeout
        while not self.sm.done:
            await asyncio.sleep(min(0.05, limit / 4))
            if self._deadman is not None:
                self._deadman.beat()  # the loop runs: the deadman thread stays quiet
            if self.sm.state.offboard and self._fault is None:
                age = self.clock() - self._last_setpoint
                if age > limit:
                    self.trip(Reason.PERCEPTION_STALL,
                              f"watchdog: no fresh setpoint for {age:.2f} s (limit {limit:.2f} s)")

    def _last_words(self, text: str) -> None:
        """From the deadman thread, the loop being stuck: one event line, then everything to the OS."""
        self.log.event(text, "error")
        self.log.flush()

    async def _status_loop(self) -> None:
        wd = Notifier.watchdog_interval()
        period = min(self.cfg.app.status_interval, wd) if wd else self.cfg.app.status_interval
        next_status = 0.0
        while True:
            self.notifier.watchdog()  # proves the event loop runs; systemd kills us if it stops
            now = self.clock()
            if now >= next_status:
                next_status = now + self.cfg.app.status_interval
                text = self._status_text()
                self.notifier.status(text)
                if self.status_line and self.stderr is not None:
                    # One updating line on a terminal; plain lines in a file or the journal.
                    self.stderr.write("\r\x1b[K" + text if self._tty else text + "\n")
                    self.stderr.flush()
            if self.sm.done:
                if self.status_line and self.stderr is not None and self._tty:
                    self.stderr.write("\n")
                return
            await asyncio.sleep(period)

    def _status_text(self) -> str:
        parts = [f"t={self.log.now():5.1f}s", self.sm.state.value]
        if self._connected:
            parts.append(f"mode={self.link.flight_mode}")
            b = self._baro_rel()
            if b is not None:
                parts.append(f"alt={b:5.1f}m")
        out = self._last_out
        if out is not None and self.sm.state.offboard:
            parts.append(f"ctrl={out.mode} thr={out.setpoint.thrust:.2f} ldot={out.lambda_dot:+.2f}")
        if self.stats.latencies_ms:
            parts.append(f"lat_p50={np.median(self.stats.latencies_ms[-60:]):.1f}ms")
        parts.append(f"gates={self.stats.gates_passed}")
        return " ".join(parts)
