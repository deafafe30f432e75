"""The app against real PX4 SITL (SIH): a flight through a stationary gate, confirmed by the simulator's truth."""

from __future__ import annotations

from pathlib import Path

import pytest
from px4kit import finish, flight_folder, start_app

from companion.flightlog import gate_crossings, read_flight
from companion.px4sitl.launcher import PX4Sitl

pytestmark = [pytest.mark.px4, pytest.mark.slow]


def test_flight_through_a_stationary_gate(px4: PX4Sitl, log_dir: Path) -> None:
    proc = start_app(px4, log_dir, "app.synthetic.motion=stationary", "app.takeoff_altitude=6")
    rc, out = finish(proc, timeout=180)
    folder = flight_folder(log_dir)
    f = read_flight(folder)
    assert rc == 0, out
    assert f.summary["outcome"] == "SAFE_LANDED", f.summary
    # The score came from SIH's ground truth, not PX4's EKF: on the ground before take-off the truth's
    # height is SIH's flat ground (EKF2's z is 1-3 m off there).
    assert f.config["px4"]["truth_url"] == px4.truth_url
    truth = f["truth"]
    assert abs(truth["d"][0]) < 0.1, truth["d"][0]
    # It did fly: PX4 takes off to 6 m on the EKF's height, which is 1-3 m off SIH's truth from the ground on
    # (../shared/px4-sitl/README.md; CI saw a truth peak of 4.7 m in a flight through the gate's centre).
    assert -truth["d"].min() > 6.0 - 3.0
    cross = gate_crossings(f)
    assert len(cross) == 1, cross
    assert cross[0].through, f"crossed {cross[0].d_center:.2f} m from the centre (radius {cross[0].radius} m)"
    assert f.summary["gates_passed"] == 1
