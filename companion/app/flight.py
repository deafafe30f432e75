"""The flight: camera -> perception -> LOS filter -> controller -> setpoint, under one state machine.

Read ``FlightApp._frame_loop`` top to bottom for the data path of one frame (the decisions are the flight core's,
companion/core.py); ``_sequence`` for the order of a flight; ``_safe_end`` (companion/app/safeend.py) for what
every fault does. Around the sequence run three monitors (companion/app/monitors.py): telemetry (logs it;
detects link loss and pilot takeover), the watchdog (no fresh
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
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from companion.app import liveview, preflight
from companion.app.camera import CameraSource, Frame, Perception
from companion.app.deadman import LoopDeadman
from companion.app.gcsconfirm import GcsConfirm
from companion.app.hovercheck import HoverAfterTakeoff
from companion.app.liveview import ViewInfo
from companion.app.logrows import log_detection, log_telemetry
from companion.app.monitors import Monitors
from companion.app.notify import Notifier
from companion.app.outcome import GateJudge, verdict
from companion.app.perframe import attitude_at, frame_input, log_inputs, log_step
from companion.app.safeend import SafeEnds
from companion.app.states import Reason, State, StateMachine, Transition, VehicleView
from companion.confirm import ConfirmParams, OperatorConfirm, engage_mode
from companion.controller import ControlOutput, PNController
from companion.core import CoreStep, FlightCore
from companion.engagement import Phase
from companion.flightlog import FlightLog
from companion.limits import Abort

if TYPE_CHECKING:
    from companion.config import Config
    from companion.vehicle import TruthSource, VehicleControl

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


class FlightApp(Monitors, SafeEnds):
    def __init__(
        self,
        cfg: Config,
        link: VehicleControl,
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
        self.sm = StateMachine(clock=log.now, sinks=[self._on_transition], stderr=sm_err, vehicle=self._vehicle_view)
        self.ctrl = PNController.from_config(cfg)
        self.width, self.height = cfg.camera.width, cfg.camera.height
        self.core: FlightCore | None = None  # made when the frame loop starts (the hover thrust is known)
        self._confirm: OperatorConfirm | None = None  # app.engage confirm (made with the core)
        self._live: liveview.LiveView | None = None  # app.live_view
        self.stats = FlightStats()
        self._fault: Abort | None = None
        self._seq: asyncio.Task[None] | None = None
        self._last_setpoint = math.inf  # clock time of the last fresh setpoint (inf: none owed)
        self._offboard_start: asyncio.Task | None = None  # PX4's switch to OFFBOARD, while it is under way
        self._baro0: float | None = None
        self._connected = False
        self._last_out: ControlOutput | None = None
        self._deadman: LoopDeadman | None = None
        self._hover_logged: float | None = None
        self._failsafe_values: dict[str, float | None] = {}
        self._px4_failsafe: str | None = None  # PX4's offboard-loss failsafe took the vehicle (not a pilot): why
        self._mpc_thr_hover: float | None = None  # PX4's MPC_THR_HOVER when read and plausible
        self._hover_check: HoverAfterTakeoff | None = None  # PX4's hover measured after take-off (vehiclematch.py)
        self.vehicle_report: dict[str, Any] = {}  # summary.json "hover": pre-flight and after take-off comparisons

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
            "passes": [g.as_dict() for g in self.core.engagement.passes] if self.core is not None else [],
            "truth": self._truth_summary(),
            "verdict": self._verdict,
            "frames": self.stats.frames,
            "setpoints": self.stats.setpoints,
            "frame_to_setpoint_ms": {"p50": float(np.percentile(lat, 50)) if lat.size else None,
                                     "p95": float(np.percentile(lat, 95)) if lat.size else None, "n": int(lat.size)},
            "cpu_percent": 100.0 * self.stats.cpu_s / self.stats.wall_s if self.stats.wall_s > 0 else None,
            "states": [h.dst.value for h in self.sm.history],
            "hover": self.vehicle_report,
        }

    def _truth_summary(self) -> dict[str, Any] | None:
        """Each gate against ground truth (None in the field: no truth)."""
        if self.judge is None or not self.judge.has_truth:
            return None
        gates = self.judge.results()
        icpt = self.judge.intercepts(self.core.engagement.passes) if self.core is not None else {}
        return {"gates": [g.as_dict() for g in gates], "through": sum(g.through for g in gates),
                "missed": sum(g.crossed and not g.through for g in gates),
                "intercepts": [r.as_dict() for r in icpt.values()]}

    # ------------------------------------------------------------------------------ sequence
    async def _sequence(self) -> None:
        cfg = self.cfg
        self._check_fault()  # a signal during set-up: nothing connected, nothing commanded
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
            self._mpc_thr_hover = hover if getattr(self.link, "hover_thrust_source", "config") == "autopilot" else None
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
        self._failsafe_values = values  # also tells PX4's offboard-loss failsafe from a pilot (monitors.py)
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
        """The frame loop: each frame's box goes to the flight core (companion/core.py), which decides ACQUIRE ->
        ENGAGE -> PASS -> RECOVER (-> ENGAGE ...) -> HANDBACK, or an abort; here only I/O: camera, perception,
        the setpoint to PX4, the state machine and the log."""
        self.core = FlightCore.from_config(self.cfg, controller=self.ctrl)  # with the autopilot's hover thrust
        self._hover_check = HoverAfterTakeoff(self, self._mpc_thr_hover)  # PX4's hover, before the engagement
        self._confirm = (OperatorConfirm(ConfirmParams.from_config(self.cfg))
                         if engage_mode(self.cfg) == "confirm" else None)
        gcs = None
        if self._confirm is not None and self.cfg.app.confirm.command:  # the ground station's confirm/withdraw
            gcs = GcsConfirm(self.link, self._confirm, lambda: self.core is not None and self.core.engagement.awaiting,
                             self.log.event, self.clock, self.cfg.app.confirm.command)
            if not await gcs.start():
                gcs = None
        self._live = liveview.from_config(self.cfg, self.log.event)  # app.live_view: annotated stream (own process)
        if self._live is not None:
            self.log.event(f"live view at {self._live.url}")
        try:
            await self._frame_loop(self.core)
        finally:
            if gcs is not None:
                await gcs.close()
            if self._live is not None:
                self._live.close()
            await self._cancel_offboard_start()

    async def _frame_loop(self, core: FlightCore) -> None:
        while True:
            self._check_fault()
            frame = await self.camera.read()
            t_avail = self.clock()
            q = attitude_at(self.link, frame.t)  # one lookup: perception and the core
            box = await self._perceive(frame, q)
            self._check_fault()
            valid = box is not None and box.is_valid(self.width, self.height)
            self.stats.frames += 1
            log_detection(self.log, frame, box, valid)
            if self._switching_to_offboard():
                continue  # perceived and logged (the tracker keeps the gate); PX4 does not fly our setpoints yet
            inp = frame_input(frame.t, box, self.link, self._baro_rel(), t_avail, q)
            if inp is None:
                raise _Tripped(Abort(Reason.TELEMETRY_INVALID, "no attitude from the autopilot for a frame"))
            if self._confirm is not None:  # app.engage confirm: RC switch or GCS command (companion/confirm.py)
                inp = replace(inp, confirm=self._confirm.step(
                    self.clock(), getattr(self.link, "rc", None), core.engagement.awaiting,
                    acquiring=core.engagement.phase is Phase.ACQUIRE))
                if self._confirm.withdrawn is not None:
                    self.log.event(f"confirmation withdrawn: {self._confirm.withdrawn}", "warn")
                    self._confirm.withdrawn = None
            if self._hover_check is not None and not self._hover_check.done:  # before the first setpoint
                self._hover_check.frame(core, self.sm.state is State.ACQUIRE, t_avail)
            log_inputs(self.log, inp, core.hover_thrust)
            step = core.step(inp)
            d = step.decision
            if d.control is not None:
                self._last_out = d.control
            for ev in d.events:
                self.log.event(ev)
            self.stats.gates_passed = step.passes_confirmed
            step.tell_tracker(self.perception)  # not to hold on to (or coast) a passed gate or a refused candidate
            self._note_hover(step)
            if self._live is not None:  # never waits: a copy into shared memory only when the view wants one
                # the rival too: an operator asked to confirm sees what else in view competes with the candidate
                self._live.offer(frame.image, ViewInfo(box, d.phase.value, core.engagement.awaiting, d.why,
                                                       getattr(box, "rival", None)))
            if await self._apply(frame, step, t_avail):
                return

    async def _apply(self, frame: Frame, step: CoreStep, t_avail: float) -> bool:
        """Carry out one decision; True when the flight's normal end has been reached."""
        d = step.decision
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
            self._log_control(frame, step, (self._last_setpoint - t_avail) * 1e3)
            return False
        await self.link.set_setpoint(d.setpoint)
        t_sent = self.clock()
        self._last_setpoint = t_sent
        self.stats.setpoints += 1
        lat_ms = (t_sent - t_avail) * 1e3
        self.stats.latencies_ms.append(lat_ms)
        self._log_control(frame, step, lat_ms)
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

    def _outcome(self, d: Any) -> tuple[Reason, str]:
        """The normal end's reason: what the engagement claimed, checked against ground truth where it exists."""
        judge = self.judge
        truth = judge.results() if judge is not None and judge.has_truth else None
        assert self.core is not None
        icpt = judge.intercepts(self.core.engagement.passes) if truth is not None and judge is not None else None
        reason, line = verdict(self.core.engagement.passes, truth, icpt)
        self._verdict = line
        self.log.event(f"outcome {reason.name}: {line}", "info" if reason is Reason.OK else "error")
        return reason, f"{d.why}; {line}"

    def _note_hover(self, step: CoreStep) -> None:
        """hover.estimate: a new estimate of the core's (companion/hover.py) is named in the events when it
        moved by more than 0.01 (the log's hover topic has every one)."""
        e = step.hover
        if e is not None and (self._hover_logged is None or abs(e.hover_thrust - self._hover_logged) > 0.01):
            self._hover_logged = e.hover_thrust
            h0 = self.core.hover_estimator.hover0 if self.core is not None and self.core.hover_estimator else None
            self.log.event(f"hover thrust {e.hover_thrust:.3f} estimated from the IMU ({e.samples} samples, "
                           f"std {e.std:.3f}; started from {h0:.3f})")

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
            why = f"PX4 holds; {await self._at_rest()}"
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
        return f"; {self._verdict}" if reason in (Reason.GATE_MISSED, Reason.PASS_NOT_CONFIRMED,
                                                  Reason.INTERCEPT_IMPACT, Reason.TARGET_MISSED) else ""

    async def _perceive(self, frame: Frame, q: Any) -> Any:
        if self.perception_in_thread:
            # The detector releases the GIL; running it in a thread keeps the monitors responsive.
            call = asyncio.get_running_loop().run_in_executor(None, self.perception.process, frame, q)
            # A call that never returns (a hung driver or model) must end the flight in every state, not
            # only under the offboard watchdog: in ACQUIRE the loop would otherwise wait forever.
            limit = max(2.0, 4.0 * self.cfg.safety.perception_stall_timeout)
            try:
                return await asyncio.wait_for(call, limit)
            except TimeoutError:
                raise _Tripped(Abort(Reason.PERCEPTION_STALL, f"detector call did not return within "
                                     f"{limit:.1f} s")) from None
        return self.perception.process(frame, q)

    def _baro_raw(self) -> float | None:
        b = self.link.baro
        return None if b is None else b.altitude_raw_m

    def _baro_rel(self) -> float | None:
        b = self._baro_raw()
        if b is None or self._baro0 is None or not math.isfinite(b):
            return None
        return b - self._baro0

    def _vehicle_view(self) -> VehicleView | None:
        """What PX4 last reported (None before the link connected): the state machine checks terminal claims."""
        if not self._connected:
            return None
        link = self.link
        return VehicleView(armed=link.armed, mode=link.flight_mode, landed=link.landed_state,
                           link_ok=bool(link.link_ok))

    # ------------------------------------------------------------------------------ logging
    def _on_transition(self, tr: Transition) -> None:
        self.log.state(tr.src.value, tr.dst.value, tr.reason, t=tr.t)
        self.notifier.status(f"{tr.dst.value}: {tr.reason}")

    def _log_control(self, frame: Frame, step: CoreStep, lat_ms: float) -> None:
        d = step.decision
        out: ControlOutput | None = d.control  # type: ignore[assignment]
        # ctrl_mode: the controller's mode in ENGAGE; "pass" (straight) / "recover" (level) otherwise.
        mode = out.mode if out is not None and d.phase is Phase.ENGAGE else d.phase.value.lower()
        log_step(self.log, frame.t - self.log.t0, step, self.sm.state.value, mode, lat_ms)

    def _log_telemetry(self) -> None:
        truth = log_telemetry(self.log, self.link, self.truth)
        if truth is not None and self.judge is not None:
            self.judge.vehicle(truth.t_rx, truth.position_ned, truth.velocity_ned)
