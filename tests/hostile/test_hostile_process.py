"""Failing disks, a second app on the same vehicle, a hung worker thread, odd environments: the real
`companion fly` process against the simulated PX4 (real mavsdk over UDP), real filesystems, real signals.

A full disk is a real one: a small tmpfs mounted for the test (needs root, as on this machine and in CI;
skipped otherwise).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from flighthelpers import BASE_OVERRIDES

from companion.app.vehiclelock import VehicleBusy, VehicleLock, lock_name
from companion.flightlog import read_flight

pytestmark = pytest.mark.timeout(180)
APP_YAML = Path(__file__).resolve().parents[2] / "config" / "app.yaml"


def fly_cmd(url: str, log_dir: Path, *overrides: str) -> list[str]:
    cmd = [sys.executable, "-m", "companion.cli", "fly", "--config", str(APP_YAML), "--url", url,
           "--log-dir", str(log_dir), "--no-plot", "--yes"]
    for o in (*BASE_OVERRIDES, *overrides):
        cmd += ["--set", o]
    return cmd


def run_fly(url: str, log_dir: Path, *overrides: str, timeout: float = 120.0,
            env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(fly_cmd(url, log_dir, *overrides), capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **(env or {})})


def one_line(text: str) -> str:
    lines = text.strip().splitlines()
    assert len(lines) == 1, text[-3000:]
    return lines[0]


@contextlib.contextmanager
def tmpfs(path: Path, size: str, ro: bool = False) -> Iterator[Path]:
    """A real small filesystem (tmpfs) at ``path``; skips the test where mounting is not allowed."""
    path.mkdir(parents=True, exist_ok=True)
    opts = f"size={size}" + (",ro" if ro else "")
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a small tmpfs needs root")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(path)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def fill(folder: Path) -> None:
    """Fill the filesystem of ``folder`` to the last byte."""
    with open(folder / "filler", "wb", buffering=0) as f:
        with contextlib.suppress(OSError):
            while True:
                f.write(b"\0" * 65536)
        with contextlib.suppress(OSError):
            while True:
                f.write(b"\0")


def armed_ever(sim) -> bool:
    return any(e.startswith("arm") and not e.startswith("arm_denied") for _, e in sim.events)


# ------------------------------------------------------------------------------------------------ logging


def test_log_folder_not_a_folder_is_refused_before_connecting(sim, tmp_path):
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("x")
    r = run_fly(sim.url_for_mavsdk, blocker / "flights")
    line = one_line(r.stderr)
    assert r.returncode == 2 and line.startswith("companion fly: cannot start the flight log: ") and \
        "not_a_dir/flights: cannot make the flight-log folder (Not a directory)" in line, line
    assert not armed_ever(sim) and sim.setpoint_count == 0


def test_read_only_log_folder_is_refused_before_connecting(sim, tmp_path):
    with tmpfs(tmp_path / "ro", "1m", ro=True) as ro:
        r = run_fly(sim.url_for_mavsdk, ro / "flights")
        line = one_line(r.stderr)
        assert r.returncode == 2 and "Read-only file system" in line, line
    assert not armed_ever(sim)


def test_full_disk_at_start_is_refused_and_leaves_nothing_behind(sim, tmp_path):
    with tmpfs(tmp_path / "full", "1m") as disk:
        (disk / "flights").mkdir()
        (disk / "flights" / "earlier").mkdir()
        (disk / "flights" / "earlier" / "keep.csv").write_text("t\n1\n")  # a log recorded before
        fill(disk)
        r = run_fly(sim.url_for_mavsdk, disk / "flights", "log.min_free_mb=0")
        line = one_line(r.stderr)
        assert r.returncode == 2 and "No space left on device" in line, line
        # No half-made flight folder, no 0-byte meta.json.tmp, and what was there before is intact.
        assert sorted(p.name for p in (disk / "flights").iterdir()) == ["earlier"]
        assert (disk / "flights" / "earlier" / "keep.csv").read_text() == "t\n1\n"
        # And with the default free-space floor, a disk that is merely nearly full is refused the same way.
        (disk / "filler").unlink()
        r = run_fly(sim.url_for_mavsdk, disk / "flights")
        line = one_line(r.stderr)
        assert r.returncode == 2 and "MB free, the flight log needs 20 MB (log.min_free_mb)" in line, line
    assert not armed_ever(sim)


def test_disk_full_mid_flight_the_flight_goes_on_and_the_log_says_so(sim, tmp_path):
    """A tmpfs just large enough for the log's start: it fills up during the flight."""
    with tmpfs(tmp_path / "small", "340k") as disk:
        r = run_fly(sim.url_for_mavsdk, disk / "flights", "log.min_free_mb=0")
        err = r.stderr
        assert r.returncode == 0, err[-3000:]  # the flight's own outcome: through the gate and landed
        fails = [ln for ln in err.splitlines() if "flight log write failed" in ln]
        assert len(fails) == 1 and "No space left on device" in fails[0], err[-3000:]
        assert "Traceback" not in err
        (folder,) = (disk / "flights").iterdir()
        f = read_flight(folder)
        s = f.summary
        assert s["outcome"] == "SAFE_LANDED" and s["exit_code"] == 0  # final, never "running"
        assert s["log_complete"] is False and s["log_errors"] and s["log_rows_dropped"] > 0
        # states.csv holds only true transitions: a prefix of the flight's real path, never an invented one.
        logged = f.state_path()
        assert logged == s["states"][: len(logged)], (logged, s["states"])
        assert "ABORT_NOT_ARMED" not in logged
        assert all(t.truncated_rows <= 1 for t in f.tables.values())  # at most the row cut by the full disk
        assert not list(folder.glob("*.tmp")) and not (folder / ".reserve").exists()
    assert sim.landed and not sim.armed


def test_sigkill_loses_at_most_the_documented_bound(tmp_path):
    """A real writer at 30 Hz with the default flush interval, killed with SIGKILL right after it reported a
    row: every row older than flush_interval + two write gaps is on disk (README: at most 0.5 s). The bound
    is checked on the log's own clock, so a slow machine cannot fail it."""
    from companion.flightlog import DEFAULT_FLUSH_INTERVAL

    script = f"""
import sys, time
from companion.flightlog import FlightLog
log = FlightLog({str(tmp_path / 'k')!r}, config={{}})
i = 0
while True:
    t = log.now()
    log.write("truth", n=float(i), e=0.0, d=0.0, vn=0.0, ve=0.0, vd=0.0)
    i += 1
    if i % 37 == 0:
        print(repr(t), flush=True)
    time.sleep(1 / 30)
"""
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        for _ in range(3):
            t_reported = float(proc.stdout.readline())
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    tr = read_flight(tmp_path / "k")["truth"]
    t_disk = tr["t"]
    gaps = t_disk[1:] - t_disk[:-1]
    lost = t_reported - t_disk.max()
    assert lost <= DEFAULT_FLUSH_INTERVAL + 2 * max(gaps.max(), 1 / 30) + 1e-6, (lost, gaps.max())
    assert DEFAULT_FLUSH_INTERVAL + 2 / 30 < 0.5  # README's bound holds at the nominal write rate
    print(f"SIGKILL lost {lost:.3f} s of rows (flush interval {DEFAULT_FLUSH_INTERVAL} s)")


# ------------------------------------------------------------------------------------------ process hygiene


def test_second_app_on_the_same_vehicle_is_refused(sim, tmp_path):
    first = subprocess.Popen(fly_cmd(sim.url_for_mavsdk, tmp_path / "a"), stderr=subprocess.PIPE, text=True)
    try:
        assert first.stderr is not None
        for line in first.stderr:  # wait until the first app holds the lock and logs
            if "logging to" in line:
                break
        r = run_fly(sim.url_for_mavsdk, tmp_path / "b", timeout=60)
        line = one_line(r.stderr)
        assert r.returncode == 2, line
        assert f"another companion app (pid {first.pid}) is flying this vehicle" in line, line
        assert not (tmp_path / "b").exists()
        rest = first.communicate(timeout=120)[1]
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert first.returncode == 0, rest[-3000:]  # the first flight was not disturbed
    assert sum(1 for _, e in sim.events if e.startswith("arm") and not e.startswith("arm_denied")) == 1
    # Released at the end: the vehicle is free again.
    VehicleLock(sim.url_for_mavsdk).acquire().release()


def test_a_killed_app_never_leaves_the_vehicle_locked(tmp_path):
    url = "udpin://127.0.0.1:45999"
    holder = subprocess.Popen([sys.executable, "-c", f"""
from companion.app.vehiclelock import VehicleLock
import sys, time
VehicleLock({url!r}, __import__('pathlib').Path({str(tmp_path)!r})).acquire()
print('held', flush=True)
time.sleep(600)
"""], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(VehicleBusy, match=f"pid {holder.pid}"):
            VehicleLock(url, tmp_path).acquire()
        holder.send_signal(signal.SIGKILL)
        holder.wait(timeout=10)
    finally:
        if holder.poll() is None:
            holder.kill()
    VehicleLock(url, tmp_path).acquire().release()  # the kernel dropped the flock with the process
    assert (tmp_path / lock_name(url)).exists()


def test_lock_name_is_the_vehicle_not_the_baud_rate():
    assert lock_name("serial:///dev/ttyACM0:57600") == lock_name("serial:///dev/ttyACM0:921600")
    assert lock_name("udpin://127.0.0.1:14540") != lock_name("udpin://127.0.0.1:14541")
    assert lock_name("udpin://127.0.0.1:14540") == lock_name("udpin://0.0.0.0:14540") == lock_name("udp://:14540")
    assert lock_name("udpout://10.0.0.2:14540") != lock_name("udpout://10.0.0.3:14540")
    assert "/" not in lock_name("serial:///dev/ttyACM0:57600")


@pytest.mark.parametrize("after", [0.0, 1.2], ids=["in_acquire", "later"])
def test_hung_detector_thread_the_process_still_exits_with_its_outcome(sim, tmp_path, after):
    """The detector call never returns (in its worker thread), from the first frame (ACQUIRE: no offboard
    watchdog there) or later (usually engaged): the flight ends in SAFE_HOLD with PERCEPTION_STALL (12), and
    the process exits instead of waiting for the thread forever."""
    from companion.app.assemble import detector_available
    from companion.config import load_config

    if detector_available(load_config()) is not None:
        pytest.skip("the shipped gate detector is not available")
    t0 = time.monotonic()
    r = run_fly(sim.url_for_mavsdk, tmp_path / "flights", "app.synthetic.render=image", "app.synthetic.fault=block",
                f"app.synthetic.fault_after={after}", timeout=150)
    dt = time.monotonic() - t0
    assert r.returncode == 12, r.stderr[-3000:]
    assert "still running after the safe end: exiting anyway (exit 12)" in r.stderr
    (folder,) = (tmp_path / "flights").iterdir()
    s = json.loads((folder / "summary.json").read_text())
    assert s["outcome"] == "SAFE_HOLD" and s["reason"] == "PERCEPTION_STALL" and s["log_complete"] is True
    assert sim.mode == "HOLD" and sim.armed
    print(f"hung detector: process exited {dt:.1f} s after start")


# ------------------------------------------------------------------------------------------ small CLI probes


def test_relative_notify_socket_is_a_warning_not_a_traceback(capsys, monkeypatch):
    from companion.app.notify import Notifier

    monkeypatch.setenv("NOTIFY_SOCKET", "run/notify.sock")
    n = Notifier()
    assert not n.enabled and n.ready("x") is False
    line = one_line(capsys.readouterr().err)
    assert "NOTIFY_SOCKET='run/notify.sock' is neither an absolute path nor @name" in line


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "companion.cli", *args], capture_output=True, text=True,
                          timeout=60, cwd=cwd)


def test_log_plot_on_corrupt_files_is_one_line(tmp_path):
    folder = tmp_path / "f"
    folder.mkdir()
    (folder / "meta.json").write_text('{"format": "companion-flightlog-csv", "ver')  # cut short
    (folder / "states.csv").write_text("t,from_state,to_state,reason\n")
    r = _cli("log", "plot", str(folder), cwd=tmp_path)
    line = one_line(r.stderr)
    assert r.returncode == 1 and line.startswith(f"companion log plot: {folder}: cannot plot") and \
        "meta.json" in line, line
    (folder / "meta.json").write_text("{}")
    (folder / "telemetry.csv").write_bytes(b"t,roll_deg\n\x89PNG\xff\xfe,\x00\x01\n0.1,zz\n")
    r = _cli("log", "plot", str(folder), cwd=tmp_path)
    line = one_line(r.stderr)
    assert r.returncode == 1 and "cannot plot" in line, line
    assert (folder / "telemetry.csv").read_bytes().startswith(b"t,roll_deg")  # the log is never rewritten


def test_sim_px4_bad_port_is_one_line(tmp_path):
    r = subprocess.run([sys.executable, "-m", "companion.sim.px4", "--port", "99999"], capture_output=True,
                       text=True, timeout=60, cwd=tmp_path)
    assert r.returncode == 2 and one_line(r.stderr) == "companion.sim.px4: --port 99999: not a UDP port (0..65535)"
