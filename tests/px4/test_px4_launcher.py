"""PX4 SITL never outlives what started it: SIGKILL of the parent, Ctrl-C of ``companion sim --autopilot px4``."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from px4kit import REPO, SKIP_REASON, instance_range, sitl_dir

pytestmark = [pytest.mark.px4, pytest.mark.slow]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # A zombie (exited, not reaped by its dead parent yet) counts as gone.
    with open(f"/proc/{pid}/stat") as f:
        return f.read().split(")")[-1].split()[0] != "Z"


def _wait_gone(pid: int, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while _alive(pid):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.1)
    return True


@pytest.fixture
def sitl() -> Path:
    d = sitl_dir()
    if d is None:
        pytest.skip(SKIP_REASON)
    return d


def test_px4_dies_with_a_killed_parent(sitl: Path, tmp_path: Path) -> None:
    r = instance_range()
    code = ("import sys, time\n"
            "from companion.px4sitl.launcher import PX4Sitl\n"
            f"p = PX4Sitl(sys.argv[1], candidates=range({r.start}, {r.stop}), work_parent=sys.argv[2]).start()\n"
            "print(p.proc.pid, flush=True)\n"
            "time.sleep(600)\n")
    parent = subprocess.Popen([sys.executable, "-c", code, str(sitl), str(tmp_path)], cwd=REPO,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert parent.stdout is not None
        line = parent.stdout.readline()
        assert line.strip().isdigit(), f"the parent did not start PX4: {line!r}"
        px4 = int(line)
        assert _alive(px4)
        parent.kill()  # SIGKILL: no atexit, no finally; only the kernel's parent-death signal is left
        parent.wait(10)
        assert _wait_gone(px4, 15.0), "PX4 outlived its SIGKILLed parent"
    finally:
        if parent.poll() is None:
            parent.kill()


def _interactive_sigint() -> None:
    """preexec_fn: SIGINT as a terminal's foreground process has it (tests/app/test_signals.py says why)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_of_companion_sim_stops_px4(sitl: Path, tmp_path: Path) -> None:
    r = instance_range()
    proc = subprocess.Popen([sys.executable, "-m", "companion.cli", "sim", "--autopilot", "px4", "--px4-dir",
                             str(sitl), "--no-status", "--no-plot", "--set", f"log.directory={tmp_path / 'flights'}",
                             "--set", f"px4.work_dir={tmp_path}", "--set", f"px4.instance_min={r.start}",
                             "--set", f"px4.instance_max={r.stop - 1}"],
                            cwd=REPO, stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONFAULTHANDLER": "1"},
                            preexec_fn=_interactive_sigint)
    try:
        assert proc.stderr is not None
        pid = None
        deadline = time.monotonic() + 60
        while pid is None and time.monotonic() < deadline:
            line = proc.stderr.readline()
            if "(pid " in line:
                pid = int(line.split("(pid ")[1].split(")")[0])
        assert pid is not None, "companion sim did not report PX4's pid"
        time.sleep(2.0)  # PX4 is starting up / waiting for its pre-flight checks
        proc.send_signal(signal.SIGINT)  # what Ctrl-C sends to the foreground process
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:  # CI saw this twice: say where the app was (its stack, its last words)
            with contextlib.suppress(OSError):
                proc.send_signal(signal.SIGABRT)  # PYTHONFAULTHANDLER: every thread's stack to stderr
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)
            raise AssertionError(f"companion sim still ran 30 s after SIGINT; its stderr since PX4's pid: "
                                 f"{proc.stderr.read()[-6000:]!r}") from None
        assert proc.returncode == 130  # companion: interrupted
        assert _wait_gone(pid, 15.0), "PX4 still runs after Ctrl-C"
        assert not (tmp_path / "flights").exists()  # interrupted before the flight: no flight log
    finally:
        if proc.poll() is None:
            proc.kill()


def _px4_under(folder: Path) -> list[tuple[int, int]]:
    """(pid, parent pid) of the PX4 daemons whose working folder is under ``folder``."""
    found = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            argv = (d / "cmdline").read_bytes().split(b"\0")
            stat = (d / "stat").read_text()
        except OSError:
            continue
        if len(argv) > 3 and argv[0].endswith(b"/px4") and str(folder).encode() in b" ".join(argv):
            found.append((int(d.name), int(stat.split(")")[-1].split()[1])))
    return found


def test_a_killed_px4_eval_takes_its_workers_and_px4_with_it(sitl: Path, tmp_path: Path) -> None:
    # Found by hand: SIGTERM to `companion eval --autopilot px4` left its worker processes alive, and they went on
    # starting PX4 instances for minutes with nobody listening.
    r = instance_range()
    proc = subprocess.Popen([sys.executable, "-m", "companion.cli", "eval", "table1", "--autopilot", "px4",
                             "--px4-dir", str(sitl), "--runs", "1", "--jobs", "1", "--no-progress", "--no-plots",
                             "--out", str(tmp_path / "out"), "--set", f"px4.work_dir={tmp_path}",
                             "--set", f"px4.instance_min={r.start}", "--set", f"px4.instance_max={r.stop - 1}"],
                            cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 90
        px4: list[tuple[int, int]] = []
        while not px4:
            assert time.monotonic() < deadline and proc.poll() is None, "the eval never started PX4"
            time.sleep(0.2)
            px4 = _px4_under(tmp_path)
        (pid, worker), = px4
        assert worker != proc.pid  # PX4 belongs to a worker process, not to the eval itself
        proc.terminate()  # SIGTERM: what systemd, `kill` or a CI timeout send
        proc.wait(30)
        assert _wait_gone(worker, 20.0), "the eval's worker outlived it"
        assert _wait_gone(pid, 20.0), "PX4 outlived the eval"
        time.sleep(2.0)
        assert _px4_under(tmp_path) == [], "a PX4 was started after the eval was killed"
    finally:
        if proc.poll() is None:
            proc.kill()
