"""SIGTERM and SIGKILL of a real ``companion fly`` process mid-flight, against a simulated PX4 the test hosts."""

from __future__ import annotations

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


def _start_fly(tmp_path: Path, url: str, env: dict[str, str] | None = None,
               extra: tuple[str, ...] = ()) -> tuple[subprocess.Popen, Path]:
    logdir = tmp_path / "flights"
    cmd = [sys.executable, "-m", "companion.cli", "fly", "--yes", "--url", url, "--log-dir", str(logdir), "--no-plot"]
    for o in (*BASE_OVERRIDES, *extra):
        cmd += ["--set", o]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            cwd=Path(__file__).resolve().parents[2], env={**os.environ, **(env or {})})
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
    # mavsdk died with the process: setpoints stopped, PX4's offboard-loss failsafe holds.
    assert sim.wait_event("failsafe:offboard_loss", timeout=5.0) is not None
    assert sim.wait_for(lambda: sim.mode == "HOLD", timeout=5.0)


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
    # The vehicle left OFFBOARD: the link's loop guard (a thread) commanded HOLD at ~1.2 s, or, had that
    # failed, PX4's offboard-loss failsafe after the kill. Either way no setpoint arrives any more.
    assert sim.wait_for(lambda: sim.mode == "HOLD", timeout=5.0)
    ev = [e for _, e in sim.events]
    assert any(e.startswith("mode:HOLD") for e in ev[ev.index("mode:OFFBOARD:command"):])
    n = sim.setpoint_count
    time.sleep(0.5)
    assert sim.setpoint_count == n
