"""``companion log summary`` / ``log export`` on the log of a real simulated flight (real mavsdk over UDP),
every number recomputed here from the CSV files with the csv module alone (the gate crossing also checked
against summary.json's truth, which the summary reports)."""

from __future__ import annotations

import csv
import itertools
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from flighthelpers import make_config, run_flight

from companion.app.states import Reason
from companion.flightlog import gate_crossings, read_flight

pytestmark = pytest.mark.timeout(150)


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, encoding="utf-8", newline="") as f:
        return list(csv.DictReader(f))


def _companion(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "companion.cli", *args], capture_output=True, text=True,
                          timeout=120)


def test_log_summary_and_export_match_the_flight_log(sim, tmp_path):
    cfg = make_config(tmp_path, sim.url_for_mavsdk)
    reason, folder, summary = run_flight(cfg)
    assert reason is Reason.OK, summary

    res = _companion("log", "summary", str(folder), "--json")
    assert res.returncode == 0, res.stderr
    s = json.loads(res.stdout)

    # Outcome: as the app wrote it.
    written = json.loads((folder / "summary.json").read_text())
    assert (s["outcome"], s["reason"], s["exit_code"]) == ("SAFE_LANDED", "OK", 0)
    assert s["outcome"] == written["outcome"]

    # States with their times and durations.
    states = _rows(folder / "states.csv")
    assert [x["state"] for x in s["states"]] == [r["to_state"] for r in states]
    for i, (x, r) in enumerate(zip(s["states"], states, strict=True)):
        assert x["t_enter"] == pytest.approx(float(r["t"]), abs=1e-6)
        if i + 1 < len(states):
            assert x["duration"] == pytest.approx(float(states[i + 1]["t"]) - float(r["t"]), abs=1e-6)
        else:
            assert x["duration"] is None

    # Gate: recomputed from truth and gate rows (linear interpolation of the plane's signed distance).
    truth, gate = _rows(folder / "truth.csv"), _rows(folder / "gate.csv")
    assert len(s["gates"]) == 1
    tg = np.array([float(r["t"]) for r in gate])
    g = {k: np.array([float(r[k]) for r in gate]) for k in ("gate_n", "gate_e", "gate_d", "normal_n", "normal_e",
                                                              "normal_d")}
    prev = None
    found = None
    for r in truth:
        t = float(r["t_truth"])  # the sample's own time (the row's t is when the telemetry loop wrote it)
        if t < tg[0] or t > tg[-1]:
            continue
        c = np.array([np.interp(t, tg, g[k]) for k in ("gate_n", "gate_e", "gate_d")])
        n = np.array([np.interp(t, tg, g[k]) for k in ("normal_n", "normal_e", "normal_d")])
        d = np.array([float(r[k]) for k in ("n", "e", "d")]) - c
        sd = float(d @ n)
        if prev is not None and prev[1] > 0 >= sd:
            a = prev[1] / (prev[1] - sd)
            rel = prev[2] + a * (d - prev[2])
            found = (prev[0] + a * (t - prev[0]), float(np.linalg.norm(rel - (rel @ n) * n)))
            break
        prev = (t, sd, d)
    assert found is not None
    # The log's re-score of its own topics is that computation; the summary shows the app's live judgement
    # (summary.json "truth", the same record the flight's printed lines use): both take each truth sample at its
    # arrival time (t_truth), so they differ only where the judge extrapolates the gate and the log interpolates
    # it, however late the telemetry loop wrote the rows.
    (c,) = gate_crossings(read_flight(folder))
    assert c.t == pytest.approx(found[0], abs=1e-3) and c.d_center == pytest.approx(found[1], abs=0.02)
    (judged,) = written["truth"]["gates"]
    meta = json.loads((folder / "meta.json").read_text())
    assert s["gates"][0]["d_center"] == judged["d_center_m"] and s["gates"][0]["through"] is judged["through"]
    assert s["gates"][0]["t"] == pytest.approx(judged["t_monotonic_s"] - meta["t0_monotonic"], abs=1e-9)
    assert s["gates"][0]["t"] == pytest.approx(found[0], abs=0.1)
    assert s["gates"][0]["d_center"] == pytest.approx(found[1], abs=0.02)
    assert s["gates"][0]["through"] is (found[1] < float(gate[0]["radius"]))

    # Frames and dropped frames from the detections topic.
    det = _rows(folder / "detections.csv")
    assert s["frames"] == len(det)
    idx = [int(float(r["frame"])) for r in det]
    tf = [float(r["t_frame"]) for r in det]
    period = 1.0 / cfg.camera.rate
    by_index = sum(max(0, b - a - 1) for a, b in itertools.pairwise(idx))
    by_time = sum(round((b - a) / period) - 1 for a, b in itertools.pairwise(tf) if b - a > 1.5 * period)
    assert s["dropped_frames"] == max(by_index, by_time)
    assert s["frame_rate_hz"] == pytest.approx((len(tf) - 1) / (tf[-1] - tf[0]), rel=1e-6)

    # Latency percentiles: every setpoint except the first (that one includes PX4's switch to OFFBOARD).
    sp = _rows(folder / "setpoints.csv")
    lat = sorted(float(r["latency_ms"]) for r in sp[1:])
    assert s["setpoints"] == len(sp)
    for p in (50, 95, 99):
        k = (len(lat) - 1) * p / 100.0  # numpy's default "linear" percentile, by hand
        lo, hi = math.floor(k), math.ceil(k)
        expect = lat[lo] + (lat[hi] - lat[lo]) * (k - lo)
        assert s["latency_ms"][f"p{p}"] == pytest.approx(expect, rel=1e-9)
    assert s["latency_ms"]["max"] == pytest.approx(lat[-1])
    assert s["latency_ms"]["p50"] == pytest.approx(written["frame_to_setpoint_ms"]["p50"], abs=0.01)

    text = _companion("log", "summary", str(folder))
    assert text.returncode == 0 and "SAFE_LANDED" in text.stdout and "gate 1:" in text.stdout

    # Export: one CSV, time column first, every logged value present at its own time.
    out = tmp_path / "export.csv"
    res = _companion("log", "export", str(folder), "-o", str(out))
    assert res.returncode == 0, res.stderr
    merged = _rows(out)
    header = list(merged[0].keys())
    assert header[0] == "t" and "telemetry/roll_deg" in header and "setpoints/thrust" in header
    times = [float(r["t"]) for r in merged]
    assert times == sorted(times)
    sp_rows = [r for r in merged if r["setpoints/thrust"] != ""]
    assert len(sp_rows) == len(sp)
    for a, b in zip(sp_rows, sp, strict=True):
        assert float(a["t"]) == pytest.approx(float(b["t"]), abs=1e-6)
        assert float(a["setpoints/thrust"]) == pytest.approx(float(b["thrust"]), rel=1e-6)
        assert a["setpoints/state"] == b["state"]
    held_out = tmp_path / "held.csv"
    res = _companion("log", "export", str(folder), "-o", str(held_out), "--fill", "hold")
    assert res.returncode == 0, res.stderr
    held = _rows(held_out)
    assert [r["t"] for r in held] == [r["t"] for r in merged]
    first_sp = next(i for i, r in enumerate(merged) if r["setpoints/thrust"] != "")
    assert all(r["setpoints/thrust"] != "" for r in held[first_sp:])  # held from the first sample on
    last = None
    for a, b in zip(merged, held, strict=True):  # a held cell is the last logged value, never a new one
        last = a["setpoints/thrust"] or last
        assert b["setpoints/thrust"] == (last or "")
    st_rows = [r for r in merged if r["states/to_state"] != ""]
    assert [r["states/to_state"] for r in st_rows] == [r["to_state"] for r in states]
    assert all(r["states/state_index"].lstrip("-").isdigit() for r in st_rows)


def test_log_summary_of_a_missing_folder_is_one_line(tmp_path):
    res = _companion("log", "summary", str(tmp_path / "nope"))
    assert res.returncode == 2
    assert len(res.stderr.strip().splitlines()) == 1 and "no flight log" in res.stderr


def test_check_accepts_the_default_and_refuses_a_bad_file(tmp_path):
    ok = _companion("check", "--no-detector")
    assert ok.returncode == 0 and "config OK" in ok.stdout and "guidance: k_pn" in ok.stdout
    bad = tmp_path / "bad.yaml"
    bad.write_text("guidance:\n  gamma_bar: 21 m/s\n")
    res = _companion("check", str(bad))
    assert res.returncode == 2
    line = res.stderr.strip()
    assert len(line.splitlines()) == 1 and str(bad) in line and "guidance.gamma_bar" in line
    missing_model = _companion("check", "--set", f"perception.model={tmp_path / 'none.onnx'}")
    assert missing_model.returncode == 2 and "perception.model" in missing_model.stderr
