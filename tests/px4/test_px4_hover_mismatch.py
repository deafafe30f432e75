"""Real PX4 SITL: a 1.5 kg SIH vehicle (thrust-to-weight 2.5, true hover 0.40) flown with the default config (hover
0.50, MPC_THR_HOVER 0.50): after take-off the app reads the thrust PX4 commands in its hover (ATTITUDE_TARGET),
prints the WARNING line and flies PX4's value (issue 20, companion/vehiclematch.py)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from px4kit import finish, flight_folder, start_app

from companion.px4sitl.launcher import PX4Sitl

pytestmark = [pytest.mark.px4, pytest.mark.slow]

MASS, T_MAX = 1.5, 9.19688  # kg, N per motor


def test_a_lighter_vehicle_is_named_after_take_off(px4: PX4Sitl, log_dir: Path) -> None:
    true_hover = MASS * 9.81 / (4 * T_MAX)  # SIH's thrust is linear in the command: 0.400
    mass0, tmax0 = px4.param_get("SIH_MASS"), px4.param_get("SIH_T_MAX")
    px4.param_set("SIH_MASS", MASS)  # SIH reads its physics parameters live (../shared/px4-sitl/README.md)
    px4.param_set("SIH_T_MAX", T_MAX)
    try:
        # The gate far away, the flight short: only the take-off and PX4's hover matter here.
        proc = start_app(px4, log_dir, "app.synthetic.motion=stationary", "app.takeoff_altitude=5",
                         "app.max_gates=1", "app.acquire_frames=60")  # 2 s of PX4's hover before the engagement
        rc, out = finish(proc, timeout=150)
    finally:
        px4.param_set("SIH_MASS", mass0)  # the next test on this PX4 flies the default vehicle
        px4.param_set("SIH_T_MAX", tmax0)
    summary = json.loads((flight_folder(log_dir) / "summary.json").read_text())
    r = summary["hover"]["after_takeoff"]
    assert r["px4_commanded"] is not None, (r, out)
    assert r["px4_commanded"] == pytest.approx(true_hover, abs=0.03), r
    assert r["configured"] == 0.5 and r["mpc_thr_hover"] == pytest.approx(0.5) and r["warning"], r
    assert r["flies_source"] == "PX4 measured" and r["flies"] == pytest.approx(r["px4_commanded"])
    assert f"companion: {r['line']}" in out and r["line"].startswith("WARNING hover thrust after take-off")
    assert summary["outcome"].startswith("SAFE_"), (rc, out)  # a safe end; this test is about the line, not the gate
