"""Log tools on hostile paths and files (issue 22): no output may overwrite a flight's raw log; write errors,
oversized fields, non-finite times, devices, FIFOs and oversized files each end in one line."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

from companion.flightlog import FlightLog

pytestmark = pytest.mark.timeout(120)


def _flight(tmp_path: Path) -> Path:
    log = FlightLog(tmp_path / "flight")
    for j in range(20):
        log.write("telemetry", t=0.05 * j, t_att=0.05 * j, qw=1.0, qx=0.0, qy=0.0, qz=0.0, armed=1)
    log.state("CONNECT", "ARM", "test")
    log.event("hello")
    log.close({"outcome": "SAFE_LANDED", "reason": "OK", "exit_code": 0})
    return tmp_path / "flight"


def _companion(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "companion.cli", *args], capture_output=True, text=True,
                          timeout=100)


def _digest(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.iterdir() if p.is_file()}


def _one_line(res: subprocess.CompletedProcess, code: int, fragment: str) -> None:
    assert res.returncode == code, (res.returncode, res.stdout, res.stderr)
    assert len(res.stderr.strip().splitlines()) == 1 and "Traceback" not in res.stderr, res.stderr
    assert fragment in res.stderr, res.stderr


@pytest.mark.parametrize("name", ["telemetry.csv", "summary.json", "meta.json", "states.csv", "events.csv"])
def test_export_never_overwrites_a_raw_file(tmp_path, name):
    f = _flight(tmp_path)
    before = _digest(f)
    _one_line(_companion("log", "export", str(f), "-o", str(f / name)), 2, f"would overwrite {name}")
    # Through ".." and through a symlink placed elsewhere: the real path is what counts.
    _one_line(_companion("log", "export", str(f), "-o", str(f / ".." / "flight" / name)), 2, "would overwrite")
    (tmp_path / "link.csv").symlink_to(f / name)
    _one_line(_companion("log", "export", str(f), "-o", str(tmp_path / "link.csv")), 2, "would overwrite")
    assert _digest(f) == before
    assert _companion("log", "summary", str(f)).returncode == 0


def test_export_refuses_a_hard_link_to_the_log_and_plot_refuses_raw_files(tmp_path):
    f = _flight(tmp_path)
    before = _digest(f)
    os.link(f / "telemetry.csv", tmp_path / "hard.csv")
    _one_line(_companion("log", "export", str(f), "-o", str(tmp_path / "hard.csv")), 2, "is the flight log's")
    _one_line(_companion("log", "plot", str(f), "-o", str(f / "states.csv")), 1, "would overwrite states.csv")
    assert _digest(f) == before
    # Its own products stay writable, and a new file elsewhere too.
    assert _companion("log", "export", str(f)).returncode == 0 and (f / "flight.csv").is_file()
    assert _companion("log", "export", str(f), "-o", str(tmp_path / "x.csv")).returncode == 0


def test_write_errors_are_one_line_and_not_success(tmp_path):
    f = _flight(tmp_path)
    _one_line(_companion("log", "export", str(f), "-o", "/dev/full"), 2, "No space left on device")
    _one_line(_companion("log", "plot", str(f), "-o", "/dev/full"), 1, "No space left on device")


def test_a_huge_field_is_refused_with_its_line(tmp_path):
    f = _flight(tmp_path)
    line = len((f / "events.csv").read_text().splitlines()) + 1
    with open(f / "events.csv", "a") as fh:
        fh.write(f'9.0,info,"{"x" * 200_000}"\n')
    _one_line(_companion("log", "summary", str(f)), 2, f"events.csv: line {line}: not a flight-log CSV")


def test_non_finite_times_are_counted(tmp_path):
    f = _flight(tmp_path)
    with open(f / "telemetry.csv", "a") as fh:
        fh.write("nan" + ",1" * 18 + "\n")
        fh.write("inf" + ",1" * 18 + "\n")
    res = _companion("log", "export", str(f), "-o", str(tmp_path / "x.csv"))
    assert res.returncode == 0, res.stderr
    assert "left out 2 row(s) whose t is not a finite number (telemetry: 2)" in res.stderr


def test_devices_fifos_and_oversized_files_are_refused_unread(tmp_path):
    f = _flight(tmp_path)
    (f / "telemetry.csv").unlink()
    (f / "telemetry.csv").symlink_to("/dev/zero")  # before: 5.4 GB, then MemoryError
    _one_line(_companion("log", "summary", str(f)), 2, "telemetry.csv: not a regular file")
    (f / "telemetry.csv").unlink()
    with open(f / "telemetry.csv", "wb") as fh:  # sparse: no disk used
        fh.truncate(300 * 1024 * 1024)
    _one_line(_companion("log", "export", str(f), "-o", str(tmp_path / "x.csv")), 2, "more than the 268 MB")
    (f / "telemetry.csv").unlink()
    (f / "summary.json").unlink()
    os.mkfifo(f / "summary.json")  # before: hung forever
    _one_line(_companion("log", "summary", str(f)), 2, "summary.json: not a regular file")
