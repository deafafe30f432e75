"""``companion bench``'s reference kernel and the ratios to it (companion/bench.py). Speeds are reported, never
asserted: these tests check what is computed and written, not how fast."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from companion.bench import _kernel, bench_kernel
from companion.cli import main


def test_kernel_computes_what_it_says():
    m = np.arange(9.0).reshape(3, 3)
    a, b = np.array([1.0, -2.0, 0.5]), np.array([0.0, 1.0, 3.0])
    v = [sum(m[i, j] * a[j] for j in range(3)) for i in range(3)]  # by hand: no numpy
    c = [v[1] * b[2] - v[2] * b[1], v[2] * b[0] - v[0] * b[2], v[0] * b[1] - v[1] * b[0]]
    out = _kernel(m, a, b)
    assert out.shape == (3,)
    assert out[0] == c[0] and out[1] == c[1]
    assert out[2] == math.atan2(c[1], c[0])  # the kernel's own call (numpy's SIMD arctan2 may differ in the last bit)
    assert out[2] == pytest.approx(float(np.arctan2(c[1], c[0])), rel=1e-15)


def test_bench_prints_and_stores_the_controller_ratio(tmp_path, capsys):
    r = bench_kernel(calls=10, repetitions=3)
    assert r["calls"] == 10 and r["repetitions"] == 3 and r["median_us"] > 0.0
    path = tmp_path / "bench.json"
    assert main(["bench", "--quick", "--only", "controller_step_us", "--json", str(path)]) == 0
    res = json.loads(path.read_text())
    k = res["reference_kernel_us"]["median"]
    assert res["ratio_to_kernel"]["controller_step"] == res["controller_step_us"]["median"] / k
    assert res["ratio_to_kernel"]["goals"] == {"controller_step": 1.6, "sim_frame": 7.0}
    assert "x the kernel" in capsys.readouterr().out


def test_bench_runs_the_simulator_on_every_core_at_once(tmp_path, capsys):
    """The "200x real time on 2 cores" figure: one simulator process per core, their speeds summed."""
    path = tmp_path / "bench.json"
    assert main(["bench", "--quick", "--only", "sim_speed_all_cores", "--json", str(path)]) == 0
    r = json.loads(path.read_text())["sim_speed_all_cores"]
    assert r["processes"] >= 1 and len(r["each_x_realtime"]) == r["processes"]
    assert r["sim_speed_x_realtime"] == sum(r["each_x_realtime"]) and min(r["each_x_realtime"]) > 0.0
    assert f"simulator on {r['processes']} cores at once" in capsys.readouterr().out
