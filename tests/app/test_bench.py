"""bench_app (what ``companion bench`` reports as frame_to_setpoint_ms): structure and consistency, no timing goals."""

from __future__ import annotations

import pytest

from companion.app.bench import bench_app

pytestmark = pytest.mark.timeout(120)


def test_bench_app_reports_latency_percentiles_and_cpu():
    r = bench_app(quick=True, render="geometric")
    lat = r["frame_to_setpoint_ms"]
    assert r["outcome"] == "SAFE_LANDED" and r["reason"] == "OK" and r["camera"] == "geometric"
    assert lat["n"] > 50  # ~6 s engaged at 30 Hz
    assert 0.0 < lat["p50"] <= lat["p95"]
    assert 0.0 < r["cpu_percent"] < 200.0  # of one core; 2 cores at most
