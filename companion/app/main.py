"""``companion fly`` (the flight app), ``companion log plot``, and running a flight as the process's work.

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
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from collections.abc import Awaitable

    from companion.app.session import SignalHandoff


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


def _cmd_fly(args: argparse.Namespace) -> int:
    from companion.app.record import is_recording, record_kwargs
    from companion.app.session import HANDOFF, StartRefused, fly
    from companion.config import load_config
    from companion.configbase import ConfigError

    _guard_signals(HANDOFF)
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

    HANDOFF.open()  # a signal before fly()'s guard exists is kept for it (companion/app/session.py)
    _STARTED.set()  # from here fly() owns SIGTERM/SIGINT (companion/app/session.py) until its log is closed
    try:
        reason, folder, _ = run_flight_process(fly(cfg, status_line=args.status, plot=not args.no_plot,
                                                   record=args.record, record_kw=record_kwargs(args),
                                                   confirm=None if args.yes else stdin_confirm))
    except StartRefused as e:
        print(f"companion fly: {e}", file=sys.stderr)
        return 2
    for sig in (signal.SIGTERM, signal.SIGINT):
        # The flight is over and logged: a late signal must not turn its exit code into -15/-2 while the
        # interpreter shuts down (which resets Python-level handlers to the default, not SIG_IGN).
        signal.signal(sig, signal.SIG_IGN)
    print(f"companion: flight log {folder}", file=sys.stderr)
    return exit_when_done(int(reason))


_STARTED = threading.Event()


def _guard_signals(handoff: SignalHandoff) -> None:
    """The process's SIGTERM/SIGINT outside fly(): before it, they end the command with one line ("interrupted",
    exit 130: nothing was commanded); between calling fly() and its guard existing, ``handoff`` keeps them for the
    flight; after it (the log is closed, worker threads are joined) they are ignored, so the exit code stays the
    flight's outcome instead of -15 / a KeyboardInterrupt traceback."""

    def on_signal(signum: int, frame: Any) -> None:
        if not _STARTED.is_set():
            raise KeyboardInterrupt
        if handoff.offer(signal.Signals(signum).name):
            return  # fly() is starting: its guard trips the flight with it at once
        with contextlib.suppress(Exception):
            os.write(2, f"companion: {signal.Signals(signum).name} received after the flight ended: ignored\n".encode())

    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, on_signal)


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
