"""One flight of the app, start to safe state: ``fly`` (``companion fly``, ``companion sim``, bench, tests).

The vehicle lock, the flight log, the link, the camera and perception (companion/app/assemble.py), the
state machine (companion/app/flight.py), then everything closed in order; an exception that gets out of
the state machine still ends in a named safe state (``_escaped``).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from companion.app.assemble import build_camera

if TYPE_CHECKING:
    from collections.abc import Awaitable, Callable

    from companion.app.flight import FlightApp
    from companion.app.states import Reason
    from companion.config import Config
    from companion.vehicle import TruthSource


class StartRefused(RuntimeError):
    """The flight cannot start (vehicle locked by another app, flight log unusable): one line, exit 2.

    Raised before the app connects, so nothing has been commanded.
    """



async def fly(
    cfg: Config,
    *,
    status_line: bool = False,
    plot: bool = True,
    stderr: Any = sys.stderr,
    handle_signals: bool = True,
    alongside: Callable[[FlightApp], Awaitable[None]] | None = None,
    record: str | Path | None = None,
    record_kw: dict[str, Any] | None = None,
    confirm: Callable[[str], Awaitable[bool]] | None = None,
) -> tuple[Reason, Path, dict[str, Any]]:
    """One flight, start to safe state. Returns (outcome, flight folder, summary).

    ``alongside(app)`` runs next to the flight and is cancelled when it ends (tests inject faults with it).
    """
    from companion.app.vehiclelock import VehicleBusy, VehicleLock

    guard = _SignalGuard(asyncio.get_running_loop(), stderr) if handle_signals else None
    try:
        # One app per vehicle, held until the link is closed (then nothing of ours commands it any more).
        lock = VehicleLock(cfg.link.url)
        try:
            lock.acquire()
        except VehicleBusy as e:
            raise StartRefused(str(e)) from None
        try:
            return await _fly_locked(cfg, status_line=status_line, plot=plot, stderr=stderr, guard=guard,
                                     alongside=alongside, record=record, record_kw=record_kw, confirm=confirm)
        finally:
            lock.release()
    finally:
        if guard is not None:
            guard.restore()  # only now: the summary is written, the plot drawn


class SignalHandoff:
    """A signal that arrives after the CLI handed SIGTERM/SIGINT to ``fly`` and before fly's guard exists.

    The CLI (companion/app/main.py) stops turning signals into "interrupted" when it calls ``fly``; the guard takes
    over at fly's first lines. In between (an event loop and an executor made, a module imported: tens of ms, far
    more on a loaded machine) a signal was "received after the flight ended: ignored" and the whole flight was
    flown (found reading the code behind a loaded test run's lost SIGINT; a ``systemctl stop`` at start-up the
    same). Now it is kept here and the guard trips the flight with it at once, as for a signal during set-up.
    """

    def __init__(self) -> None:
        self._open = False
        self.pending: str | None = None

    def open(self) -> None:
        """The CLI is about to call ``fly``: signals from here are the flight's."""
        self._open, self.pending = True, None

    def offer(self, name: str) -> bool:
        """From the CLI's handler: True if the flight will act on the signal (its guard does not exist yet)."""
        if not self._open:
            return False
        self.pending = self.pending or name
        return True

    def take(self) -> str | None:
        """fly's guard exists: the signal kept meanwhile, if any; later ones are the guard's."""
        pending, self.pending, self._open = self.pending, None, False
        return pending


HANDOFF = SignalHandoff()


class _SignalGuard:
    """SIGTERM/SIGINT for one flight, from ``fly``'s first line to its last.

    The first signal trips the state machine (exit 23 after its safe end). One before the state machine exists is
    kept and trips it at once; later ones (a double Ctrl-C, a stop script that sends two) are logged and ignored:
    a second signal must not kill the process halfway through the safe end and leave summary.json "running"
    (issue #22: exit -15 / -2). Python-level handlers (not loop.add_signal_handler, which restores the default
    action, i.e. death, when removed) so the caller's handlers come back only after the log is closed.
    """

    # SIGABRT: what systemd's watchdog (WatchdogSec) sends when WATCHDOG=1 stopped; a loop that runs again
    # ends like a SIGTERM, with the watchdog named in the log and summary.json final.
    SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGABRT)

    def __init__(self, loop: asyncio.AbstractEventLoop, stderr: Any) -> None:
        self.loop, self.stderr = loop, stderr
        self.app: FlightApp | None = None
        self.log: Any = None
        self.pending: str | None = None
        self.old = {sig: signal.signal(sig, self._on_signal) for sig in self.SIGNALS}
        self.pending = HANDOFF.take() or self.pending  # one the CLI kept while fly() was starting

    def _on_signal(self, signum: int, frame: Any) -> None:
        from companion.app.states import Reason

        name = signal.Signals(signum).name
        if signum == signal.SIGABRT:
            name = "SIGABRT (systemd's watchdog: the event loop missed WatchdogSec)"
        app = self.app
        if app is None:
            self.pending = self.pending or name  # before the state machine: it starts with this fault
        elif not app.sm.done and app._fault is None:
            self.loop.call_soon_threadsafe(app.trip, Reason.SIGNAL, f"{name} received")
            return
        else:
            with contextlib.suppress(Exception):
                os.write(2, f"companion: {name} received while the flight ends: ignored (the safe end goes on)\n"
                         .encode())
        if self.log is not None:
            self.loop.call_soon_threadsafe(self._log_late, name)

    def _log_late(self, name: str) -> None:
        with contextlib.suppress(Exception):
            self.log.event(f"{name} received while the flight ends: ignored", "warn")

    def attach(self, app: FlightApp) -> None:
        from companion.app.states import Reason

        self.app = app
        if self.pending is not None:
            app.trip(Reason.SIGNAL, f"{self.pending} received during set-up")

    def restore(self) -> None:
        for sig, old in self.old.items():
            signal.signal(sig, old)


async def _fly_locked(
    cfg: Config,
    *,
    status_line: bool,
    plot: bool,
    stderr: Any,
    guard: _SignalGuard | None,
    alongside: Callable[[FlightApp], Awaitable[None]] | None,
    record: str | Path | None,
    record_kw: dict[str, Any] | None,
    confirm: Callable[[str], Awaitable[bool]] | None = None,
) -> tuple[Reason, Path, dict[str, Any]]:
    from companion.app.flight import FlightApp
    from companion.app.link import VehicleLink
    from companion.app.notify import Notifier
    from companion.app.outcome import GateJudge
    from companion.app.states import Reason
    from companion.config import config_as_dict
    from companion.flightlog import FlightLog, FlightLogError

    try:  # refused before connecting: a flight without its log is not flown
        log = FlightLog.create(cfg.log.directory, config_as_dict(cfg), min_free_mb=cfg.log.min_free_mb,
                               flush_interval=cfg.log.flush_interval, stderr=stderr)
    except FlightLogError as e:
        raise StartRefused(f"cannot start the flight log: {e}") from None
    print(f"companion: logging to {log.folder}", file=stderr, flush=True)
    if guard is not None:
        guard.log = log
    notifier = Notifier()
    app: FlightApp | None = None
    link = VehicleLink.from_config(cfg, on_event=lambda kind, detail: app.on_link_event(kind, detail) if app
                                   else log.event(f"link {kind} {detail}"))
    truth: TruthSource | None = None
    try:
        from companion.app.telemetry import LinkPositionTruth
        from companion.px4sitl.truth import open_truth

        # PX4 SIH's ground truth for the camera and the score (px4.truth_url), else the link's own position.
        truth = open_truth(cfg) or LinkPositionTruth(link)
        judge = GateJudge.for_config(cfg)  # ground truth, where a simulator provides it: scores the gates, never steers
        camera, perception, in_thread = build_camera(cfg, link, log, judge, truth)
        if record is not None:  # --record DIR: every frame with its time and attitude (companion/app/record.py)
            from companion.app.record import RecordingCamera, link_attitude, recorder_for_flight

            camera = RecordingCamera(camera, recorder_for_flight(record, cfg, log, stderr, **(record_kw or {})),
                                     link_attitude(link))
        app = FlightApp(cfg, link, camera, perception, log, notifier=notifier, stderr=stderr,
                        status_line=status_line, perception_in_thread=in_thread, judge=judge,
                        confirm=confirm, truth=truth)
        if guard is not None:
            guard.attach(app)
        side = asyncio.create_task(alongside(app)) if alongside is not None else None
        try:
            reason = await app.run()
        finally:
            if side is not None:
                side.cancel()
                await asyncio.gather(side, return_exceptions=True)
        summary = app.summary()
    except Exception as e:
        if app is None:  # set-up failed before the state machine ran: nothing connected, nothing armed
            reason = Reason.CAMERA_FAILED
            summary = {"outcome": "ABORT_NOT_ARMED", "reason": reason.name, "exit_code": int(reason),
                       "detail": f"{type(e).__name__}: {e}"}
            log.state("INIT", "ABORT_NOT_ARMED", summary["detail"])
            print(f"companion: set-up failed: {summary['detail']}", file=stderr, flush=True)
        else:
            reason, summary = await _escaped(app, link, e, stderr)
    finally:
        with contextlib.suppress(Exception):
            await asyncio.wait_for(link.close(), 10.0)
        if truth is not None:
            truth.close()
        notifier.close()
    log.close(summary)
    if plot and cfg.log.plot:
        try:
            from companion.app.plot import plot_flight

            plot_flight(log.folder)
        except Exception as e:  # (a plot must never change the flight's outcome)
            print(f"companion: plot failed: {type(e).__name__}: {e}", file=stderr)
    return reason, log.folder, summary


async def _escaped(app: FlightApp, link: Any, err: Exception, stderr: Any) -> tuple[Reason, dict[str, Any]]:
    """An exception got out of the state machine (a bug): record only what is true of the vehicle.

    If the machine already reached its safe state, that stands. Otherwise streaming is stopped
    (closing the link ends MAVSDK's resending, so PX4's offboard-loss failsafe acts once we
    commanded it) and the state named is the one that is true then: not armed on the ground,
    PX4's own failsafe in the air.
    """
    from companion.app.states import Reason

    detail = f"{type(err).__name__}: {err}"
    print(f"companion: flight logic failed: {detail}", file=stderr, flush=True)
    if not app.sm.done:
        with contextlib.suppress(Exception):
            await asyncio.wait_for(link.close(), 10.0)
        from companion.app.safeend import name_last_resort

        with contextlib.suppress(Exception):
            name_last_resort(app.sm, link, f"{detail}; streaming stopped", Reason.EXCEPTION)
    summary = app.summary()
    summary.setdefault("error", detail)
    reason = app.sm.outcome if app.sm.outcome is not None else Reason.EXCEPTION
    return reason, summary
