"""Delay prediction (issue 9 latency): a late frame's LOS and LOS rate brought forward through its age.

Checked against independent computations: straight-line relative motion (angular momentum ``r x v``), and our
own velocity/displacement change integrated numerically from the command history; and in closed loop on the
latency suite's hardest delay.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from companion.config import load_config
from companion.controller import PNController
from companion.sim.runner import RunSpec, run_once, with_overrides
from perception.types import BoundingBox

VEHICLES = Path(__file__).resolve().parents[1] / "config" / "vehicles"
LEVEL = np.array([1.0, 0.0, 0.0, 0.0])
DT = 1.0 / 30.0


@functools.cache
def _controller(*overrides: str) -> PNController:
    return PNController.from_config(load_config([], list(overrides)))


def _ctrl(*overrides: str) -> PNController:
    """A fresh controller (the config is loaded once per set of overrides: property tests call this often)."""
    c = _controller(*overrides)
    c.reset()
    return c


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _feed(ctrl: PNController, age: float, n: int = 40) -> list:
    outs = []
    for i in range(n):
        t = i * DT
        b = BoundingBox(320 + 3 * i, 240 - i, 40.0 + 2 * i, 40.0 + 2 * i, 0.9, t)
        outs.append(ctrl.step(t, b, LEVEL, None, t + age))
    return outs


def test_defaults_predict_with_our_own_motion() -> None:
    p = _ctrl().p
    assert p.delay_prediction and p.delay_compensation
    assert p.own_delay == pytest.approx(load_config().airframe.response_time)
    sih = PNController.from_config(load_config([VEHICLES / "sih.yaml"])).p
    assert sih.own_drag_rate == pytest.approx(1.0) and sih.own_delay == pytest.approx(0.22)


def test_prediction_changes_nothing_for_a_fresh_frame() -> None:
    on = _ctrl("guidance.delay_prediction=true")
    off = _ctrl("guidance.delay_prediction=false", "guidance.delay_compensation=false")
    for a, b in zip(_feed(on, 0.0), _feed(off, 0.0), strict=True):
        assert a.setpoint.R_ned_frd == pytest.approx(b.setpoint.R_ned_frd, abs=0.0)
        assert a.setpoint.thrust == b.setpoint.thrust and a.lambda_dot == b.lambda_dot


def test_prediction_raises_the_rate_of_a_late_frame_of_a_closing_gate() -> None:
    # The box grows (the gate nears) and drifts: 200 ms later the gate is nearer and the LOS turns faster.
    on = _ctrl("guidance.delay_prediction=true", "guidance.delay_compensation=false")
    off = _ctrl("guidance.delay_prediction=false", "guidance.delay_compensation=false")
    late_on, late_off = _feed(on, 0.2), _feed(off, 0.2)
    assert late_on[-1].lambda_dot > 1.05 * late_off[-1].lambda_dot


def _prime(ctrl: PNController, d: float, d_dot: float, t: float, tau: float) -> None:
    assert ctrl._closing is not None
    ctrl._closing.x = np.array([d, d_dot])
    ctrl._closing.t = t
    ctrl._t_now = t + tau


@settings(max_examples=300, deadline=None)
@given(st.floats(3.0, 60.0), st.floats(-25.0, 5.0), st.floats(0.0, 0.4), st.floats(0.0, 0.35),
       st.floats(0.0, 2 * math.pi), st.floats(-0.6, 0.6))
def test_prediction_is_straight_line_relative_motion(d: float, d_dot: float, lam: float, tau: float,
                                                      az: float, el: float) -> None:
    """Without our own commands the prediction is the gate flying straight relative to us: LOS at
    ``r + v tau`` and LOS rate ``|r' x v| / |r'|^2`` (angular momentum, an independent formula)."""
    ctrl = _ctrl("guidance.delay_prediction=true", "guidance.delay_compensation=false")
    los = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    n = _unit(np.cross(los, [0.3, -0.5, 0.8]))
    t = 5.0
    _prime(ctrl, d, d_dot, t, tau)
    l2, lam2, n2 = ctrl._predict_state(t, los, lam, n)
    v = d_dot * los + d * lam * n
    r1 = d * los + v * tau
    if tau == 0.0:
        assert l2 is los and lam2 == lam
        return
    if float(r1 @ los) <= 0.0:
        assert (l2 is los) and lam2 == lam  # predicted past the gate: the frame is used as it is
        return
    assert l2 == pytest.approx(_unit(r1), abs=1e-9)
    d1 = max(float(np.linalg.norm(r1)), ctrl.p.gate_radius, 0.5)
    expect = float(np.linalg.norm(np.cross(r1, v))) / (float(np.linalg.norm(r1)) * d1)
    assert lam2 == pytest.approx(expect, rel=1e-9, abs=1e-12)
    if lam2 > 1e-6:  # the direction of a vanishing rate is rounding
        assert float(n2 @ l2) == pytest.approx(0.0, abs=1e-9) and np.linalg.norm(n2) == pytest.approx(1.0)
        # The LOS rate vector is where the relative velocity turns the LOS: v's part normal to l2, over range.
        w = v - float(v @ l2) * l2
        assert n2 == pytest.approx(_unit(w), abs=1e-6)


@settings(max_examples=80, deadline=None)
@given(st.floats(0.05, 1.0), st.floats(0.0, 0.3), st.floats(0.05, 0.35), st.floats(-8.0, 8.0), st.floats(0.0, 3.0))
@example(0.5, 0.22, 0.3, 4.0, 2.0)  # drag rate = 1 / lag: the closed form's limit case
@example(0.2, 0.14, 0.3, -3.0, 0.0)  # no drag
def test_own_motion_since_capture_against_an_integral(tau_lag: float, response: float, age: float,
                                                      a_y: float, drag: float) -> None:
    """With delay_compensation the prediction takes our own velocity and displacement change since the
    capture off the relative motion: commands act ``airframe.response_time`` after they are given, are
    reached with a first-order lag, and drag takes the added velocity back at ``airframe.drag_rate`` -- checked
    against a fine numerical integration of the same model."""
    ctrl = _ctrl("guidance.delay_prediction=true", "guidance.delay_compensation=true",
                 f"guidance.delay_compensation_lag={tau_lag} s", f"airframe.response_time={response} s",
                 f"airframe.drag_rate={drag}")
    cmds = [(0.0, np.array([0.0, a_y, 0.0])), (0.1, np.array([1.0, -a_y, 0.5])), (0.25, np.array([0.0, 0.0, 2.0])),
            (0.4, np.array([0.0, a_y, -1.0]))]
    for tc, a in cmds:
        ctrl._t_now = tc
        ctrl._note_command(a)
    t_cap = 0.45
    d, d_dot, lam = 20.0, -12.0, 0.1
    los = np.array([1.0, 0.0, 0.0])
    n = np.array([0.0, 1.0, 0.0])
    _prime(ctrl, d, d_dot, t_cap, age)
    l2, lam2, _ = ctrl._predict_state(t_cap, los, lam, n)
    # Independent: Euler integration of tau da_eff/dt = a_cmd(t - response) - a_eff and
    # d(dv)/dt = a_eff - drag dv over [t_cap, t_cap + age].
    h = 1e-4
    eff = np.zeros(3)
    dv = np.zeros(3)
    dp = np.zeros(3)
    s = 0.0
    while s < t_cap + age - 1e-12:
        past = [a for tc, a in cmds if tc <= s - response]
        cmd = past[-1] if past else np.zeros(3)
        if s >= t_cap:
            dp += dv * h
            dv += (eff - drag * dv) * h
        eff = eff + (cmd - eff) * (h / tau_lag)
        s += h
    v = d_dot * los + d * lam * n - dv
    r1 = d * los + (d_dot * los + d * lam * n) * age - dp
    assert l2 == pytest.approx(_unit(r1), abs=2e-4)
    d1 = max(float(np.linalg.norm(r1)), 1.0)
    expect = float(np.linalg.norm(np.cross(r1, v))) / (float(np.linalg.norm(r1)) * d1)
    assert lam2 == pytest.approx(expect, abs=2e-3 * (1.0 + expect))


def test_closed_loop_latency_linear_fast_300ms() -> None:
    """The latency suite's hardest delay on the gate that flees sideways (x500, engagement protocol): every
    run of these through the 1 m gate with the prediction; without it they miss by 1.5-5.7 m (today's
    failures, docs/guidance.md "Latency session")."""
    base = with_overrides(load_config(), {"sim": {"camera": {"delay": 0.3}}})
    off = with_overrides(base, {"guidance": {"delay_prediction": False, "delay_compensation": False}})
    seeds = (1005, 1006, 1008)
    with_pred = [run_once(base, RunSpec("linear_fast", s)).outcome for s in seeds]
    without = [run_once(off, RunSpec("linear_fast", s)).outcome for s in seeds]
    assert all(o.crossed and o.d_center is not None and o.d_center < 1.0 for o in with_pred)
    assert all(o.d_center is None or o.d_center > 1.0 for o in without)


# -- the LOS-rate low-pass scheduled on the time to go (los_filter.rate_cutoff_min) ---------------------------


@settings(max_examples=200, deadline=None)
@given(st.floats(0.5, 80.0), st.floats(-30.0, 3.0), st.floats(0.0, 0.4))
def test_rate_cutoff_follows_the_time_to_go(d: float, d_dot: float, age: float) -> None:
    ctrl = _ctrl()
    p = ctrl.p
    assert p.rate_cutoff_min == pytest.approx(0.5) and p.rate_cutoff_tgo == pytest.approx(2.0)
    assert ctrl._rate_cutoff() == p.rate_cutoff_hz  # no range yet: the fixed cut-off
    _prime(ctrl, d, d_dot, 1.0, 0.0)
    ctrl._latency = age
    fc = ctrl._rate_cutoff()
    t_go = d / -d_dot - age if d_dot < -0.5 else math.inf
    if not (t_go > 0.0) or math.isinf(t_go):
        assert fc == p.rate_cutoff_hz  # not closing, or due now: no schedule
    else:
        assert fc == pytest.approx(min(p.rate_cutoff_hz, max(0.5, 2.0 / t_go)))
    assert 0.5 <= fc <= p.rate_cutoff_hz
    off = _ctrl("los_filter.rate_cutoff_min=0 Hz")
    _prime(off, d, d_dot, 1.0, 0.0)
    assert off._rate_cutoff() == off.p.rate_cutoff_hz


def test_far_gate_jitter_is_filtered_near_gate_response_is_not() -> None:
    """Box noise on a gate far away (small box, seconds to go) reaches the LOS rate less with the schedule;
    close to the gate (a fraction of a second to go) the filter is the fixed one."""
    rng = np.random.default_rng(3)
    noise = rng.normal(0.0, 1.0, size=(90, 2))

    def rate_std(ctrl: PNController, size: float, d_dot: float) -> float:
        rates = []
        for i in range(90):
            t = i * DT
            b = BoundingBox(320 + noise[i, 0], 240 + noise[i, 1], size, size, 0.9, t)
            out = ctrl.step(t, b, LEVEL, None, t)
            if ctrl._closing is not None and ctrl._closing.x is not None:
                # hold the closing speed: the schedule's input, not under test here
                ctrl._closing.x = (ctrl._closing.state[0], d_dot)
            rates.append(out.lambda_dot)
        return float(np.std(rates[30:]))

    sched, fixed = _ctrl(), _ctrl("los_filter.rate_cutoff_min=0 Hz")
    assert rate_std(sched, 24.0, -6.0) < 0.7 * rate_std(fixed, 24.0, -6.0)  # a 24 px ring: tens of metres away
    sched, fixed = _ctrl(), _ctrl("los_filter.rate_cutoff_min=0 Hz")
    assert rate_std(sched, 200.0, -20.0) == pytest.approx(rate_std(fixed, 200.0, -20.0), rel=1e-12)


def test_sih_controller_protocol_roll_setpoint_calmer_with_the_schedule() -> None:
    """The SIH profile's roll-setpoint jitter (issue 9's oscillation goal), closed loop on the paper's protocol."""
    sih = load_config([VEHICLES / "sih.yaml"])
    off = with_overrides(sih, {"los_filter": {"rate_cutoff_min": 0.0}})
    for motion, seed in (("stationary", 0), ("linear_slow", 1000)):
        a = run_once(sih, RunSpec(motion, seed, protocol="controller"))
        b = run_once(off, RunSpec(motion, seed, protocol="controller"))
        assert a.outcome.success(1.0) and b.outcome.success(1.0)
        assert a.roll_osc.rms_rate_dps < 0.8 * b.roll_osc.rms_rate_dps
