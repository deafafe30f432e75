"""The flight's honest outcome: the truth judge (plane crossing against the radius) and the verdict, then
end to end: a flight whose camera "confirms" a pass that ground truth shows missed exits GATE_MISSED."""

from __future__ import annotations

import math

import numpy as np
import pytest
from flighthelpers import make_config, run_flight

from companion.app.outcome import GateJudge, verdict
from companion.app.states import Reason
from companion.engagement import GatePass
from companion.flightlog import gate_crossings, read_flight

NORMAL = np.array([-1.0, 0.0, 0.0])  # gate plane x = 20 (NED north), facing the vehicle coming from the south


def fly_past(judge: GateJudge, offset_e: float, gate_v_e: float = 0.0, dt: float = 0.05) -> None:
    """Vehicle north at 10 m/s along e = offset_e; gate at n = 20 moving east; samples on one clock."""
    for i in range(80):
        t = i * dt
        judge.gate(t, 1, np.array([20.0, gate_v_e * t, -5.0]), NORMAL, 1.0)
        tv = t + 0.01  # the vehicle sampled between gate samples: the gate is extrapolated to tv
        judge.vehicle(tv, np.array([10.0 * tv, offset_e, -5.0]))


def test_judge_scores_the_crossing_distance_against_the_radius():
    j = GateJudge()
    assert not j.has_truth
    fly_past(j, 0.4)
    (g,) = j.results()
    assert j.has_truth and g.crossed and g.through and g.d_center == pytest.approx(0.4, abs=1e-9)
    j = GateJudge()
    fly_past(j, 1.3)
    (g,) = j.results()
    assert g.crossed and not g.through and g.d_center == pytest.approx(1.3, abs=1e-9)


def test_judge_extrapolates_a_moving_gate_to_the_vehicle_sample_time():
    j = GateJudge()
    fly_past(j, 0.0, gate_v_e=2.0)  # crossing at t = 2 s: the gate is at e = 4 m then
    (g,) = j.results()
    assert g.d_center == pytest.approx(4.0, abs=1e-6) and g.t == pytest.approx(2.0, abs=1e-6)


def test_judge_never_counts_a_gate_twice_and_ignores_a_crossing_from_behind():
    j = GateJudge()
    fly_past(j, 0.2)
    for i in range(40):  # back through the plane from behind, and forth again
        j.vehicle(4.0 + i * 0.05, np.array([40.0 - 2.0 * i, 0.0, -5.0]))
    assert len(j.results()) == 1 and j.results()[0].d_center == pytest.approx(0.2, abs=1e-9)


def _p(status: str, gate: int = 1) -> GatePass:
    return GatePass(gate, 0.0, status, 1.0, 2.0, "the gate left the view" if status == "confirmed" else "timeout")


def test_verdict_with_truth():
    from companion.app.outcome import GateResult

    through, miss = GateResult(1, 1.0, True, 3.0, 0.4), GateResult(1, 1.0, True, 3.0, 1.36)
    none = GateResult(1, 1.0, False)
    assert verdict([_p("confirmed")], [through])[0] is Reason.OK
    r, line = verdict([_p("confirmed")], [miss])
    assert r is Reason.GATE_MISSED and line == "gate 1 missed: crossed its plane 1.36 m from the centre (radius 1.00 m)"
    r, line = verdict([_p("not_confirmed")], [none])  # claimed, never crossed
    assert r is Reason.GATE_MISSED and "1 pass(es) claimed but ground truth saw 0" in line
    assert verdict([_p("not_confirmed")], [through])[0] is Reason.OK  # truth settles the camera's doubt
    assert verdict([_p("pulled_up")], [none])[0] is Reason.OK  # an intercept claims no pass
    assert verdict([], [none, none])[0] is Reason.OK  # nothing claimed, nothing crossed: no target, no miss


def test_verdict_without_truth():
    assert verdict([_p("confirmed")], None)[0] is Reason.OK
    r, line = verdict([_p("confirmed"), _p("not_confirmed", 2)], None)
    assert r is Reason.PASS_NOT_CONFIRMED and line.startswith("gate 2: pass not confirmed")
    assert Reason.GATE_MISSED.value not in (0, 1, 2) and Reason.PASS_NOT_CONFIRMED != Reason.GATE_MISSED


@pytest.mark.timeout(150)
def test_a_missed_gate_is_not_exit_0(sim, tmp_path):
    """The straight pass starts 2.5 s before contact (app.ttc_threshold) while the gate moves on at 7 m/s:
    the vehicle crosses the gate plane well outside the 1 m ring. The camera sees the gate leave the view
    and "confirms" the pass; ground truth says it was missed, and the exit code says so."""
    # The 3-4 s straight pass sinks ~1 m/s on this vehicle: from 5 m it may reach the altitude floor first (a
    # true outcome, but not this test's); from 9 m it cannot. The camera "confirms" the pass ~1 s before the
    # vehicle reaches the gate plane (the gate left the view): a 3 s recover lets the plane be crossed before the
    # verdict at hand-back (with 1 s the two raced: crossed 20 ms before it in one CI run, and the verdict said,
    # truly then, "ground truth saw 0 gate(s) flown through").
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.close_trigger=ttc", "app.ttc_threshold=2.5",
                      "app.pass_timeout=4.0", "sim.gates.linear_fast_speed=7", "app.takeoff_altitude=9",
                      "app.recover_time=3")
    reason, folder, summary = run_flight(cfg)
    assert reason is Reason.GATE_MISSED, summary
    assert summary["exit_code"] == 30 and summary["reason"] == "GATE_MISSED"
    f = read_flight(folder)
    assert f.state_path()[-3:] == ["HANDBACK", "LAND", "SAFE_LANDED"]  # a normal end, but not a pass
    assert f.summary["exit_code"] == 30
    (g,) = summary["truth"]["gates"]
    assert g["crossed"] and not g["through"] and g["d_center_m"] > 1.0
    assert summary["verdict"] == f"gate 1 missed: crossed its plane {g['d_center_m']:.2f} m from the centre " \
                                 "(radius 1.00 m)"
    assert f.states[-1]["reason"].endswith(summary["verdict"])  # the miss named on the final line
    assert summary["gates_passed"] == 0 or summary["passes"][0]["status"] == "confirmed"
    # Independent: the flight log's own plane-crossing scorer (logged truth and gate) agrees.
    (c,) = gate_crossings(f)
    assert not c.through and math.isclose(c.d_center, g["d_center_m"], abs_tol=0.3)
