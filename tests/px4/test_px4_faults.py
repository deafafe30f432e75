"""Faults against real PX4 SITL (SIH): the autopilot's own rules decide, the app must tell the truth about them."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest
from px4kit import Px4Bench, finish, flight_folder, start_app, states, wait_state

from companion.app.states import Reason
from companion.flightlog import read_flight, read_table
from companion.px4sitl.launcher import PX4Sitl
from companion.px4sitl.truth import SihTruth

pytestmark = [pytest.mark.px4, pytest.mark.slow]


def _height(px4: PX4Sitl) -> float:
    truth = SihTruth(px4.truth_url, px4.origin)
    try:
        return -float(truth.wait(5.0).position_ned[2])
    finally:
        truth.close()


def test_sigkill_mid_engagement_px4_failsafe_and_log_intact(px4: PX4Sitl, log_dir: Path) -> None:
    proc = start_app(px4, log_dir, "app.synthetic.motion=stationary", "app.synthetic.distance=45",
                     "app.takeoff_altitude=6")
    folder = flight_folder(log_dir)
    wait_state(folder, "ENGAGE", proc, timeout=120)
    deadline = time.monotonic() + 10.0
    while px4.status().nav_mode != "Offboard":  # PX4 switches 0.2-1 s after the app asked
        assert time.monotonic() < deadline and proc.poll() is None, f"PX4 never in Offboard: {px4.status()}"
        time.sleep(0.1)
    # Mid-engagement: the app has been commanding for a while (its setpoints reached the log's file).
    while len(read_table(folder / "setpoints.csv")) < 5:
        assert time.monotonic() < deadline + 10.0 and proc.poll() is None, "no setpoints logged"
        time.sleep(0.1)
    time.sleep(1.0)
    os.kill(proc.pid, signal.SIGKILL)
    t_kill = time.monotonic()
    proc.communicate(timeout=10)
    # PX4's offboard-loss failsafe (COM_OF_LOSS_T 1 s) takes the vehicle out of Offboard by itself.
    modes = []
    while time.monotonic() - t_kill < 10.0:
        st = px4.status()
        modes.append(st.nav_mode)
        if st.nav_mode != "Offboard":
            break
        time.sleep(0.2)
    assert modes[-1] != "Offboard", f"PX4 still in Offboard 10 s after the app died: {modes}"
    assert px4.status().armed  # the failsafe flies it (descends / lands); it did not just drop
    # Our flight log is intact up to the kill: readable, every data topic flushed to within 0.5 s + a frame.
    f = read_flight(folder)
    assert f.summary == {"outcome": "running"}  # killed: no summary was written over the placeholder
    assert states(folder)[-1] == "ENGAGE"
    t_kill_flight = t_kill - f.meta["t0_monotonic"]
    for topic in ("setpoints", "telemetry", "truth", "gate"):
        tab = f[topic]
        assert tab.truncated_rows <= 1, topic
        assert len(tab) > 0, topic
        assert tab["t"][-1] > t_kill_flight - 1.0, (topic, tab["t"][-1], t_kill_flight)
    assert set(f["setpoints"]["state"]) >= {"ENGAGE"}


def test_sigint_during_takeoff_commands_a_confirmed_hold(px4: PX4Sitl, log_dir: Path) -> None:
    proc = start_app(px4, log_dir, "app.takeoff_altitude=12")
    folder = flight_folder(log_dir)
    wait_state(folder, "TAKEOFF", proc, timeout=90)
    time.sleep(1.5)
    proc.send_signal(signal.SIGINT)
    rc, out = finish(proc, timeout=60)
    assert rc == int(Reason.SIGNAL), out
    assert states(folder)[-1] == "SAFE_HOLD", states(folder)
    st = px4.status()
    assert st.armed and st.nav_mode == "Hold", st  # commanded and confirmed before the app named it
    # Held, not climbing on to the 12 m take-off. When the Hold lands during PX4's lift-off ramp (a loaded
    # machine: the vehicle still on the ground) PX4 may finish leaving the ground and then stop: CI 2026-12-02 saw
    # 0.0 -> 1.04 m in 3 s once, and 0.0 m for 4.5 s then +0.4 m another time. So the check waits for the height
    # to settle (as PX4 decides when, not on a timer) and bounds where it settles, far below the 12 m take-off.
    # PX4 holds its *estimated* height, and SIH's EKF height is off from the truth by 1-3 m after a few flights on
    # one instance (see _take_off_by_px4): CI 2026-12-06 saw PX4 report IN_AIR and confirm Hold with the truth still
    # on the ground (0.001 m), then a slow rise to settle 2.6 m up over 18 s. The bound is that error plus 1 m of
    # lift-off; a take-off that went on (MPC_TKO_SPEED 1.5 m/s to 12 m) would be far past it and never settle.
    heights, settled = _settled_heights(px4, settle_s=3.0, at_least_s=10.0, timeout_s=30.0)
    h0, h_end = heights[0], heights[-1]
    trace = " -> ".join(f"{h:.1f}" for h in heights[::4])
    assert settled, f"still climbing 30 s after the app said Hold: {trace} m"
    assert h_end - h0 < 4.0 and max(heights) < 6.0, f"climbed on after the app said Hold: {trace} m"


def _settled_heights(px4: PX4Sitl, settle_s: float, at_least_s: float, timeout_s: float,
                     dt: float = 0.5) -> tuple[list[float], bool]:
    """Heights every dt, for at least at_least_s (a late lift-off shows), until the last settle_s of them span
    < 0.2 m (True) or timeout_s passes (False)."""
    truth = SihTruth(px4.truth_url, px4.origin)
    n = round(settle_s / dt) + 1
    heights: list[float] = []
    try:
        t0 = time.monotonic()
        while time.monotonic() < t0 + timeout_s:
            heights.append(-float(truth.wait(5.0).position_ned[2]))
            last = heights[-n:]
            if time.monotonic() > t0 + at_least_s and len(last) == n and max(last) - min(last) < 0.2:
                return heights, True
            time.sleep(dt)
    finally:
        truth.close()
    return heights, False


def _take_off_by_px4(px4: PX4Sitl, lift_off_s: float = 25.0) -> bool:
    """PX4's own take-off to 4 m and Hold there; False if the vehicle never left the ground.

    PX4's Takeoff ends by itself on its *estimated* altitude (the EKF's height is off by 1-3 m): past 3 m of true
    height Hold is commanded here rather than waiting for it. Seen twice in CI after several flights on one SIH
    instance: PX4 "Takeoff detected", thrust setpoint at 100 % for 90 s, motors at 3-54 % (the mixer spending
    them on a roll the vehicle resting ~3 deg tilted on SIH's ground never makes), true height 0.0 m.
    """
    px4.param_set("MIS_TAKEOFF_ALT", 4.0)
    px4.client("commander", "arm")
    px4.client("commander", "takeoff")
    t0 = time.monotonic()
    while True:
        st, h = px4.status(), _height(px4)
        if st.nav_mode == "Hold" and h > 3.0:
            _settle(px4)
            return True
        if st.nav_mode == "Takeoff" and h > 3.0:
            px4.client("commander", "mode", "auto:loiter", check=False)
        if h < 0.5 and time.monotonic() - t0 > lift_off_s:
            return False
        assert time.monotonic() - t0 < 90.0, (f"PX4 not airborne in Hold 90 s after take-off: {st}, true height "
                                              f"{h:.1f} m; console tail: {px4.console_tail()}")
        time.sleep(0.5)


def _settle(px4: PX4Sitl, timeout_s: float = 15.0) -> None:
    """Wait until Hold has stopped the climb (true height steady within 0.1 m over 1 s): Hold commanded past 3 m
    of a climb to 4 m overshoots for a few seconds (CI saw 1.05 m between "in Hold" and the app's refusal)."""
    t0, h = time.monotonic(), _height(px4)
    while time.monotonic() - t0 < timeout_s:
        time.sleep(1.0)
        h, h_prev = _height(px4), h
        if abs(h - h_prev) < 0.1:
            return


def test_start_while_airborne_is_refused(px4: PX4Sitl, px4_bench: Px4Bench, log_dir: Path) -> None:
    if not _take_off_by_px4(px4):  # the SIH ground deadlock above: the set-up, not the app, failed; once more
        px4 = px4_bench.fresh()
        assert _take_off_by_px4(px4), f"a fresh PX4 did not lift off either: {px4.console_tail()}"
    h0 = _height(px4)
    rc, out = finish(start_app(px4, log_dir), timeout=90)
    path = states(flight_folder(log_dir))
    assert "ARM" not in path and "TAKEOFF" not in path, path
    assert rc == int(Reason.VEHICLE_BUSY), out  # refused before commanding anything
    assert path[-1] == "REFUSED", path
    st = px4.status()
    assert st.armed and st.nav_mode == "Hold", st
    assert abs(_height(px4) - h0) < 1.0
