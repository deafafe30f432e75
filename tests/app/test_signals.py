"""SIGTERM and SIGKILL of a real ``companion fly`` process mid-flight, against a simulated PX4 the test hosts."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from flighthelpers import BASE_OVERRIDES

from companion.app.states import Reason
from companion.flightlog import read_flight

pytestmark = pytest.mark.timeout(120)


def interactive_sigint() -> None:
    """preexec_fn: SIGINT as a terminal's foreground process has it. A child inherits an ignored SIGINT (a CI
    started as a background job ignores it, and so does everything below it), and then Python installs no
    KeyboardInterrupt handler: a Ctrl-C in the app's first 0.3 s, or during `companion sim`'s PX4 start, did nothing
    in such a run. The app honours an ignored SIGINT; what these tests check is a Ctrl-C in a terminal."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start_fly(tmp_path: Path, url: str, env: dict[str, str] | None = None,
               extra: tuple[str, ...] = ()) -> tuple[subprocess.Popen, Path]:
    logdir = tmp_path / "flights"
    cmd = [sys.executable, "-m", "companion.cli", "fly", "--yes", "--url", url, "--log-dir", str(logdir), "--no-plot"]
    for o in (*BASE_OVERRIDES, *extra):
        cmd += ["--set", o]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            cwd=Path(__file__).resolve().parents[2], env={**os.environ, **(env or {})},
                            preexec_fn=interactive_sigint)
    return proc, logdir


class NotifySocket:
    """What systemd does for Type=notify: an AF_UNIX datagram socket; collects every message."""

    def __init__(self, path: Path) -> None:
        self.path = str(path)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(self.path)
        self.sock.settimeout(0.2)
        self.messages: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.messages.append(self.sock.recv(4096).decode())
            except TimeoutError:
                continue
            except OSError:
                return

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.sock.close()


def _wait_engaged(proc: subprocess.Popen, logdir: Path, timeout: float = 40.0) -> Path:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, f"companion fly exited early: {proc.stderr.read()}"
        for states in logdir.glob("*/states.csv"):
            if ",ENGAGE," in states.read_text():
                return states.parent
        time.sleep(0.1)
    raise TimeoutError("companion fly never reached ENGAGE")


def _reap(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.wait(timeout=10)
    if proc.stderr:
        proc.stderr.close()


def test_sigterm_mid_flight_hands_over_to_hold(sim, tmp_path):
    notify = NotifySocket(tmp_path / "notify.sock")
    env = {"NOTIFY_SOCKET": notify.path, "WATCHDOG_USEC": "1000000"}
    proc, logdir = _start_fly(tmp_path, sim.url_for_mavsdk, env)
    try:
        folder = _wait_engaged(proc, logdir)
        time.sleep(0.7)
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=30)
        err = proc.stderr.read()
    finally:
        _reap(proc)
        notify.close()
    assert rc == Reason.SIGNAL.value, err
    f = read_flight(folder)
    assert f.state_path()[-3:] == ["ENGAGE", "HANDBACK", "SAFE_HOLD"]
    assert "SIGTERM" in f.states[-1]["reason"]
    assert f.summary["outcome"] == "SAFE_HOLD" and f.summary["reason"] == "SIGNAL"
    assert "SAFE_HOLD" in err and "SIGTERM" in err  # the safe state and its reason on stderr too
    assert sim.mode == "HOLD" and sim.armed
    assert not any(e.startswith("failsafe") for _, e in sim.events)  # an orderly hand-over, not a failsafe
    # systemd notify protocol, as a Type=notify service with WatchdogSec would see it.
    msgs = notify.messages
    assert msgs[0].startswith("READY=1")
    assert msgs.count("WATCHDOG=1") >= 5
    assert any(m.startswith("STATUS=ENGAGE") for m in msgs)
    assert msgs[-1].startswith("STOPPING=1") and "SAFE_HOLD" in msgs[-1]


def test_sigkill_mid_flight_leaves_a_readable_log(sim, tmp_path):
    proc, logdir = _start_fly(tmp_path, sim.url_for_mavsdk)
    try:
        folder = _wait_engaged(proc, logdir)
        time.sleep(1.2)
        t_kill = time.monotonic()
        os.kill(proc.pid, signal.SIGKILL)
        rc = proc.wait(timeout=10)
    finally:
        _reap(proc)
    assert rc == -signal.SIGKILL
    f = read_flight(folder)
    assert f.summary == {"outcome": "running"}  # never closed: the reader still works
    assert f.state_path()[-1] == "ENGAGE"
    t_kill_flight = t_kill - f.meta["t0_monotonic"]
    # At most the last second is lost (flush every log.flush_interval = 0.5 s).
    for topic in ("los", "setpoints", "telemetry", "detections"):
        assert f[topic]["t"].max() >= t_kill_flight - 1.0, topic
    # mavsdk died with the process: setpoints stopped, PX4's offboard-loss failsafe acts (its default,
    # COM_OBL_RC_ACT 0 with no RC: the Position-mode fallback descends and lands).
    assert sim.wait_event("failsafe:offboard_loss", timeout=5.0) is not None
    assert sim.wait_event("mode:POSCTL:failsafe", timeout=5.0) is not None


def test_blocked_event_loop_kills_the_process_so_px4_fails_safe(sim, tmp_path):
    """A call that never returns on the loop's thread: no watchdog task can run; the deadman thread kills us."""
    proc, logdir = _start_fly(tmp_path, sim.url_for_mavsdk,
                              extra=("app.synthetic.fault=block", "app.synthetic.fault_after=1.0"))
    try:
        folder = _wait_engaged(proc, logdir)
        rc = proc.wait(timeout=30)
        err = proc.stderr.read()
    finally:
        _reap(proc)
    assert rc == -signal.SIGKILL
    assert "event loop stalled" in err
    f = read_flight(folder)
    assert f.summary == {"outcome": "running"} and f.state_path()[-1] == "ENGAGE"
    assert any("event loop stalled" in str(t) for t in f["events"]["text"])  # its last words reached the log
    # The vehicle left OFFBOARD: the link's loop guard (a thread) commanded HOLD ~1.2 s into the stall, before
    # the deadman's kill at 2 s, whether PX4 had confirmed OFFBOARD yet or not (the stall may come while the
    # switch is pending: frames are perceived meanwhile). No setpoint arrives any more.
    assert sim.wait_for(lambda: sim.mode == "HOLD", timeout=5.0)
    ev = [e for _, e in sim.events]
    assert any(e.startswith("mode:HOLD") for e in ev[ev.index("mode:OFFBOARD:command"):])
    n = sim.setpoint_count
    time.sleep(0.5)
    assert sim.setpoint_count == n


def _wait_state_file(proc: subprocess.Popen, logdir: Path, state: str, timeout: float = 40.0) -> Path:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, f"companion fly exited early: {proc.stderr.read()}"
        for states in logdir.glob("*/states.csv"):
            if f",{state}," in states.read_text():
                return states.parent
        time.sleep(0.05)
    raise TimeoutError(f"companion fly never reached {state}")


def test_sigint_during_takeoff_commands_a_confirmed_hold(sim, tmp_path):
    proc, logdir = _start_fly(tmp_path, sim.url_for_mavsdk, extra=("app.takeoff_altitude=8",))
    try:
        folder = _wait_state_file(proc, logdir, "TAKEOFF")
        time.sleep(1.0)
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=30)
        err = proc.stderr.read()
    finally:
        _reap(proc)
    assert rc == Reason.SIGNAL.value, err
    f = read_flight(folder)
    assert f.state_path()[-2:] == ["TAKEOFF", "SAFE_HOLD"]
    assert f.states[-1]["reason"] == "SIGINT received; PX4 holds"
    assert "TAKEOFF -> SAFE_HOLD: SIGINT received; PX4 holds (exit 23 SIGNAL)" in err
    ev = [e for _, e in sim.events]
    assert "mode:HOLD:command" in ev and "mode:HOLD:takeoff_done" not in ev  # commanded, before the top
    assert sim.mode == "HOLD" and sim.armed and sim.truth().p[2] < 7.5


def _udp_sockets(pid: int) -> list[str]:
    """Local addresses (ip:port) of every UDP socket the process holds, from /proc (IPv4 and IPv6)."""
    import os as _os

    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = _os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    out = []
    for table, v6 in ((f"/proc/{pid}/net/udp", False), (f"/proc/{pid}/net/udp6", True)):
        for line in Path(table).read_text().splitlines()[1:]:
            cols = line.split()
            if cols[9] in inodes:
                ip_hex, port_hex = cols[1].split(":")
                if v6:
                    ip = "::" if int(ip_hex, 16) == 0 else ip_hex
                else:
                    ip = ".".join(str(b) for b in bytes.fromhex(ip_hex)[::-1])
                out.append(f"{ip}:{int(port_hex, 16)}")
    return out


def _children(pid: int) -> list[int]:
    kids = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        kids += [int(c) for c in (task / "children").read_text().split()]
    return kids


@pytest.mark.skipif(not Path("/proc/self/net/udp").exists(), reason="needs Linux /proc")
def test_companion_sim_binds_only_localhost(tmp_path):
    """`companion sim`: the app (mavsdk) and the simulated PX4 hold UDP sockets on 127.0.0.1 only."""
    cmd = [sys.executable, "-m", "companion.cli", "sim", "--no-plot", "--no-status", "--camera", "geometric",
           "--set", f"log.directory={tmp_path / 'flights'}", "--set", "app.synthetic.distance=25",
           "--set", "app.takeoff_altitude=5"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            cwd=Path(__file__).resolve().parents[2])
    try:
        _wait_state_file(proc, tmp_path / "flights", "ARM", timeout=60.0)  # mavsdk connected, PX4 answering
        app_socks = _udp_sockets(proc.pid)
        kids = _children(proc.pid)
        sim_socks = [s for k in kids for s in _udp_sockets(k)]
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=30)
        finally:
            _reap(proc)
    assert kids, "the simulated PX4 runs as a child process"
    assert app_socks and sim_socks, (app_socks, sim_socks)
    for s in app_socks + sim_socks:
        assert s.startswith("127.0.0.1:"), (app_socks, sim_socks)


@pytest.mark.parametrize("second", [signal.SIGTERM, signal.SIGINT])
def test_a_second_signal_during_the_safe_end_changes_nothing(sim, tmp_path, second):
    """Issue #22: a second SIGTERM 0.15 s after the first (double Ctrl-C, a stop script) killed the process
    (exit -15, summary.json "running"); SIGTERM then SIGINT: exit -2. Now the first one's safe end stands."""
    proc, logdir = _start_fly(tmp_path, sim.url_for_mavsdk)
    try:
        folder = _wait_engaged(proc, logdir)
        time.sleep(0.7)
        proc.send_signal(signal.SIGTERM)
        time.sleep(0.15)
        if proc.poll() is None:
            proc.send_signal(second)
        for _ in range(20):  # and more, through the whole teardown, until the process is gone
            if proc.poll() is not None:
                break
            time.sleep(0.1)
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(second)
        rc = proc.wait(timeout=30)
        err = proc.stderr.read()
    finally:
        _reap(proc)
    assert rc == Reason.SIGNAL.value, err[-2000:]
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err[-2000:]
    f = read_flight(folder)
    assert f.summary["outcome"] == "SAFE_HOLD" and f.summary["reason"] == "SIGNAL", f.summary
    assert "SIGTERM" in f.states[-1]["reason"]
    assert sim.mode == "HOLD" and sim.armed
    assert all(t.truncated_rows == 0 for t in f.tables.values())


def _loading_app_modules(pid: int) -> bool:
    """The process has started importing the app (pydantic's compiled core is mapped): past Python's own start."""
    try:
        return "pydantic_core" in Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return False


@pytest.mark.parametrize("when", ["loading", "set-up"])
def test_sigint_while_starting_is_one_line_not_a_traceback(sim, tmp_path, when):
    """Issue #22: SIGINT in the first 0.3 s (the app's modules still loading) gave a KeyboardInterrupt traceback.
    Before the flight: one line, a defined exit code, nothing armed. (Python's own start-up, before any of the
    app's code runs, is not the app's to handle.)"""
    t0 = time.monotonic()
    proc, logdir = _start_fly(tmp_path, sim.url_for_mavsdk)
    try:
        deadline = time.monotonic() + 30
        ready = (lambda: _loading_app_modules(proc.pid)) if when == "loading" else (
            lambda: any(logdir.glob("*/meta.json")))
        while not (seen := ready()) and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.002)
        # What the harness saw, for a failure (CI twice flew the whole flight: was the signal sent in time?)
        sent = (f"signal sent {time.monotonic() - t0:.2f} s after the start, {when} seen {seen}, "
                f"process {'running' if proc.poll() is None else f'already exited {proc.returncode}'}")
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=30)
        err = proc.stderr.read()
    finally:
        _reap(proc)
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err[-2000:]
    assert rc in (130, Reason.SIGNAL.value), (rc, sent, err[-2000:])
    last = [ln for ln in err.splitlines() if ln.startswith("companion: ")][-1:]
    assert last and ("interrupted" in last[0] or "SIGINT" in last[0] or "flight log" in last[0]), err[-2000:]
    assert not sim.armed
    for summary in logdir.glob("*/summary.json"):  # a flight folder, if one was made, is closed
        assert '"running"' not in summary.read_text()


def test_a_signal_while_fly_starts_is_kept_for_the_flight(capfd) -> None:
    """A signal after the CLI handed signals to fly() and before fly's guard existed was "received after the flight
    ended: ignored" and the whole flight was flown (exit 0); a ``systemctl stop`` at start-up the same. The CLI's
    own handler, called as the signal calls it, must keep it for the flight's guard, which trips the flight with
    it at once."""
    import asyncio
    import io

    from companion.app import main, session

    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    loop = asyncio.new_event_loop()
    try:
        main._guard_signals(session.HANDOFF)
        handler = signal.getsignal(signal.SIGINT)
        assert callable(handler)
        with pytest.raises(KeyboardInterrupt):  # before fly(): the command is interrupted, nothing flown
            handler(signal.SIGINT, None)
        session.HANDOFF.open()
        main._STARTED.set()
        handler(signal.SIGINT, None)  # fly() called, its guard not made yet: kept, no exception
        handler(signal.SIGTERM, None)  # a second one: the first is what the flight names
        guard = session._SignalGuard(loop, io.StringIO())
        try:
            assert guard.pending == "SIGINT"

            class _App:
                tripped: tuple = ()

                def trip(self, reason: Reason, why: str) -> None:
                    self.tripped = (reason, why)

            app = _App()
            guard.attach(app)  # type: ignore[arg-type]
            assert app.tripped == (Reason.SIGNAL, "SIGINT received during set-up")
        finally:
            guard.restore()
        assert "ignored" not in capfd.readouterr().err
        handler(signal.SIGTERM, None)  # the guard took over and gave back: after the flight, ignored (and said)
        assert "SIGTERM received after the flight ended: ignored" in capfd.readouterr().err
        assert session.HANDOFF.take() is None
    finally:
        main._STARTED.clear()
        loop.close()
        for s, h in saved.items():
            signal.signal(s, h)


def _freeze(proc: subprocess.Popen, seconds: float) -> None:
    """The app stopped as a whole (SIGSTOP: every thread, MAVSDK's too), then resumed."""
    os.kill(proc.pid, signal.SIGSTOP)
    time.sleep(seconds)
    os.kill(proc.pid, signal.SIGCONT)


def test_app_frozen_in_engage_names_px4s_failsafe_and_never_holds_over_it(sim, tmp_path):
    """Issue #22: frozen 3 s in ENGAGE, the app commanded Hold over PX4's failsafe descent on resume, then its
    deadman killed it (exit -9, summary "running") saying "PX4's offboard-loss failsafe takes over" while PX4
    held at 7 m. Now: what PX4 does is read from a fresh heartbeat first; its failsafe is named; summary final."""
    proc, logdir = _start_fly(tmp_path, sim.url_for_mavsdk)
    try:
        folder = _wait_engaged(proc, logdir)
        deadline = time.monotonic() + 10.0  # the app has seen PX4 in OFFBOARD (its switch is done)
        while "'new': 'OFFBOARD'" not in (folder / "events.csv").read_text() and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)
        _freeze(proc, 3.0)
        rc = proc.wait(timeout=30)
        err = proc.stderr.read()
    finally:
        _reap(proc)
    ev = [e for _, e in sim.events]
    assert "failsafe:offboard_loss" in ev and "mode:POSCTL:failsafe" in ev, ev  # PX4's failsafe acted, truly
    assert rc == Reason.AUTOPILOT_MODE.value, (rc, err[-3000:])
    f = read_flight(folder)
    assert f.summary["outcome"] == "AUTOPILOT" and f.summary["exit_code"] == 33, f.summary
    last = f.states[-1]["reason"]
    assert "offboard-loss failsafe" in last and "did not run" in last and "POSCTL" in last, last
    assert "event loop stalled" not in err  # no kill
    # No Hold of ours over the failsafe: PX4 still flies its failsafe (descending in Position mode).
    assert "mode:HOLD:command" not in ev[ev.index("mode:POSCTL:failsafe"):], ev
    assert sim.mode == "POSCTL"
    assert all(t.truncated_rows == 0 for t in f.tables.values())


def test_app_frozen_in_takeoff_is_an_app_stall_not_a_link_loss(sim, tmp_path):
    """Issue #22: frozen 3 s in TAKEOFF (or 1.5 s in ACQUIRE) ended as SAFE_FAILSAFE_LINK "no telemetry",
    though the link was fine: the app had stalled."""
    proc, logdir = _start_fly(tmp_path, sim.url_for_mavsdk, extra=("app.takeoff_altitude=10",))
    try:
        folder = _wait_state_file(proc, logdir, "TAKEOFF")
        time.sleep(0.3)
        _freeze(proc, 3.0)
        rc = proc.wait(timeout=30)
        err = proc.stderr.read()
    finally:
        _reap(proc)
    assert rc == Reason.PERCEPTION_STALL.value, (rc, err[-3000:])
    f = read_flight(folder)
    assert f.state_path()[-2:] == ["TAKEOFF", "SAFE_HOLD"], f.state_path()
    last = f.states[-1]["reason"]
    assert "the app stalled" in last and "no telemetry" not in last and "PX4 holds" in last, last
    assert not any(e == "link:dropped" for _, e in sim.events)  # the link was never down
    assert sim.mode == "HOLD" and sim.armed
    assert all(t.truncated_rows == 0 for t in f.tables.values())


def test_watchdog_sigabrt_is_recorded_and_the_summary_is_final(sim, tmp_path):
    """Issue #22: systemd's watchdog SIGABRT left summary.json "running" with no record that it fired."""
    proc, logdir = _start_fly(tmp_path, sim.url_for_mavsdk, extra=("app.takeoff_altitude=8",))
    try:
        folder = _wait_state_file(proc, logdir, "TAKEOFF")
        time.sleep(0.5)
        proc.send_signal(signal.SIGABRT)
        rc = proc.wait(timeout=30)
        err = proc.stderr.read()
    finally:
        _reap(proc)
    assert rc == Reason.SIGNAL.value, (rc, err[-2000:])
    f = read_flight(folder)
    assert f.summary["reason"] == "SIGNAL" and f.summary["outcome"] == "SAFE_HOLD", f.summary
    assert "SIGABRT" in f.states[-1]["reason"] and "watchdog" in f.states[-1]["reason"]
    assert any("SIGABRT" in str(t) for t in f["events"]["text"])
    assert sim.mode == "HOLD" and sim.armed
