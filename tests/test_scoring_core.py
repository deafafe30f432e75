"""companion/scoring.py, the one crossing geometry: the streaming and array forms give the same numbers, and
the simulator's scorer, the app's judge and the flight log's re-score all report them."""

from __future__ import annotations

import ast
import math
from pathlib import Path

import numpy as np
import pytest

from companion.scoring import GatePlane, plane_crossings, segment_crossing, signed_distance, unit

N = np.array([-1.0, 0.2, 0.1])  # not unit on purpose: both forms normalise it


def samples(seed: int = 0, n: int = 400):
    """A vehicle weaving back and forth through a moving gate's plane, on uneven sample times."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.01, 0.06, n))
    p = np.column_stack([20.0 + 6.0 * np.sin(1.3 * t), 0.5 * np.cos(0.7 * t), -5.0 + 0.3 * np.sin(2.1 * t)])
    p += rng.normal(0.0, 0.01, p.shape)
    g = np.column_stack([np.full(n, 20.0), 1.5 * t - 3.0, np.full(n, -5.2)])
    return t, p, g


def stream(t, p, g):
    plane = GatePlane(N)
    return [c for c in (plane.update(float(ti), pi, gi) for ti, pi, gi in zip(t, p, g, strict=True)) if c is not None]


def test_streaming_and_array_forms_give_identical_numbers():
    for seed in range(5):
        t, p, g = samples(seed)
        a, s = plane_crossings(N, t, p, g), stream(t, p, g)
        assert len(a) >= 3  # several crossings, front to back only
        assert [(c.t, c.d_center, c.angle_deg) for c in a] == [(c.t, c.d_center, c.angle_deg) for c in s]
        assert all(np.array_equal(x.point, y.point) for x, y in zip(a, s, strict=True))


def test_segment_geometry():
    n = unit([-1.0, 0.0, 0.0])
    g = np.array([20.0, 0.0, 0.0])
    p0, p1 = np.array([19.0, 0.3, 0.4]), np.array([21.0, 0.3, 0.4])
    c = segment_crossing(n, 1.0, p0, g, signed_distance(n, p0, g), 2.0, p1, g, signed_distance(n, p1, g))
    assert c is not None and c.t == pytest.approx(1.5) and c.d_center == pytest.approx(0.5)
    assert c.angle_deg == pytest.approx(0.0, abs=1e-6) and np.allclose(c.point, [20.0, 0.3, 0.4])
    q1 = np.array([21.0, 2.3, 0.4])  # 45 degrees off the normal
    c = segment_crossing(n, 1.0, p0, g, signed_distance(n, p0, g), 2.0, q1, g, signed_distance(n, q1, g))
    assert c.angle_deg == pytest.approx(45.0) and c.d_center == pytest.approx(math.hypot(1.3, 0.4))
    # Back to front, or touching the plane from behind: no crossing.
    assert segment_crossing(n, 1.0, p1, g, signed_distance(n, p1, g), 2.0, p0, g, signed_distance(n, p0, g)) is None
    assert segment_crossing(n, 1.0, p0, g, 0.0, 2.0, p1, g, -1.0) is None


def test_the_three_callers_report_the_core_numbers(tmp_path):
    from companion.app.outcome import GateJudge
    from companion.flightlog import FlightLog, gate_crossings, read_flight
    from companion.sim.scoring import PlaneCrossingScorer

    t, p, g = samples(1)
    first = plane_crossings(N, t, p, g)[0]
    sim = PlaneCrossingScorer(N)
    out = next(o for o in (sim.update(float(ti), pi, gi) for ti, pi, gi in zip(t, p, g, strict=True)) if o)
    assert (out.t_gate, out.d_center) == (first.t, first.d_center)

    # The judge extrapolates the gate from its last two samples: a gate logged at each vehicle sample's time is
    # then exactly the logged centre.
    judge = GateJudge()
    for ti, pi, gi in zip(t, p, g, strict=True):
        judge.gate(float(ti), 1, gi, N, 1.0)
        judge.vehicle(float(ti), pi)
    (r,) = judge.results()
    assert (r.t, r.d_center) == (first.t, first.d_center)

    # The flight log: the same samples as rows (9 significant digits), re-scored over arrays.
    log = FlightLog(tmp_path / "f", clock=lambda: 0.0)
    for ti, pi, gi in zip(t, p, g, strict=True):
        n = N / np.linalg.norm(N)
        log.write("gate", t=ti, k=1, gate_n=gi[0], gate_e=gi[1], gate_d=gi[2], normal_n=n[0], normal_e=n[1],
                  normal_d=n[2], radius=1.0, visible=True)
        log.write("truth", t=ti, n=pi[0], e=pi[1], d=pi[2], vn=0.0, ve=0.0, vd=0.0)
    log.close({"outcome": "SAFE_LANDED"})
    f = read_flight(tmp_path / "f")
    logged = [(c.t, c.d_center) for c in gate_crossings(f)]
    tt = f["truth"]["t"]
    pp = np.column_stack([f["truth"][k] for k in ("n", "e", "d")])
    gg = np.column_stack([f["gate"][k] for k in ("gate_n", "gate_e", "gate_d")])
    nn = [f["gate"][k][0] for k in ("normal_n", "normal_e", "normal_d")]
    assert logged == [(c.t, c.d_center) for c in plane_crossings(nn, tt, pp, gg)]
    assert logged[0] == pytest.approx((first.t, first.d_center), abs=1e-6)


def test_the_core_is_pure():
    """companion/scoring.py imports nothing from the app or the simulator (both import it)."""
    tree = ast.parse(Path(__file__).parents[1].joinpath("companion", "scoring.py").read_text())
    mods = [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    mods += [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    assert not [m for m in mods if m.startswith("companion")], mods
