"""The flight: camera -> perception -> LOS filter -> controller -> setpoint, under one state machine.

Read ``FlightApp._frame`` top to bottom for the data path of one frame; ``_sequence`` for the
order of a flight; ``_safe_end`` for what every fault does. Around the sequence run three
monitors: telemetry (logs it; detects link loss and pilot takeover), the watchdog (no fresh
setpoint while we own the vehicle -> hand over to HOLD; MAVSDK would otherwise resend the last
setpoint forever) and the status line / systemd notifications.

Any fault calls ``trip(reason, detail)``: the first one wins, the sequence task is cancelled and
``_safe_end`` brings the vehicle to one named safe state (companion/app/states.py), logged
with its reason. Vehicle position/velocity is only logged (truth topic), never used here.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from companion.app import linkerrors as linkmod
from companion.app import preflight
from companion.app.camera import CameraFailed, CameraSource, Frame, Perception
from companion.app.deadman import LoopDeadman
from companion.app.notify import Notifier
from companion.app.outcome import GateJudge, verdict
from companion.app.safety import Abort
from companion.app.states import Reason, State, StateMachine, Transition
from companion.controller import ControlOutput, PNController
from companion.engagement import Decision, Engagement, EngagementParams, Phase
from companion.flightlog import FlightLog
from companion.frames import euler_ned_deg_from_R
from companion.hover import HoverThrustEstimator, use_hover_thrust

if TYPE_CHECKING:
    from companion.config import Config
    from companion.vehicle import TruthSource

GROUND_STATES = frozenset({State.INIT, State.CONNECT, State.PREFLIGHT, State.ARM})
# Modes a pilot selects (mavsdk FlightMode names); any other mode we did not ask for is PX4's own choice.
PILOT_MODES = frozenset({"POSCTL", "ALTCTL", "MANUAL", "STABILIZED", "ACRO", "RATTITUDE"})
# Modes the vehicle may show while the app is in a state; anything else is noticed (companion/app/states.py).
EXPECTED_MODES: dict[State, frozenset[str]] = {
    State.TAKEOFF: frozenset({"TAKEOFF", "HOLD"}),
    State.ACQUIRE: frozenset({"HOLD"}),
    State.ENGAGE: frozenset({"HOLD", "OFFBOARD"}),  # HOLD until PX4 confirms OFFBOARD at the first engage
    State.PASS: frozenset({"OFFBOARD"}),
    State.RECOVER: frozenset({"OFFBOARD"}),
    State.HANDBACK: frozenset({"OFFBOARD", "HOLD"}),
    State.LAND: frozenset({"LAND", "HOLD"}),  # HOLD until PX4 shows the LAND we commanded
}


class _ClearLine:
    """A text stream that clears the terminal line (the live status line) before each message."""

    def __init__(self, inner: TextIO) -> None:
        self.inner = inner

    def write(self, text: str) -> int:
        return self.inner.write(("\r\x1b[K" + text) if text.strip() else text)

    def flush(self) -> None:
        self.inner.flush()


class _Tripped(Exception):
    """Raised inside the sequence for an abort it finds itself (safety limit, no target)."""

    def __init__(self, abort: Abort) -> None:
        super().__init__(abort.detail)
        self.abort = abort


@dataclass
class FlightStats:
    latencies_ms: list[float] = field(default_factory=list)  # frame available -> setpoint sent
    frames: int = 0
    setpoints: int = 0
    gates_passed: int = 0
    cpu_s: float = 0.0
    wall_s: float = 0.0


class FlightApp:
    def __init__(
        self,
        cfg: Config,
        link: Any,
        camera: CameraSource,
        perception: Perception,
        log: FlightLog,
        *,
        notifier: Notifier | None = None,
        stderr: TextIO | None = sys.stderr,
        status_line: bool = False,
        perception_in_thread: bool = False,
        judge: GateJudge | None = None,
        confirm: preflight.Confirm | None = None,
        truth: TruthSource | None = None,
    ) -> None:
        self.cfg = cfg
        self.link = link
        self.camera = camera
        self.perception = perception
        self.log = log
        self.notifier = notifier or Notifier(address="")
        self.stderr = stderr
        self.status_line = status_line
        self.perception_in_thread = perception_in_thread
        self.judge = judge  # ground truth (simulators only): scores the gates, never steers
        self.truth = truth  # where the vehicle is: the truth topic and the judge only, never the controller
        self._verdict: str | None = None  # the normal end's outcome line (companion/app/outcome.py)
        self.confirm = confirm  # asks the operator to confirm the pre-flight summary; None: do not ask
        self.clock = time.monotonic
        # With a live status line, a state message first clears the line it would otherwise append to.
        self._tty = bool(stderr is not None and getattr(stderr, "isatty", lambda: False)())
        sm_err = _ClearLine(stderr) if status_line and self._tty else stderr
        self.sm = StateMachine(clock=log.now, sinks=[self._on_transition], stderr=sm_err)
        self.ctrl = PNController.from_config(cfg)
        self.width, self.height = cfg.camera.width, cfg.camera.height
        self.engagement: Engagement | None = None  # made when the frame loop starts (the hover thrust is known)
        self.stats = FlightStats()
        self._fault: Abort | None = None
        self._seq: asyncio.Task[None] | None = None
        self._last_setpoint = math.inf  # clock time of the last fresh setpoint (inf: none owed)
        self._offboard_start: asyncio.Task | None = None  # PX4's switch to OFFBOARD, while it is under way
        self._baro0: float | None = None
        self._connected = False
        self._last_out: ControlOutput | None = None
        self._deadman: LoopDeadman | None = None
        self._hover: HoverThrustEstimator | None = None  # hover.estimate (companion/hover.py)
        self._hover_u: float | None = None
        self._hover_logged: float | None = None

    # ------------------------------------------------------------------------------ public
    def trip(self, reason: Reason, detail: str) -> None:
        """Report a fault (from a monitor, a signal handler, ...). The first one wins."""
        if self._fault is not None or self.sm.done:
            return
        self._fault = Abort(reason, detail)
        self.log.event(f"fault {reason.name}: {detail}", "error")
        if self._seq is not None and not self._seq.done():
            self._seq.cancel()

    def _check_fault(self) -> None:
        """Raise the tripped fault inside the sequence.

        trip() also cancels the sequence task, but Python 3.11's asyncio.wait_for (used by the link for
        every mavsdk call) can swallow a cancellation that races with the call's completion: the fault
        must not depend on it, so the sequence checks at every step too.
        """
        if self._fault is not None:
            raise _Tripped(self._fault)

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
            return
        self.log.event(f"link {kind} {detail}" if detail else f"link {kind}", "warn" if kind in (
            "watchdog", "loop_guard", "loop_guard_stop", "offboard_lost", "link_lost", "close_leaked",
            "telemetry_error", "telemetry_rejected", "telemetry_invalid", "envelope", "exposed") else "info")
        if kind in ("watchdog", "loop_guard"):  # the link's setpoint watchdog / loop guard: our output stopped
            self.trip(Reason.PERCEPTION_STALL, f"link watchdog: no fresh setpoint for {detail.get('age', 0):.2f} s")
        elif kind == "offboard_lost":  # PX4 left OFFBOARD by itself: the pilot or a PX4 failsafe has it
            mode = str(detail.get("mode"))
            self.trip(Reason.PILOT_TAKEOVER if mode in PILOT_MODES else Reason.AUTOPILOT_MODE,
                      f"vehicle left OFFBOARD for {mode}")
        elif kind == "link_lost":
            self.trip(Reason.LINK_LOST, f"no telemetry for {detail.get('age', 0):.1f} s")
        elif kind == "telemetry_invalid":
            self.trip(Reason.TELEMETRY_INVALID, f"{detail.get('count')} {detail.get('what')} samples rejected "
                      f"within 1 s (last: {detail.get('why')})")
        elif kind == "envelope" and detail.get("action") == "clamped" and self.stderr is not None:
            print(f"companion: setpoint envelope: {detail.get('why')}", file=self.stderr, flush=True)

    async def run(self) -> Reason:
        cpu0, wall0 = time.process_time(), self.clock()
        deadman = LoopDeadman(self.cfg.safety.loop_stall_timeout, lambda: self.sm.state.offboard,
                              self._last_words).start()
        self._deadman = deadman
        monitors = [asyncio.create_task(self._monitor(), name="telemetry-monitor"),
                    asyncio.create_task(self._watchdog(), name="watchdog"),
                    asyncio.create_task(self._status_loop(), name="status")]
        self.notifier.ready("connecting")
        self._seq = asyncio.create_task(self._sequence(), name="flight-sequence")
        try:
            await self._seq
        except asyncio.CancelledError:
            if self._fault is None:  # cancelled from outside (not by trip): treat as a signal
                self._fault = Abort(Reason.SIGNAL, "flight task cancelled")
        except _Tripped as e:
            self._fault = self._fault or e.abort
        except Exception as e:  # (any exception ends in a safe state, with its text)
            self._check_vehicle()  # a takeover or disarm seen in telemetry explains it better than the exception
            self._fault = self._fault or self._classify(e)
        if not self.sm.done:
            fault = self._fault or Abort(Reason.EXCEPTION, "flight sequence ended without a safe state")
            self.log.event(f"safe end from {self.sm.state.value}: {fault.reason.name}", "error")
            try:
                await asyncio.wait_for(self._safe_end(fault), self.cfg.link.command_timeout * 3 + 5.0)
            except Exception as e:
                await self._last_resort(fault, e)
        if self._connected:
            self._log_telemetry()  # the vehicle as we leave it (the monitor samples only every 50 ms)
        self.notifier.stopping(self._status_text())
        for m in monitors:
            m.cancel()
        await asyncio.gather(*monitors, return_exceptions=True)
        deadman.stop()
        self.camera.close()
        self.stats.cpu_s = time.process_time() - cpu0
        self.stats.wall_s = self.clock() - wall0
        assert self.sm.outcome is not None
        return self.sm.outcome

    def summary(self) -> dict[str, Any]:
        lat = np.array(self.stats.latencies_ms)
        last = self.sm.history[-1] if self.sm.history else None
        return {
            "outcome": self.sm.state.value,
            "reason": self.sm.outcome.name if self.sm.outcome is not None else None,
            "exit_code": int(self.sm.outcome) if self.sm.outcome is not None else None,
            "detail": last.reason if last else "",
            "gates_passed": self.stats.gates_passed,
            "passes": [g.as_dict() for g in self.engagement.passes] if self.engagement is not None else [],
            "truth": self._truth_summary(),
            "verdict": self._verdict,
            "frames": self.stats.frames,
            "setpoints": self.stats.setpoints,
            "frame_to_setpoint_ms": {"p50": float(np.percentile(lat, 50)) if lat.size else None,
                                     "p95": float(np.percentile(lat, 95)) if lat.size else None, "n": int(lat.size)},
            "cpu_percent": 100.0 * self.stats.cpu_s / self.stats.wall_s if self.stats.wall_s > 0 else None,
            "states": [h.dst.value for h in self.sm.history],
        }

    def _truth_summary(self) -> dict[str, Any] | None:
        """Each gate against ground truth (None in the field: no truth)."""
        if self.judge is None or not self.judge.has_truth:
            return None
        gates = self.judge.results()
        return {"gates": [g.as_dict() for g in gates], "through": sum(g.through for g in gates),
                "missed": sum(g.crossed and not g.through for g in gates)}

    # ------------------------------------------------------------------------------ sequence
    async def _sequence(self) -> None:
        cfg = self.cfg
        self.sm.go(State.CONNECT, f"connecting to {cfg.link.url}")
        await self.link.connect()
        self._connected = True
        self._check_fault()
        self.sm.go(State.PREFLIGHT, "autopilot found")
        await self._vehicle_as_found()
        await self.link.wait_healthy()
        hover = await self.link.hover_thrust()
        self._check_fault()
        await self._check_failsafe_params()
        if hover is not None and 0.05 < hover < 0.95:
            self.ctrl = self.ctrl.with_hover_thrust(hover, cfg.airframe.thrust_to_weight)
            self.log.event(f"hover thrust {hover:.3f} from MPC_THR_HOVER")
        ref = cfg.safety.altitude_reference  # an app started in the air is told where the ground is
        self._baro0 = self._baro_raw() if ref is None else ref  # on the ground: the altitude floor is above this
        not_confirmed = await preflight.run(self, self.confirm)  # summary + operator's yes before arming
        self._check_fault()
        if not_confirmed is not None:
            raise _Tripped(Abort(Reason.NOT_CONFIRMED, not_confirmed))
        if cfg.app.start == "takeoff":
            self.sm.go(State.ARM, "preflight checks passed")
            await self.link.arm()
            self._check_fault()
            self.sm.go(State.TAKEOFF, f"armed; take-off to {cfg.app.takeoff_altitude:.1f} m")
            await self.link.takeoff(cfg.app.takeoff_altitude)
            self._check_fault()
            self.sm.go(State.ACQUIRE, "take-off done, PX4 holds")
        else:
            self.sm.go(State.WAIT_PILOT, "waiting for the pilot to hover")
            await self._wait_pilot_hover()
            self._check_fault()
            self.sm.go(State.ACQUIRE, "pilot hovers armed in the air")
        await self._fly()

    async def _vehicle_as_found(self) -> None:
        """PX4's rules before we command anything: never arm or take off a vehicle that is armed or flying
        (start=takeoff), and put one found disarmed in OFFBOARD (after an offboard-loss landing) in HOLD,
        without which PX4 1.15 refuses its pre-flight checks."""
        link = self.link
        await link.wait_until(lambda: link.armed is not None and link.landed_state is not None
                              and link.flight_mode is not None, self.cfg.link.mode_timeout + 2.0,
                              "no heartbeat and landed state from the autopilot")
        self._check_fault()
        airborne = link.landed_state not in ("ON_GROUND", "UNKNOWN")
        if self.cfg.app.start == "takeoff" and (link.armed or airborne):
            raise _Tripped(Abort(Reason.VEHICLE_BUSY, (
                f"vehicle found {'armed' if link.armed else 'disarmed'}, landed state {link.landed_state}, mode "
                f"{link.flight_mode}: refusing to arm or take off (app.start=pilot flies a vehicle in the air)")))
        if link.armed is False and link.flight_mode == "OFFBOARD":
            self.log.event("vehicle found disarmed in OFFBOARD (after an offboard-loss landing): commanding HOLD",
                           "warn")
            await link.hold()
            self._check_fault()
            self.log.event("HOLD confirmed; pre-flight checks can pass again")

    async def _check_failsafe_params(self) -> None:
        """Read and report what PX4 does if the app dies; refuse when offboard loss would not end safely."""
        from companion.app.failsafe import judge

        values = await self.link.failsafe_params(timeout=min(self.cfg.link.command_timeout, 3.0))
        self._check_fault()
        line, problems = judge(values, self.cfg.safety.max_offboard_loss_time)
        self.log.event(line, "warn" if problems else "info")
        if self.stderr is not None:
            print(f"companion: {line}", file=self.stderr, flush=True)
        if problems:
            text = "; ".join(problems)
            if self.cfg.safety.require_safe_offboard_loss:
                raise _Tripped(Abort(Reason.UNSAFE_FAILSAFE, f"{text} (safety.require_safe_offboard_loss)"))
            self.log.event(f"failsafe not safe, flying anyway (safety.require_safe_offboard_loss false): {text}",
                           "warn")

    async def _wait_pilot_hover(self) -> None:
        """Armed, in the air, above the altitude floor, not in an automatic take-off or landing, for 1 s."""
        deadline = self.clock() + self.cfg.app.pilot_wait_timeout
        link = self.link
        since: float | None = None
        while True:
            alt = self._baro_rel()
            hovering = (link.armed and link.landed_state == "IN_AIR" and link.flight_mode not in ("TAKEOFF", "LAND")
                        and (alt is None or alt > self.cfg.safety.altitude_floor))
            since = (since or self.clock()) if hovering else None
            if since is not None and self.clock() - since >= 1.0:
                return
            self._check_fault()
            if self.clock() > deadline:
                raise _Tripped(Abort(Reason.NO_TARGET, f"the pilot did not hover within "
                                     f"{self.cfg.app.pilot_wait_timeout:.0f} s"))
            await asyncio.sleep(0.1)

    async def _fly(self) -> None:
        """The frame loop: each frame's box goes to the engagement core (companion/engagement.py), which
        decides ACQUIRE -> ENGAGE -> PASS -> RECOVER (-> ENGAGE ...) -> HANDBACK, or an abort; here only I/O:
        camera, perception, the setpoint to PX4, the state machine and the log."""
        p = self.ctrl.p
        params = EngagementParams.from_config(self.cfg, hover_thrust=p.hover_thrust, f_min=p.guidance.f_min,
                                              f_max=p.guidance.f_max)
        self.engagement = eng = Engagement.from_config(self.cfg, self.ctrl, params)
        try:
            await self._frame_loop(eng)
        finally:
            await self._cancel_offboard_start()

    async def _frame_loop(self, eng: Engagement) -> None:
        while True:
            self._check_fault()
            frame = await self.camera.read()
            t_avail = self.clock()
            box = await self._perceive(frame)
            self._check_fault()
            valid = box is not None and box.is_valid(self.width, self.height)
            self.stats.frames += 1
            self._log_detection(frame, box, valid)
            if self._switching_to_offboard():
                continue  # perceived and logged (the tracker keeps the gate); PX4 does not fly our setpoints yet
            imu = self.link.imu  # the newest accelerometer sample (50 Hz) for the controller's closing speed
            d = eng.step(frame.t, box, self._attitude_at(frame.t), self._baro_rel(),
                         accel_frd=imu.accel_frd if imu is not None else None, t_now=t_avail)
            if d.control is not None:
                self._last_out = d.control
            for ev in d.events:
                self.log.event(ev)
            self.stats.gates_passed = eng.passes_confirmed
            if await self._apply(frame, d, t_avail):
                return

    async def _apply(self, frame: Frame, d: Decision, t_avail: float) -> bool:
        """Carry out one decision; True when the flight's normal end has been reached."""
        if d.phase is Phase.ACQUIRE:
            return False  # PX4 holds; nothing to send
        if d.phase is Phase.LAND:
            await self._land_normally(Reason.NO_TARGET, d.why, State.LAND)
            return True
        if d.phase is Phase.HANDBACK:
            reason, why = self._outcome(d)
            await self._land_normally(reason, why, State.HANDBACK)
            return True
        if d.phase is Phase.ABORT:
            assert d.reason is not None
            raise _Tripped(Abort(d.reason, d.why))
        assert d.setpoint is not None
        first = d.previous is Phase.ACQUIRE
        if d.changed:
            self.sm.go(State(d.phase.value), d.why)
            if d.phase is Phase.RECOVER:
                reset = getattr(self.perception, "reset", None)
                if reset is not None:
                    reset()  # the tracker must not hold on to (or coast) the gate we just passed
        self._hover_update(d.setpoint.thrust)
        if first:
            # PX4 accepts OFFBOARD only while setpoints arrive: the link sends this one first, then waits until
            # PX4 reports OFFBOARD (OffboardDenied otherwise), 0.3-0.9 s on PX4 1.15. That wait runs beside the
            # frame loop (_switching_to_offboard): awaited here it blinded perception for that long at every
            # engagement (the tracker lost the gate and re-acquired whatever was most confident: clutter, on
            # real PX4).
            self._offboard_start = asyncio.create_task(self.link.start_offboard(d.setpoint),
                                                       name="app:start_offboard")
            self._last_setpoint = self.clock()
            # Logged, but not a latency sample: the mode switch is still under way.
            self._log_control(frame, d, (self._last_setpoint - t_avail) * 1e3)
            return False
        await self.link.set_setpoint(d.setpoint)
        t_sent = self.clock()
        self._last_setpoint = t_sent
        self.stats.setpoints += 1
        lat_ms = (t_sent - t_avail) * 1e3
        self.stats.latencies_ms.append(lat_ms)
        self._log_control(frame, d, lat_ms)
        return False

    def _switching_to_offboard(self) -> bool:
        """True while PX4 has not yet confirmed OFFBOARD: frames are perceived, but the engagement waits (as
        before, its next step sees the time that passed), since PX4 does not fly our setpoints yet. A refused or
        unanswered switch raises here (OffboardDenied / CommandTimeout), mapped to its safe state as before."""
        task = self._offboard_start
        if task is None:
            return False
        if not task.done():
            self._last_setpoint = self.clock()  # the link streams the first setpoint meanwhile
            return True
        self._offboard_start = None
        task.result()
        self._check_fault()
        self._last_setpoint = self.clock()
        return False

    async def _cancel_offboard_start(self) -> None:
        """The flight left the frame loop (an end or an abort) while PX4 was still switching to OFFBOARD: stop
        waiting, so nothing starts streaming setpoints after the safe end has commanded its mode."""
        task, self._offboard_start = self._offboard_start, None
        if task is None:
            return
        if not task.done():
            task.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await task

    def _outcome(self, d: Decision) -> tuple[Reason, str]:
        """The normal end's reason: what the engagement claimed, checked against ground truth where it exists."""
        judge = self.judge
        truth = judge.results() if judge is not None and judge.has_truth else None
        reason, line = verdict(self.engagement.passes, truth)
        self._verdict = line
        self.log.event(f"outcome {reason.name}: {line}", "info" if reason is Reason.OK else "error")
        return reason, f"{d.why}; {line}"

    def _attitude_at(self, t: float) -> np.ndarray:
        """PX4's attitude estimate (IMU; NED/FRD wxyz) at a frame's capture time, not at its processing
        time: the box must be rotated to the world with the attitude the camera had when it saw it."""
        q = self.link.attitude_history.at(t)
        return q if q is not None else self.link.attitude.q_wxyz

    def _hover_update(self, thrust: float) -> None:
        """hover.estimate: the IMU's specific force against the thrust we commanded since the last setpoint
        (companion/hover.py); the controller flies with the estimate from then on."""
        if not self.cfg.hover.estimate:
            return
        if self._hover is None:
            self._hover = HoverThrustEstimator(self.ctrl.p.hover_thrust, self.cfg.hover)
        imu, h = self.link.imu, self._hover
        if imu is not None and self._hover_u is not None:
            e = h.update(imu.t_rx, self._hover_u, -float(imu.accel_frd[2]))  # FRD: the thrust axis is -z
            if e is not None:
                use_hover_thrust(self.ctrl, e.hover_thrust, self.cfg.airframe.thrust_to_weight,
                                 getattr(self, "engagement", None))  # the pass and recovery too
                self.log.write("hover", u_cmd=self._hover_u, a_up=-float(imu.accel_frd[2]),
                               hover_thrust=e.hover_thrust, std=e.std, samples=e.samples)
                if self._hover_logged is None or abs(e.hover_thrust - self._hover_logged) > 0.01:
                    self._hover_logged = e.hover_thrust
                    self.log.event(f"hover thrust {e.hover_thrust:.3f} estimated from the IMU ({e.samples} samples, "
                                   f"std {e.std:.3f}; started from {h.hover0:.3f})")
        self._hover_u = thrust

    async def _land_normally(self, reason: Reason, why: str, via: State) -> None:
        pilot = self.cfg.app.start == "pilot"  # the pilot took off, the pilot lands
        if via is State.HANDBACK:
            self.sm.go(State.HANDBACK, why)
            self._last_setpoint = math.inf  # we no longer owe setpoints
            await self.link.stop_offboard()
            self._check_fault()
            if pilot:
                self.sm.go(State.SAFE_HOLD, "PX4 holds; the pilot lands" + self._verdict_tail(reason), reason)
                return
            why = "PX4 holds; landing"
        elif pilot:
            self.sm.go(State.SAFE_PILOT, why + "; the pilot keeps control", reason)
            return
        self.sm.go(State.LAND, why)
        await self.link.land()
        self._check_fault()
        await self.link.wait_landed_and_disarm()
        self._check_fault()
        self.sm.go(State.SAFE_LANDED, "landed and disarmed" + self._verdict_tail(reason), reason)

    def _verdict_tail(self, reason: Reason) -> str:
        """A normal end that is not what was claimed says why, on the final line (stderr, log, summary)."""
        return f"; {self._verdict}" if reason in (Reason.GATE_MISSED, Reason.PASS_NOT_CONFIRMED) else ""

    async def _perceive(self, frame: Frame) -> Any:
        if self.perception_in_thread:
            # The detector releases the GIL; running it in a thread keeps the monitors responsive.
            call = asyncio.get_running_loop().run_in_executor(None, self.perception.process, frame)
            # A call that never returns (a hung driver or model) must end the flight in every state, not
            # only under the offboard watchdog: in ACQUIRE the loop would otherwise wait forever.
            limit = max(2.0, 4.0 * self.cfg.safety.perception_stall_timeout)
            try:
                return await asyncio.wait_for(call, limit)
            except TimeoutError:
                raise _Tripped(Abort(Reason.PERCEPTION_STALL, f"detector call did not return within "
                                     f"{limit:.1f} s")) from None
        return self.perception.process(frame)

    def _baro_raw(self) -> float | None:
        b = self.link.baro
        return None if b is None else b.altitude_raw_m

    def _baro_rel(self) -> float | None:
        b = self._baro_raw()
        if b is None or self._baro0 is None or not math.isfinite(b):
            return None
        return b - self._baro0

    # ------------------------------------------------------------------------------ safe ends
    async def _safe_end(self, fault: Abort) -> None:
        """Bring the vehicle to one named state that is TRUE of it: HOLD only when PX4 reports HOLD, landed
        only when landed and disarmed; otherwise the state names what the autopilot reports."""
        st, r, d = self.sm.state, fault.reason, fault.detail
        self._last_setpoint = math.inf  # the watchdog has nothing more to guard
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
        if r is Reason.VEHICLE_BUSY and st in GROUND_STATES:
            self.sm.go(State.REFUSED, d, r)
            return
        if st in GROUND_STATES:
            if self.link.armed is True:  # e.g. the arm ACK was lost but PX4 armed: say so, do not claim "not armed"
                self._go_seen(d + "; the vehicle is armed", r)
            else:
                self.sm.go(State.ABORT_NOT_ARMED, d, r)
            return
        pilot_start = self.cfg.app.start == "pilot"
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
            self.sm.go(State.LAND, d + "; land_after_abort")
            await self.link.land()
            await self.link.wait_landed_and_disarm()
            self._go_seen(d, r)
            return
        self._go_seen(d, r)

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
        elif mode in PILOT_MODES:
            self.sm.go(State.SAFE_PILOT, f"{detail}; the pilot has the vehicle in {mode}", reason)
        else:
            self.sm.go(State.AUTOPILOT, f"{detail}; PX4 flies in {mode} (armed {armed}, landed state {landed})",
                       reason)

    async def _last_resort(self, fault: Abort, err: BaseException) -> None:
        """The safe end itself failed: stop streaming (PX4's failsafe acts) and name that state."""
        with contextlib.suppress(Exception):
            await asyncio.wait_for(self.link.close(), 10.0)
        detail = f"{fault.detail}; safe end failed ({type(err).__name__}: {err}): streaming stopped"
        if self.sm.done:
            return
        if self.sm.state in GROUND_STATES and self.link.armed is not True:
            self.sm.go(State.ABORT_NOT_ARMED, detail, fault.reason)
        elif self.sm.state in GROUND_STATES:
            self._go_seen(detail, fault.reason)
        else:
            self.sm.go(State.SAFE_FAILSAFE_LINK, detail, fault.reason)

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
                return Abort(reason, text)
        if isinstance(e, CameraFailed):
            return Abort(Reason.CAMERA_FAILED, text)
        if isinstance(e, (TimeoutError, ConnectionError)) and self.sm.state is State.CONNECT:
            return Abort(Reason.CONNECT_FAILED, text)
        if isinstance(e, TimeoutError):
            return Abort(Reason.COMMAND_TIMEOUT, text)
        return Abort(Reason.EXCEPTION, text)

    # ------------------------------------------------------------------------------ monitors
    async def _monitor(self) -> None:
        """Telemetry to the log at 20 Hz; pilot takeover while PX4 flies its own modes for us.

        Link loss, the link's setpoint watchdog and PX4 leaving OFFBOARD arrive as link events
        (``on_link_event``); the link also refuses setpoints after any of them.
        """
        while not self.sm.done:
            await asyncio.sleep(0.05)
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
        who = Reason.PILOT_TAKEOVER if mode in PILOT_MODES else Reason.AUTOPILOT_MODE
        self.trip(who, f"flight mode changed to {mode} during {st.value}")

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

    # ------------------------------------------------------------------------------ logging
    def _on_transition(self, tr: Transition) -> None:
        self.log.state(tr.src.value, tr.dst.value, tr.reason, t=tr.t)
        self.notifier.status(f"{tr.dst.value}: {tr.reason}")

    def _log_detection(self, frame: Frame, box: Any, valid: bool) -> None:
        log_detection(self.log, frame, box, valid)

    def _log_control(self, frame: Frame, d: Decision, lat_ms: float) -> None:
        t_frame = frame.t - self.log.t0
        out: ControlOutput | None = d.control  # type: ignore[assignment]
        if out is not None:  # the controller ran (ENGAGE): its LOS and demand
            los = out.los_ned if out.los_ned is not None else (None, None, None)
            self.log.write("los", t_frame=t_frame, los_n=los[0], los_e=los[1], los_d=los[2],
                           lambda_dot=out.lambda_dot, a_n=float(np.linalg.norm(out.a_n)),
                           demand_scale=out.demand_scale, rejected=out.rejected or "")
        sp = d.setpoint
        assert sp is not None
        # ctrl_mode: the controller's mode in ENGAGE; "pass" (straight) / "recover" (level) otherwise.
        mode = out.mode if out is not None and d.phase is Phase.ENGAGE else d.phase.value.lower()
        self.log.write("setpoints", t_frame=t_frame, state=self.sm.state.value, ctrl_mode=mode,
                       roll_deg=sp.roll_deg, pitch_deg=sp.pitch_deg, yaw_deg=sp.yaw_deg, thrust=sp.thrust,
                       latency_ms=lat_ms)

    def _log_telemetry(self) -> None:
        truth = log_telemetry(self.log, self.link, self.truth)
        if truth is not None and self.judge is not None:
            self.judge.vehicle(truth.t_rx, truth.position_ned)


def log_telemetry(log: FlightLog, link: Any, truth: TruthSource | None = None) -> Any:
    """One row of the telemetry topic and, where ``truth`` has a sample, of truth (the app and shadow mode
    alike). Returns the truth sample logged (None without truth) for the app's gate judge."""
    att = link.attitude
    q = att.q_wxyz if att is not None else (None,) * 4
    r = p = y = None
    if att is not None:
        r, p, y = euler_ned_deg_from_R(att.R_ned_frd)
    imu, b = link.imu, link.baro
    extra = {}
    if imu is not None:
        a, g = imu.accel_frd, imu.gyro_frd
        extra = {"acc_f": a[0], "acc_r": a[1], "acc_d": a[2], "gyro_f": g[0], "gyro_r": g[1], "gyro_d": g[2]}
    log.write("telemetry", t_att=att.t_rx - log.t0 if att is not None else None,
              qw=q[0], qx=q[1], qy=q[2], qz=q[3], roll_deg=r, pitch_deg=p, yaw_deg=y,
              baro_alt_m=None if b is None else b.altitude_raw_m, flight_mode=link.flight_mode, armed=link.armed,
              landed_state=link.landed_state, **extra)
    sample = None if truth is None else truth.latest()  # log only: scoring and plots, never the controller
    if sample is not None:
        pn, vn = sample.position_ned, sample.velocity_ned
        log.write("truth", n=pn[0], e=pn[1], d=pn[2], vn=vn[0], ve=vn[1], vd=vn[2])
    return sample


def log_detection(log: FlightLog, frame: Frame, box: Any, valid: bool) -> None:
    """One row of the detections topic (the app and shadow mode log the same thing)."""
    t_frame = frame.t - log.t0
    if box is None:
        log.write("detections", t_frame=t_frame, frame=frame.index, valid=False)
    else:
        log.write("detections", t_frame=t_frame, frame=frame.index, cx=box.cx, cy=box.cy, w=box.w,
                  h=box.h, confidence=box.confidence, valid=valid)


def gate_logger(log: FlightLog, judge: GateJudge | None = None,
                clock: Callable[[], float] = time.monotonic) -> Callable[[int, Any, np.ndarray, float, bool], None]:
    """Callback for the synthetic camera: log each virtual gate (scene ENU -> NED), and hand it to the
    judge (on the monotonic clock of the link's truth samples). Scoring only."""
    from companion.frames import enu_to_ned

    def on_gate(k: int, gate: Any, c_enu: np.ndarray, radius: float, visible: bool) -> None:
        c, n = enu_to_ned(c_enu), enu_to_ned(gate.normal)
        log.write("gate", k=k, gate_n=c[0], gate_e=c[1], gate_d=c[2], normal_n=n[0], normal_e=n[1],
                  normal_d=n[2], radius=radius, visible=visible)
        if judge is not None:
            judge.gate(clock(), k, c, n, radius)

    return on_gate
