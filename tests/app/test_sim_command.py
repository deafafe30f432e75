"""``companion sim``: simulated PX4 process + synthetic camera + the app in real time; log and plot at the end."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from companion.flightlog import gate_crossings, latest_flight, read_flight

pytestmark = pytest.mark.timeout(120)


def test_companion_sim_flies_and_leaves_log_and_plot(tmp_path):
    cmd = [sys.executable, "-m", "companion.cli", "sim", "--camera", "geometric", "--motion", "linear_fast",
           "--set", "app.takeoff_altitude=5", "--set", f"log.directory={tmp_path / 'flights'}"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=100, cwd=Path(__file__).resolve().parents[2])
    assert r.returncode == 0, r.stderr[-2000:]
    assert "outcome: SAFE_LANDED (OK)" in r.stdout
    assert "gate 1: crossed" in r.stdout and "(through" in r.stdout
    assert "frame -> setpoint latency: p50" in r.stdout
    # The live status line went to stderr (as plain lines: stderr is not a terminal here).
    status = [line for line in r.stderr.splitlines() if line.startswith("t=")]
    assert any(" ENGAGE mode=OFFBOARD " in line and "ctrl=pn" in line for line in status), status[:20]
    assert any(" LAND mode=LAND " in line for line in status)
    folder = latest_flight(tmp_path / "flights")
    assert folder is not None and (folder / "plot.png").stat().st_size > 10_000
    f = read_flight(folder)
    assert f.state_path()[-1] == "SAFE_LANDED" and f.config["app"]["camera"] == "synthetic"
    assert len(gate_crossings(f)) == 1


def test_companion_sim_in_process_still_works(tmp_path):
    cmd = [sys.executable, "-m", "companion.cli", "sim", "--in-process", "--motion", "stationary", "--no-plot",
           "--json", str(tmp_path / "run.json")]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=100, cwd=Path(__file__).resolve().parents[2])
    assert r.returncode == 0, r.stderr[-2000:]
    assert "stationary seed 0" in r.stdout and (tmp_path / "run.json").exists()


def test_ctrl_c_hands_over_while_the_simulated_px4_keeps_running(tmp_path):
    """Ctrl-C hits the terminal's process group: the app hands over to HOLD; the sim (own session) survives it."""
    import os
    import queue
    import signal
    import threading
    import time

    # A far gate (50 m): a long engagement, so the signal lands in it even on a loaded machine.
    cmd = [sys.executable, "-m", "companion.cli", "sim", "--camera", "geometric", "--no-plot",
           "--set", "app.takeoff_altitude=5", "--set", "app.synthetic.distance=50",
           "--set", f"log.directory={tmp_path / 'flights'}"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            cwd=Path(__file__).resolve().parents[2])
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=lambda: [lines.put(x) for x in proc.stderr], daemon=True).start()
    try:
        while True:
            line = lines.get(timeout=40)
            if " ENGAGE mode=OFFBOARD " in line:
                break
        os.killpg(proc.pid, signal.SIGINT)  # what a Ctrl-C in the terminal does
        t_sig = time.monotonic()
        proc.wait(timeout=40)
        out = proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    f = read_flight(latest_flight(tmp_path / "flights"))
    at_signal = [r["to_state"] for r in f.states if float(r["t"]) <= t_sig - f.meta["t0_monotonic"]]
    assert proc.returncode == 23, (out, at_signal, f.states[-3:])
    assert "outcome: SAFE_HOLD (SIGNAL)" in out
    assert f.state_path()[-3:] == ["ENGAGE", "HANDBACK", "SAFE_HOLD"]
    assert "SIGINT" in f.states[-1]["reason"]
