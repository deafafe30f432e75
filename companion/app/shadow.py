"""Shadow mode (``companion fly --shadow``): the whole pipeline beside a pilot, commanding nothing.

The real camera (or the synthetic one), the detector and tracker, PX4's attitude, the LOS filter,
the PN controller and the engagement's decisions (acquire, engage, pass, recover) run on every frame
exactly as in a flight: the same flight core (companion/core.py) with the same input read from the vehicle
(companion/app/perframe.py: attitude at capture, accelerometer, time now, barometer), the same tracker reset
and hover-thrust estimate (tests/app/test_shadow_equals_flight.py checks the setpoints bit for bit); the
setpoints they produce are logged in the same topics (``setpoints`` rows
with ``state = SHADOW`` and ``ctrl_mode = PHASE/controller mode``) and plotted beside the attitude
the vehicle actually flew (``shadow.png``), and never sent. No arming, no take-off, no mode change,
no offboard: the link is wrapped so that any commanding call raises (``ShadowViolation``) instead of
reaching the vehicle; only telemetry and parameter reads go out.

An engagement that ends (handed back, aborted, no target) is logged and a fresh one starts, so a
pilot can fly the gates again. The shadow run ends on Ctrl-C / SIGTERM, ``--duration``, the end of
the camera stream, or link loss; exit code 0 unless the link or camera failed.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from companion.app.logrows import log_detection, log_telemetry
from companion.app.perframe import attitude_at, frame_input, log_inputs, log_step
from companion.confirm import engage_mode
from companion.core import FlightCore

if TYPE_CHECKING:
    from companion.config import Config
    from companion.vehicle import TruthSource, VehicleTelemetry

SHADOW_STATE = "SHADOW"
_COMMANDING = frozenset({"arm", "disarm", "takeoff", "land", "hold", "start_offboard", "stop_offboard", "set_setpoint",
                         "wait_landed_and_disarm", "set_mode", "kill", "return_to_launch"})


class ShadowViolation(RuntimeError):
    """Something tried to command the vehicle in shadow mode (a bug; the command was not sent)."""


class ReadOnlyLink:
    """The vehicle link with every commanding call removed: telemetry, parameters, connect and close only.

    Typed as ``companion.vehicle.VehicleTelemetry`` wherever shadow uses it (the session is declared on that
    Protocol, which has no commanding member: a type checker refuses ``link.arm()``); the runtime guard here
    catches what typing cannot (a call through ``Any``)."""

    def __init__(self, link: VehicleTelemetry) -> None:
        self._link = link

    def __getattr__(self, name: str) -> Any:
        if name in _COMMANDING:
            raise ShadowViolation(f"shadow mode: {name}() would command the vehicle; not sent")
        return getattr(self._link, name)


async def shadow(
    cfg: Config, *, duration: float | None = None, stderr: Any = sys.stderr, handle_signals: bool = True,
    plot: bool = True, record: str | Path | None = None, record_kw: dict[str, Any] | None = None,
) -> tuple[int, Path, dict[str, Any]]:
    """One shadow session. Returns (exit code, log folder, summary)."""
    from companion.app.assemble import build_camera
    from companion.app.link import VehicleLink
    from companion.app.states import Reason
    from companion.app.telemetry import LinkPositionTruth
    from companion.config import config_as_dict
    from companion.flightlog import FlightLog

    log = FlightLog.create(cfg.log.directory, config_as_dict(cfg), flush_interval=cfg.log.flush_interval)
    print(f"companion: SHADOW mode (setpoints computed and logged, never sent); logging to {log.folder}",
          file=stderr, flush=True)
    link = VehicleLink.from_config(cfg, on_event=lambda kind, detail: log.event(
        f"link {kind} {detail}" if detail else f"link {kind}", "info"))
    ro = cast("VehicleTelemetry", ReadOnlyLink(link))  # read-only by type (and by the runtime guard)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    if handle_signals:
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
    session = _Session(cfg, ro, log, stderr)
    reason, detail = Reason.OK, "shadow session ended"
    truth: TruthSource | None = None
    try:
        from companion.px4sitl.truth import open_truth

        # PX4 SIH's true pose for a synthetic camera (px4.truth_url), else the link's own position; never control.
        truth = session.truth = open_truth(cfg) or LinkPositionTruth(ro)
        log.state("INIT", "CONNECT", f"connecting to {cfg.link.url} (shadow: read-only)")
        await ro.connect()
        await ro.wait_link_ok(cfg.link.connect_timeout)
        await session.read_hover()
        camera, perception, in_thread = build_camera(cfg, ro, log, truth=truth)
        if record is not None:  # --record: the frames the pilot's flight showed, for labelling and replay
            from companion.app.record import RecordingCamera, link_attitude, recorder_for_flight

            camera = RecordingCamera(camera, recorder_for_flight(record, cfg, log, stderr, **(record_kw or {})),
                                     link_attitude(ro))
        session.camera, session.perception, session.in_thread = camera, perception, in_thread
        log.state("CONNECT", SHADOW_STATE, "shadow: setpoints computed and logged, never sent")
        reason, detail = await session.run(stop, duration)
    except ShadowViolation:
        raise  # a bug: nothing was sent, but it must not pass silently
    except Exception as e:  # connect or camera failed: nothing was commanded either way
        name = type(e).__name__
        reason = Reason.CONNECT_FAILED if not session.connected_ok(ro) else (
            Reason.CAMERA_FAILED if "Camera" in name or session.camera is None else Reason.EXCEPTION)
        detail = f"{name}: {e}"
        print(f"companion: shadow ended: {detail}", file=stderr, flush=True)
    finally:
        if handle_signals:
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.remove_signal_handler(sig)
        if session.camera is not None:
            with contextlib.suppress(Exception):
                session.camera.close()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(link.close(), 10.0)
        if truth is not None:
            truth.close()
    log.state(SHADOW_STATE if session.started else "CONNECT", "SHADOW_END", detail)
    summary = session.summary(reason, detail)
    log.close(summary)
    if plot and cfg.log.plot:
        try:
            plot_shadow(log.folder)
        except Exception as e:  # (a plot never changes the outcome)
            print(f"companion: shadow plot failed: {type(e).__name__}: {e}", file=stderr)
    print(f"companion: shadow: {session.stats['frames']} frames, {session.stats['setpoints']} setpoints computed, "
          f"0 sent; {session.stats['engagements']} engagement(s); log {log.folder}", file=stderr, flush=True)
    return int(reason), log.folder, summary


class _Session:
    def __init__(self, cfg: Config, link: VehicleTelemetry, log: Any, stderr: Any,
                 clock: Callable[[], float] = time.monotonic,
                 on_setpoint: Callable[[float, Any], None] | None = None) -> None:
        from companion.controller import PNController

        self.cfg, self.link, self.log, self.stderr = cfg, link, log, stderr
        self.clock = clock
        self.on_setpoint = on_setpoint  # each computed setpoint with its frame's time (a sink beside the log)
        self.ctrl = PNController.from_config(cfg)
        self.core: FlightCore | None = None
        self.camera: Any = None
        self.perception: Any = None
        self.in_thread = False
        self.started = False
        self.stats = {"frames": 0, "setpoints": 0, "engagements": 0, "passes": 0}
        self.hover_source = "config"
        self._baro0: float | None = None
        self._passes_before = 0  # confirmed passes of the engagements that ended before the current one
        self.truth: TruthSource | None = None  # logged in the truth topic only

    @staticmethod
    def connected_ok(link: Any) -> bool:
        try:
            return bool(link.link_ok)
        except Exception:
            return False

    async def read_hover(self) -> None:
        h = await self.link.hover_thrust()  # a parameter read, not a command
        if h is not None and 0.05 < h < 0.95:
            self.ctrl = self.ctrl.with_hover_thrust(h, self.cfg.airframe.thrust_to_weight)
            self.hover_source = getattr(self.link, "hover_thrust_source", "autopilot")
            self.log.event(f"hover thrust {h:.3f} from MPC_THR_HOVER")

    def _baro_rel(self) -> float | None:
        b = self.link.baro
        if b is None or not math.isfinite(b.altitude_raw_m):
            return None
        ref = self.cfg.safety.altitude_reference  # where the ground is, when the operator says so (as a flight)
        if ref is not None:
            self._baro0 = ref
        elif self._baro0 is None and self.link.landed_state == "ON_GROUND":
            self._baro0 = b.altitude_raw_m  # the floor is above the ground we saw; never a mid-air reference
        return None if self._baro0 is None else b.altitude_raw_m - self._baro0

    async def run(self, stop: asyncio.Event, duration: float | None) -> tuple[Any, str]:
        from companion.app.states import Reason

        self.started = True
        self.core = FlightCore.from_config(self.cfg, controller=self.ctrl)
        t_end = None if duration is None else time.monotonic() + duration
        tel = asyncio.create_task(self._telemetry(stop))
        try:
            while not stop.is_set():
                if t_end is not None and time.monotonic() >= t_end:
                    return Reason.OK, f"duration {duration:.1f} s reached"
                if not self.link.link_ok:
                    return Reason.LINK_LOST, f"no telemetry for {self.link.telemetry_age:.1f} s"
                read = asyncio.ensure_future(self.camera.read())
                waiter = asyncio.ensure_future(stop.wait())
                done, _ = await asyncio.wait({read, waiter}, timeout=1.0, return_when=asyncio.FIRST_COMPLETED)
                waiter.cancel()
                if read not in done:
                    read.cancel()
                    with contextlib.suppress(asyncio.CancelledError, Exception):
                        await read
                    continue
                await self._frame(self.core, read.result())
            return Reason.OK, "stopped by the operator"
        finally:
            tel.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await tel

    async def _frame(self, core: FlightCore, frame: Any) -> None:
        t_avail = self.clock()
        q = attitude_at(self.link, frame.t)  # as the flight: one lookup for perception and the core
        if self.in_thread:
            box = await asyncio.get_running_loop().run_in_executor(None, self.perception.process, frame, q)
        else:
            box = self.perception.process(frame, q)
        self.stats["frames"] += 1
        valid = box is not None and box.is_valid(self.cfg.camera.width, self.cfg.camera.height)
        log_detection(self.log, frame, box, valid)
        inp = frame_input(frame.t, box, self.link, self._baro_rel(), t_avail, q)
        if inp is None:
            return  # no attitude yet: nothing to compute from
        log_inputs(self.log, inp, core.hover_thrust)
        step = core.step(inp)  # the accelerometer, the time now, the hover estimate: as in a flight
        d = step.decision
        step.tell_tracker(self.perception)  # as the flight does
        if d.changed:
            self.log.event(f"shadow: {d.previous.value} -> {d.phase.value}: {d.why}")
            if d.previous.value == "ACQUIRE":
                self.stats["engagements"] += 1
                if engage_mode(self.cfg) == "confirm":  # the flight would have waited for the operator here
                    self.log.event("shadow: would have asked the operator to confirm the candidate (app.engage "
                                   "confirm) before engaging")
        for ev in d.events:
            self.log.event(f"shadow: {ev}")
        self.stats["passes"] = self._passes_before + step.passes_confirmed
        out = d.control
        if d.setpoint is not None:
            mode = f"{d.phase.value}/{getattr(out, 'mode', '-')}" if out is not None else d.phase.value
            log_step(self.log, frame.t - self.log.t0, step, SHADOW_STATE, mode, (self.clock() - t_avail) * 1e3)
            self.stats["setpoints"] += 1
            if self.on_setpoint is not None:
                self.on_setpoint(frame.t, d.setpoint)
        if d.phase.done:
            self.log.event(f"shadow: engagement ended ({d.reason.name if d.reason else '-'}): {d.why}; "
                           "a new one starts")
            self._passes_before = self.stats["passes"]
            core.restart()

    async def _telemetry(self, stop: asyncio.Event) -> None:
        while not stop.is_set():
            log_telemetry(self.log, self.link, self.truth)
            await asyncio.sleep(0.05)

    def summary(self, reason: Any, detail: str) -> dict[str, Any]:
        return {"outcome": "SHADOW_END", "mode": "shadow", "reason": reason.name, "exit_code": int(reason),
                "detail": detail, "frames": self.stats["frames"], "setpoints_computed": self.stats["setpoints"],
                "setpoints_sent": 0, "engagements": self.stats["engagements"], "passes": self.stats["passes"],
                "hover_thrust": self.ctrl.p.hover_thrust, "hover_thrust_source": self.hover_source}


def plot_shadow(folder: str | Path, output: str | Path | None = None) -> Path:
    """What the app would have commanded beside what the vehicle did (roll, pitch, yaw), and the thrust."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from companion.flightlog import read_flight

    folder = Path(folder)
    f = read_flight(folder, ["telemetry", "setpoints", "detections"])
    out = Path(output) if output is not None else folder / "shadow.png"
    tel, sp = f.tables.get("telemetry"), f.tables.get("setpoints")
    fig, ax = plt.subplots(5, 1, figsize=(11, 12), sharex=True)
    for a, col, label in zip(ax[:3], ("roll_deg", "pitch_deg", "yaw_deg"), ("roll", "pitch", "yaw"), strict=True):
        if tel is not None and len(tel):
            a.plot(tel["t"], tel[col], color="k", lw=1.0, label=f"vehicle {label} (flown by the pilot)")
        if sp is not None and len(sp):
            a.plot(sp["t"], sp[col], ".", color="tab:orange", ms=3, label=f"shadow {label} setpoint (not sent)")
        a.set_ylabel(f"{label}, deg")
        a.legend(loc="upper right", fontsize=8)
    if sp is not None and len(sp):
        ax[3].plot(sp["t"], sp["thrust"], ".", color="tab:orange", ms=3, label="shadow thrust setpoint (not sent)")
    ax[3].set_ylabel("thrust, 0..1")
    ax[3].legend(loc="upper right", fontsize=8)
    det = f.tables.get("detections")
    if det is not None and len(det):
        ax[4].plot(det["t"], det["cx"], ".", ms=2, label="box cx")
        ax[4].plot(det["t"], det["cy"], ".", ms=2, label="box cy")
        ax[4].legend(loc="upper right", fontsize=8)
    ax[4].set_ylabel("box centre, px")
    ax[4].set_xlabel("t, s (flight clock)")
    fig.suptitle(f"SHADOW {folder.name}: setpoints computed, never sent")
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return out
