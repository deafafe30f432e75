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
from companion.app.offboard import STALE_DRAIN_S
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
            self._link_or_stall(float(detail.get("age", 0.0)))
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
            stall = self._note_gap()
            if not self._connected:
                continue
            st = self.sm.state
            if (stall > self.cfg.link.link_lost_timeout and self._fault is None and not st.offboard
                    and st not in GROUND_STATES and not st.terminal):
                # We did not run as long as a lost link takes: whatever PX4 flies for us (take-off, Hold, landing)
                # went on unwatched. Named as the app's stall (not "no telemetry": the link was not at fault).
                self.trip(Reason.PERCEPTION_STALL, f"the app stalled: it did not run for {stall:.1f} s "
                          f"(during {st.value}; not a link loss)")
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
            self._link_or_stall(link.telemetry_age)
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

    def _note_gap(self) -> float:
        """One monitor tick: remember gaps in telemetry (the link) and in our own loop (nothing sent meanwhile);
        returns how long this loop did not run before this tick."""
        now = self.clock()
        stall = self._own_stall(now)
        self._last_tick = now
        if stall > 0.3:
            self._stalls = [(t, g) for t, g in getattr(self, "_stalls", []) if now - t < GAP_MEMORY_S] + [(now, stall)]
        gap = max(self.link.telemetry_age if self._connected else 0.0, stall)
        if gap > 0.3:
            self._gaps = [(t, g) for t, g in getattr(self, "_gaps", []) if now - t < GAP_MEMORY_S] + [(now, gap)]
        return stall

    def _own_stall(self, now: float) -> float:
        """How long this loop has not run (0 when it ticks every 50 ms): a stalled loop or a stopped process."""
        last = getattr(self, "_last_tick", None)
        return max(now - last - 0.05, 0.0) if last is not None else 0.0

    def _recent_gap(self) -> float:
        """The longest gap of the last GAP_MEMORY_S, counting a loop stall still under way (now)."""
        now = self.clock()
        gaps = [g for t, g in getattr(self, "_gaps", []) if now - t < GAP_MEMORY_S]
        return max([*gaps, self._own_stall(now), 0.0])

    def _recent_stall(self) -> float:
        now = self.clock()
        stalls = [g for t, g in getattr(self, "_stalls", []) if now - t < GAP_MEMORY_S]
        return max([*stalls, self._own_stall(now), 0.0])

    def _link_or_stall(self, age: float) -> None:
        """Telemetry is old: the link's fault, or our own (the app did not run, so it read nothing: a frozen
        process, a stalled loop). Named for what it is; either way the flight ends."""
        stall = self._recent_stall()
        if stall > 0.3 and stall >= age - 0.5:
            if self.sm.state.offboard:
                return  # the setpoint watchdog decides on a fresh heartbeat (PX4's failsafe may have acted)
            self.trip(Reason.PERCEPTION_STALL, f"the app stalled: it did not run for {stall:.1f} s (telemetry "
                      f"{age:.1f} s old is the app's own pause, not a link loss)")
        else:
            self.trip(Reason.LINK_LOST, f"no telemetry for {age:.1f} s")

    async def _watchdog(self) -> None:
        """No fresh setpoint while we own the vehicle -> hand over (MAVSDK keeps resending the old one).

        After the app itself did not run (a stopped process, a stalled loop) the vehicle may no longer be ours:
        PX4's offboard-loss failsafe acts after COM_OF_LOSS_T. Then a fresh heartbeat decides, before any Hold of
        ours is commanded over that failsafe: still OFFBOARD -> the stall is named and handed over to Hold;
        another mode -> who took it (PX4's failsafe, or a pilot) is named and we stop commanding.
        """
        limit = self.cfg.safety.perception_stall_timeout
        tick = min(0.05, limit / 4)
        last = self.clock()
        resumed: tuple[int, float, float] | None = None  # (heartbeats seen, when, how long we did not run)
        while not self.sm.done:
            await asyncio.sleep(tick)
            now = self.clock()
            if self._deadman is not None:
                self._deadman.beat()  # the loop runs: the deadman thread stays quiet
            paused, last = now - last - tick, now
            if not (self.sm.state.offboard and self._fault is None):
                continue
            if paused > limit and self._connected:
                resumed = (-1, now, paused)
            if resumed is not None:
                n0, t0, gap = resumed
                if now - t0 < STALE_DRAIN_S:
                    continue  # the datagrams queued while we did not run are old news: read them first
                if n0 < 0:
                    resumed = n0, t0, gap = (self.link.mode_reports, t0, gap)
                if self.link.mode_reports <= n0 and now - t0 < STALE_DRAIN_S + self.cfg.link.mode_timeout:
                    continue  # no heartbeat since we woke: what PX4 does now is not known yet
                resumed = None
                mode = self.link.flight_mode
                if mode == "OFFBOARD":
                    self.trip(Reason.PERCEPTION_STALL, f"the app stalled: it did not run for {gap:.1f} s; PX4 "
                              "still in OFFBOARD: handing over to Hold")
                else:
                    who, why = self._who_changed_mode(str(mode))
                    self.trip(who, f"the app did not run for {gap:.1f} s; the vehicle is in {mode}"
                              + (f": {why}" if why else ""))
                continue
            age = now - self._last_setpoint
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
