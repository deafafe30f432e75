"""Flight log: written as it happens, readable after a kill, readable by the csv module alone."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from companion.flightlog import TOPICS, FlightLog, latest_flight, read_flight, read_table

pytestmark = pytest.mark.timeout(60)


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_round_trip_and_plain_csv(tmp_path):
    clock = FakeClock()
    log = FlightLog(tmp_path / "f1", config={"guidance": {"k_pn": 2.1}}, flush_interval=0.5, clock=clock)
    rng = np.random.default_rng(1)
    vals = rng.normal(size=(20, 4))
    for i, (a, b, c, d) in enumerate(vals):
        clock.t = 100.0 + i / 30
        log.write("setpoints", t_frame=clock.t - 100.0, state="ENGAGE", ctrl_mode="pn", roll_deg=a,
                  pitch_deg=b, yaw_deg=c, thrust=d, latency_ms=1.5)
    log.state("INIT", "CONNECT", "start, with a comma")
    log.close({"outcome": "SAFE_LANDED", "reason": "OK"})

    f = read_flight(tmp_path / "f1")
    sp = f["setpoints"]
    assert len(sp) == 20
    np.testing.assert_allclose(sp["roll_deg"], vals[:, 0], rtol=1e-8)
    np.testing.assert_allclose(sp["thrust"], vals[:, 3], rtol=1e-8)
    np.testing.assert_allclose(sp["t"], np.arange(20) / 30, atol=1e-9)
    assert list(sp["state"]) == ["ENGAGE"] * 20
    assert f.states[0]["reason"] == "start, with a comma"
    assert f.config == {"guidance": {"k_pn": 2.1}}
    assert f.summary["outcome"] == "SAFE_LANDED" and f.summary["rows"]["setpoints"] == 20
    # Independent reader: the standard csv module sees the same header and row count.
    with open(tmp_path / "f1" / "setpoints.csv", newline="") as fh:
        rows = list(csv.reader(fh))
    assert tuple(rows[0]) == TOPICS["setpoints"] and len(rows) == 21


def test_unknown_topic_and_column_are_refused(tmp_path):
    log = FlightLog(tmp_path / "f", flush_interval=0.5)
    with pytest.raises(KeyError, match="unknown topic 'nope'"):
        log.write("nope", x=1)
    with pytest.raises(KeyError, match="no column"):
        log.write("los", bogus=1)
    log.close()


def test_flush_interval_bounds_what_the_os_has(tmp_path):
    clock = FakeClock()
    log = FlightLog(tmp_path / "f", flush_interval=0.5, clock=clock)
    log.write("truth", n=1.0, e=2.0, d=3.0, vn=0, ve=0, vd=0)
    # Not yet flushed (buffered): the file on disk holds only the header.
    assert len(read_table(tmp_path / "f" / "truth.csv")) == 0
    clock.t += 0.6
    log.write("truth", n=1.0, e=2.0, d=3.0, vn=0, ve=0, vd=0)
    assert len(read_table(tmp_path / "f" / "truth.csv")) == 2
    # States go to the OS at once.
    log.state("A", "B", "why")
    assert len(read_table(tmp_path / "f" / "states.csv")) == 1
    log.close()


def test_truncated_last_line_is_dropped(tmp_path):
    p = tmp_path / "los.csv"
    p.write_text("t,a\n0.1,1\n0.2,2\n0.3,")
    tab = read_table(p)
    assert len(tab) == 2 and tab.truncated_rows == 1
    np.testing.assert_allclose(tab["a"], [1, 2])


def test_sigkill_leaves_a_readable_log(tmp_path):
    """A real writer process killed with SIGKILL: everything older than flush_interval is on disk."""
    script = textwrap.dedent(f"""
        import sys, time
        from companion.flightlog import FlightLog
        log = FlightLog({str(tmp_path / 'k')!r}, config={{}}, flush_interval=0.2)
        log.state("INIT", "ENGAGE", "go")
        i = 0
        t0 = time.monotonic()
        while True:
            log.write("los", t_frame=i, los_n=1.0, los_e=0.0, los_d=0.0, lambda_dot=0.1, a_n=0.0,
                      demand_scale=1.0, rejected="")
            i += 1
            if i == 60:
                print("ready", flush=True)
            time.sleep(0.005)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    f = read_flight(tmp_path / "k")
    assert f.summary == {"outcome": "running"}  # never closed
    assert f.state_path() == ["ENGAGE"]
    los = f["los"]
    # 60 rows were written before "ready" (>= 0.3 s at 5 ms each, > flush_interval): most must be there.
    assert len(los) >= 30
    np.testing.assert_array_equal(los["t_frame"], np.arange(len(los)))
    assert json.loads((tmp_path / "k" / "meta.json").read_text())["format"] == "companion-flightlog-csv"


def test_create_never_reuses_a_folder(tmp_path):
    a = FlightLog.create(tmp_path)
    b = FlightLog.create(tmp_path)
    assert a.folder != b.folder
    a.close()
    b.close()
    assert latest_flight(tmp_path) in (a.folder, b.folder)
