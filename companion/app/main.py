"""``companion fly`` (the flight app), ``companion log plot``, and the helpers ``companion sim`` / bench use.

``companion fly`` flies a real vehicle: link URL and camera source from the config. With
``--synthetic`` (app.camera=synthetic) the camera is simulated from the vehicle pose that
arrives over MAVLink (hardware-in-the-loop with PX4 SIH/SITL, or the built-in simulated PX4).
The process exit code is the outcome (companion/app/states.py ``Reason``): 0 = gate(s)
passed and landed; each fault has its own code.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from collections.abc import Awaitable, Callable

    from companion.app.flight import FlightApp
    from companion.app.states import Reason
    from companion.config import Config
    from companion.vehicle import TruthSource


def register(subparsers: Any) -> None:
    from companion.app.states import Reason
    from companion.config import add_config_arguments

    codes = "\n".join(f"  {r.value:3d}  {r.name}" for r in Reason)
    p = subparsers.add_parser("fly", help="fly through gates: connect, take off, engage, pass, land (logs the flight)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
                              epilog=f"exit codes (the flight's outcome):\n{codes}\n"
                              "GATE_MISSED: ground truth (simulated PX4, PX4 SITL) says a gate's plane was crossed\n"
                              "  outside its radius, or fewer gates were flown through than passes claimed.\n"
                              "PASS_NOT_CONFIRMED: no ground truth (the field) and a pass ended on app.pass_timeout\n"
                              "  without evidence that the gate went behind.")
    add_config_arguments(p)
    p.add_argument("--url", help="mavsdk connection URL (overrides link.url)")
    p.add_argument("--synthetic", action="store_true",
                   help="synthetic camera from the vehicle pose over MAVLink (app.camera=synthetic)")
    p.add_argument("--geometric", action="store_true",
                   help="synthetic camera draws a geometric box instead of images (no detector)")
    p.add_argument("--log-dir", help="parent folder of the flight log (overrides log.directory)")
    p.add_argument("--status", action="store_true", help="live status line on stderr")
    p.add_argument("--no-plot", action="store_true", help="do not write plot.png at the end")
    from companion.app.record import add_record_arguments

    add_record_arguments(p)
    p.add_argument("--yes", "-y", action="store_true",
                   help="do not ask to confirm the pre-flight summary before arming (it is still printed and logged)")
    p.add_argument("--shadow", action="store_true",
                   help="shadow mode: the whole pipeline beside the pilot; setpoints logged and plotted, never sent "
                        "(no arming, no mode change, no offboard)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="shadow mode: stop after S seconds")
    p.set_defaults(func=_cmd_fly)

    lp = subparsers.add_parser("log", help="flight logs: plot, summary, export")
    lsub = lp.add_subparsers(dest="log_command", required=True, metavar="ACTION")
    pp = lsub.add_parser("plot", help="plot a flight folder to PNG")
    pp.add_argument("folder", help="flight folder (or a log directory: its latest flight)")
    pp.add_argument("-o", "--output", help="PNG path (default FOLDER/plot.png)")
    pp.set_defaults(func=_cmd_plot)
    from companion.logtools import register_log_actions

    register_log_actions(lsub)  # log summary, log export


def _overrides(args: argparse.Namespace) -> list[str]:
    ov = list(getattr(args, "overrides", []) or [])
    if getattr(args, "url", None):
        ov.append(f"link.url={args.url}")
    if getattr(args, "synthetic", False) or getattr(args, "geometric", False):
        ov.append("app.camera=synthetic")
    if getattr(args, "geometric", False):
        ov.append("app.synthetic.render=geometric")
    if getattr(args, "log_dir", None):
        ov.append(f"log.directory={args.log_dir}")
    return ov


class StartRefused(RuntimeError):
    """The flight cannot start (vehicle locked by another app, flight log unusable): one line, exit 2.

    Raised before the app connects, so nothing has been commanded.
    """


def _cmd_fly(args: argparse.Namespace) -> int:
    from companion.app.record import is_recording, record_kwargs
    from companion.config import load_config
    from companion.configbase import ConfigError

    if args.record and is_recording(args.record):
        raise ConfigError(f"--record {args.record}: already holds a recording (index.csv); choose a new folder")
    cfg = load_config(args.config, _overrides(args))
    if args.shadow:
        from companion.app.shadow import shadow

        code, folder, _ = run_flight_process(shadow(cfg, duration=args.duration, plot=not args.no_plot,
                                                    record=args.record, record_kw=record_kwargs(args)))
        print(f"companion: shadow log {folder}", file=sys.stderr)
        return exit_when_done(code)
    from companion.app.preflight import stdin_confirm

    try:
        reason, folder, _ = run_flight_process(fly(cfg, status_line=args.status, plot=not args.no_plot,
                                                   record=args.record, record_kw=record_kwargs(args),
                                                   confirm=None if args.yes else stdin_confirm))
    except StartRefused as e:
        print(f"companion fly: {e}", file=sys.stderr)
        return 2
    print(f"companion: flight log {folder}", file=sys.stderr)
    return exit_when_done(int(reason))


def run_flight_process(main: Awaitable[Any], executor_grace: float = 2.0) -> Any:
    """``asyncio.run`` for the CLI, without waiting forever for a hung worker thread.

    asyncio.run() joins the default executor's threads at the end (Python 3.11: without a timeout),
    and a detector call that never returns (a hung driver, a wedged model) would keep the process
    alive long after the flight reached its safe state. Here the workers get ``executor_grace``
    seconds; ``exit_when_done`` handles one that is still stuck.
    """
    import threading
    from concurrent.futures import ThreadPoolExecutor

    executor = ThreadPoolExecutor(thread_name_prefix="companion-worker")
    loop = asyncio.new_event_loop()
    loop.set_default_executor(executor)
    try:
        asyncio.set_event_loop(loop)
        return loop.run_until_complete(main)
    finally:
        try:
            tasks = asyncio.all_tasks(loop)
            for task in tasks:
                task.cancel()
            loop.run_until_complete(asyncio.gather(*tasks, return_exceptions=True))
            loop.run_until_complete(loop.shutdown_asyncgens())
        finally:
            executor.shutdown(wait=False, cancel_futures=True)
            deadline = time.monotonic() + executor_grace
            for t in threading.enumerate():
                if t.name.startswith("companion-worker"):
                    t.join(max(0.0, deadline - time.monotonic()))
            asyncio.set_event_loop(None)
            loop.close()


def exit_when_done(code: int) -> int:
    """The flight is over and its log closed: if a worker thread still runs (a hung detector call), end the
    process now with the flight's exit code instead of waiting for it at interpreter exit forever."""
    import threading

    stuck = [t.name for t in threading.enumerate() if t is not threading.main_thread() and not t.daemon
             and t.is_alive()]
    if not stuck:
        return code
    print(f"companion: worker thread(s) {', '.join(stuck)} still running after the safe end: exiting anyway "
          f"(exit {code})", file=sys.stderr)
    with contextlib.suppress(Exception):
        sys.stdout.flush()
        sys.stderr.flush()
    os._exit(code)


def _cmd_plot(args: argparse.Namespace) -> int:
    from companion.app.plot import plot_flight
    from companion.flightlog import latest_flight

    folder = Path(args.folder)
    if not (folder / "meta.json").exists():
        latest = latest_flight(folder)
        if latest is None:
            print(f"companion log plot: {folder}: no flight log here", file=sys.stderr)
            return 1
        folder = latest
    try:
        out = plot_flight(folder, args.output)
    except Exception as e:  # a corrupt or foreign file in the folder: one line, never a traceback
        text = " ".join(str(e).split())[:200]
        print(f"companion log plot: {folder}: cannot plot ({type(e).__name__}: {text})", file=sys.stderr)
        return 1
    print(out)
    return 0


def build_camera(cfg: Config, link: Any, log: Any, judge: Any = None,
                 truth: TruthSource | None = None) -> tuple[Any, Any, bool]:
    """(camera source, perception, run perception in a thread) for the configured camera; the synthetic
    camera draws from ``truth``'s pose and its gates go to the log and to ``judge``
    (companion/app/outcome.py, ground truth).

    Every source is wrapped in CheckedCamera: each frame is checked for plausibility (size, type,
    timestamps, frozen content) before perception sees it.
    """
    from companion.app.camera import CheckedCamera

    cam, perception, in_thread = _build_camera(cfg, link, log, judge, truth)
    return CheckedCamera.from_config(cam, cfg), perception, in_thread


def _build_camera(cfg: Config, link: Any, log: Any, judge: Any = None,
                  truth: TruthSource | None = None) -> tuple[Any, Any, bool]:
    from companion.app.flight import gate_logger
    from companion.app.synthcam import SyntheticCamera, VehiclePose

    if cfg.app.camera == "synthetic":
        if truth is None:
            raise ValueError("the synthetic camera draws from a truth source (open_truth or LinkPositionTruth)")

        def pose() -> VehiclePose | None:
            # Sensor simulation only: the pose draws the picture; the controller never sees it.
            att = link.attitude
            if truth.latest() is None or att is None:
                return None
            # Stamped with the attitude sample's time: the frame is "captured" at the instant whose
            # attitude drew it, so the controller's attitude-at-capture lookup sees the same attitude.
            # PX4 SIH's truth: its true pose at that instant; the link's: its newest position, PX4's attitude.
            true = truth.at(att.t_rx)
            if true is None:
                return None
            return VehiclePose(att.t_rx, true.position_ned, true.q_wxyz)

        cam = SyntheticCamera(cfg, pose, on_gate=gate_logger(log, judge))
        if cam.render == "geometric":
            return cam, cam.perception(), False
        from perception.pipeline import Pipeline

        return cam, cam.perception(Pipeline.from_config(cfg)), True
    from companion.app.camera import DeviceCamera, PipelinePerception
    from perception.pipeline import Pipeline

    return DeviceCamera.open(cfg.perception.source), PipelinePerception(Pipeline.from_config(cfg)), True


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

    # One app per vehicle, held until the link is closed (then nothing of ours commands it any more).
    lock = VehicleLock(cfg.link.url)
    try:
        lock.acquire()
    except VehicleBusy as e:
        raise StartRefused(str(e)) from None
    try:
        return await _fly_locked(cfg, status_line=status_line, plot=plot, stderr=stderr,
                                 handle_signals=handle_signals, alongside=alongside, record=record,
                                 record_kw=record_kw, confirm=confirm)
    finally:
        lock.release()


async def _fly_locked(
    cfg: Config,
    *,
    status_line: bool,
    plot: bool,
    stderr: Any,
    handle_signals: bool,
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
    from companion.app.telemetry import LinkPositionTruth
    from companion.config import config_as_dict
    from companion.flightlog import FlightLog, FlightLogError

    try:  # refused before connecting: a flight without its log is not flown
        log = FlightLog.create(cfg.log.directory, config_as_dict(cfg), min_free_mb=cfg.log.min_free_mb,
                               flush_interval=cfg.log.flush_interval, stderr=stderr)
    except FlightLogError as e:
        raise StartRefused(f"cannot start the flight log: {e}") from None
    print(f"companion: logging to {log.folder}", file=stderr, flush=True)
    notifier = Notifier()
    app: FlightApp | None = None
    link = VehicleLink.from_config(cfg, on_event=lambda kind, detail: app.on_link_event(kind, detail) if app
                                   else log.event(f"link {kind} {detail}"))
    truth: TruthSource | None = None
    try:
        from companion.px4sitl.truth import open_truth

        # PX4 SIH's ground truth for the camera and the score (px4.truth_url), else the link's own position.
        truth = open_truth(cfg) or LinkPositionTruth(link)
        judge = GateJudge()  # ground truth, where a simulator provides it: scores the gates, never steers
        camera, perception, in_thread = build_camera(cfg, link, log, judge, truth)
        if record is not None:  # --record DIR: every frame with its time and attitude (companion/app/record.py)
            from companion.app.record import RecordingCamera, link_attitude, recorder_for_flight

            camera = RecordingCamera(camera, recorder_for_flight(record, cfg, log, stderr, **(record_kw or {})),
                                     link_attitude(link))
        app = FlightApp(cfg, link, camera, perception, log, notifier=notifier, stderr=stderr,
                        status_line=status_line, perception_in_thread=in_thread, judge=judge,
                        confirm=confirm, truth=truth)
        loop = asyncio.get_running_loop()
        if handle_signals:
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.add_signal_handler(sig, app.trip, Reason.SIGNAL, f"{signal.Signals(sig).name} received")
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
        if handle_signals:
            loop = asyncio.get_running_loop()
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.remove_signal_handler(sig)
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
    from companion.app.flight import GROUND_STATES
    from companion.app.states import Reason, State

    detail = f"{type(err).__name__}: {err}"
    print(f"companion: flight logic failed: {detail}", file=stderr, flush=True)
    if not app.sm.done:
        with contextlib.suppress(Exception):
            await asyncio.wait_for(link.close(), 10.0)
        dst = State.ABORT_NOT_ARMED if app.sm.state in GROUND_STATES else State.SAFE_FAILSAFE_LINK
        with contextlib.suppress(Exception):
            app.sm.go(dst, f"{detail}; streaming stopped", Reason.EXCEPTION)
    summary = app.summary()
    summary.setdefault("error", detail)
    reason = app.sm.outcome if app.sm.outcome is not None else Reason.EXCEPTION
    return reason, summary


# ---------------------------------------------------------------------------- simulated PX4 process


class SimPX4Process:
    """The simulated PX4 in its own process (``python -m companion.sim.px4 --port 0``), for real-time runs."""

    def __init__(self, config_files: list[str] | None = None, overrides: list[str] | None = None,
                 extra: list[str] | None = None, timeout: float = 20.0) -> None:
        cmd = [sys.executable, "-m", "companion.sim.px4", "--port", "0"]
        for f in config_files or []:
            cmd += ["--config", f]
        for o in overrides or []:
            cmd += ["--set", o]
        cmd += extra or []
        from companion.px4sitl.launcher import die_with_parent

        # Own session: a Ctrl-C in the terminal reaches the app only, which hands over to HOLD while the
        # simulated PX4 still runs; the parent-death signal still ends the sim if the app is killed.
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                     bufsize=1, env={**os.environ, "PYTHONUNBUFFERED": "1"},
                                     start_new_session=True, preexec_fn=die_with_parent)
        self.remote_port: int | None = None
        self.port = self._read_port(timeout)

    def _read_port(self, timeout: float) -> int:
        import selectors

        sel = selectors.DefaultSelector()
        assert self.proc.stdout is not None
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if not sel.select(timeout=max(0.0, deadline - time.monotonic())):
                break
            line = self.proc.stdout.readline()
            if not line:
                break
            if line.startswith("PORT "):
                parts = line.split()  # "PORT <own> REMOTE <where mavsdk listens>"
                self.remote_port = int(parts[3]) if len(parts) >= 4 and parts[3].isdigit() else None
                return int(parts[1])
        self.stop()
        raise RuntimeError(f"simulated PX4 did not report its port within {timeout:.0f} s")

    @property
    def url(self) -> str:
        # mavsdk listens on 127.0.0.1 and the sim sends there, as with PX4 SITL: nothing binds 0.0.0.0.
        if self.remote_port is not None:
            return f"udpin://127.0.0.1:{self.remote_port}"
        return f"udpout://127.0.0.1:{self.port}"

    def command(self, line: str) -> None:
        """A switch on the sim's stdin (deny_arming 1, drop 1, takeover POSCTL, ...)."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def stop(self, timeout: float = 10.0) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=timeout)
        for f in (self.proc.stdin, self.proc.stdout):
            with contextlib.suppress(Exception):
                f.close()

    def __enter__(self) -> SimPX4Process:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


# ---------------------------------------------------------------------------------- companion sim


def detector_available(cfg: Config) -> str | None:
    """None when the configured detector loads, else the one-line reason it does not."""
    try:
        from perception.detector import Detector

        Detector.from_config(cfg.perception)
        return None
    except Exception as e:  # a missing or broken model file
        return f"{type(e).__name__}: {e}"


def sim_overrides(args: argparse.Namespace) -> list[str]:
    """The ``--set`` list of a ``companion sim`` flight (simulated PX4 or PX4 SITL): synthetic camera, the
    gate motion and seed asked for, and the geometric camera when the detector cannot run."""
    from companion.config import load_config

    ov = [*getattr(args, "overrides", []), "app.camera=synthetic"]
    if getattr(args, "motion", None):
        ov.append(f"app.synthetic.motion={args.motion}")
    if getattr(args, "seed", None) is not None:
        ov.append(f"sim.seed={args.seed}")
    cfg = load_config(args.config, ov)
    if cfg.app.synthetic.render == "image" and (why := detector_available(cfg)) is not None:
        print(f"companion sim: detector unavailable ({why}); using the geometric camera", file=sys.stderr)
        ov.append("app.synthetic.render=geometric")
    return ov


def run_sim(args: argparse.Namespace) -> int:
    """``companion sim``: simulated PX4 (own process) + synthetic camera + the app, in real time."""
    from companion.config import load_config

    ov = sim_overrides(args)
    with SimPX4Process(args.config, [o for o in ov if o.startswith(("sim.", "airframe."))]) as px4:
        print(f"companion sim: simulated PX4 on 127.0.0.1:{px4.port} (pid {px4.proc.pid})", file=sys.stderr)
        cfg = load_config(args.config, [*ov, f"link.url={px4.url}"])
        try:
            reason, folder, summary = run_flight_process(fly(cfg, status_line=not getattr(args, "no_status", False),
                                                             plot=not getattr(args, "no_plot", False)))
        except StartRefused as e:
            print(f"companion sim: {e}", file=sys.stderr)
            return 2
    print_flight_report(folder, summary)
    return exit_when_done(int(reason))


def print_flight_report(folder: Path, summary: dict[str, Any]) -> None:
    """The end of ``companion sim``: outcome, each gate crossing (from the logged truth), latency, log folder."""
    from companion.flightlog import gate_crossings, read_flight

    f = read_flight(folder)
    cross = gate_crossings(f)
    lat = summary.get("frame_to_setpoint_ms", {})
    print(f"outcome: {summary.get('outcome')} ({summary.get('reason')}): {summary.get('detail')}")
    for i, c in enumerate(cross, 1):
        print(f"gate {i}: crossed at t = {c.t:.2f} s, {c.d_center:.2f} m from the centre "
              f"({'through' if c.through else 'missed'}, radius {c.radius:.2f} m)")
    if lat.get("p50") is not None:
        print(f"frame -> setpoint latency: p50 {lat['p50']:.1f} ms, p95 {lat['p95']:.1f} ms; "
              f"app CPU {summary.get('cpu_percent', 0):.0f} %")
    print(f"log: {folder}" + (f"  plot: {folder / 'plot.png'}" if (folder / "plot.png").exists() else ""))


def add_sim_arguments(p: argparse.ArgumentParser) -> None:
    """The options ``companion sim`` adds for its default (simulated PX4 + app) mode."""
    p.add_argument("--no-status", action="store_true", help="no live status line on stderr")
