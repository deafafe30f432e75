"""Operator-confirmed engagement on real PX4 SITL (SIH), confirmed and withdrawn from the ground station.

The test is the ground station: a MAVLink connection of its own on PX4's GCS port (sysid 255, QGroundControl's
ids), sending HEARTBEAT at 1 Hz. It sends COMMAND_LONG MAV_CMD_USER_1 to the companion's ids (which the app logs),
PX4 forwards it over its onboard link to the app, and the app's COMMAND_ACK comes back the same way. PX4's own
HEARTBEAT on that link says what the vehicle does: no OFFBOARD before the confirmation, OFFBOARD after it, HOLD
after the withdrawal (also after the app has exited). The flight log must say the same.
"""

from __future__ import annotations

import re
import threading
import time
from pathlib import Path

import pytest
from px4kit import finish, flight_folder, start_app, states, wait_state

from companion.flightlog import read_flight, read_table
from companion.px4sitl.launcher import PX4Sitl, instance_ports

pytestmark = [pytest.mark.px4, pytest.mark.slow, pytest.mark.timeout(240)]

USER_1 = 31010  # app.confirm.command's default
OFFBOARD, HOLD = (6, 0), (4, 3)  # PX4 custom main/sub modes


class GroundStation:
    """A GCS on PX4's GCS link: heartbeats, commands with QGC-like resends, PX4's mode and the acks it hears."""

    def __init__(self, px4: PX4Sitl) -> None:
        from pymavlink import mavutil

        self.sysid = px4.instance + 1
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{instance_ports(px4.instance)['gcs_local']}",
                                               source_system=255, source_component=190)
        self.modes: list[tuple[float, tuple[int, int], bool]] = []  # (t, PX4 custom mode, armed) per heartbeat
        self.acks: list[tuple[float, int, int]] = []  # (t, command, result) addressed to us
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from pymavlink import mavutil

        next_hb = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_hb:
                self.conn.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID,
                                             0, 0, 0)
                next_hb = now + 1.0
            m = self.conn.recv_match(type=["HEARTBEAT", "COMMAND_ACK"], blocking=True, timeout=0.1)
            if m is None:
                continue
            with self._lock:
                if m.get_type() == "HEARTBEAT" and (m.get_srcSystem(), m.get_srcComponent()) == (self.sysid, 1):
                    mode = ((m.custom_mode >> 16) & 0xFF, (m.custom_mode >> 24) & 0xFF)
                    self.modes.append((time.monotonic(), mode, bool(m.base_mode & 128)))
                elif m.get_type() == "COMMAND_ACK" and (m.target_system, m.target_component) == (255, 190):
                    self.acks.append((time.monotonic(), int(m.command), int(m.result)))

    def command(self, target: tuple[int, int], param1: float, tries: int = 5) -> int:
        """COMMAND_LONG until acknowledged (a GCS resends after 1 s, as QGC does): the MAV_RESULT."""
        for _ in range(tries):
            t0 = time.monotonic()
            self.conn.mav.command_long_send(target[0], target[1], USER_1, 0, param1, 0, 0, 0, 0, 0, 0)
            while time.monotonic() - t0 < 1.5:
                with self._lock:
                    got = [a for a in self.acks if a[0] >= t0 and a[1] == USER_1]
                if got:
                    return got[0][2]
                time.sleep(0.02)
        raise AssertionError(f"no COMMAND_ACK for command {USER_1} param1 {param1} after {tries} tries")

    def modes_since(self, t0: float) -> list[tuple[int, int]]:
        with self._lock:
            return [m for t, m, _ in self.modes if t >= t0]

    def wait_mode(self, mode: tuple[int, int], since: float, timeout: float) -> float:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                hit = [t for t, m, _ in self.modes if t >= since and m == mode]
            if hit:
                return hit[0]
            time.sleep(0.05)
        raise AssertionError(f"PX4 never reported mode {mode} within {timeout:.0f} s: {self.modes_since(since)}")

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.conn.close()


def _event(folder: Path, pattern: str, proc, timeout: float) -> re.Match[str]:
    """The first flight-log event matching ``pattern`` (bounded wait; fails if the app exits first)."""
    deadline = time.monotonic() + timeout
    rx = re.compile(pattern)
    while time.monotonic() < deadline:
        p = folder / "events.csv"
        if p.exists():
            for text in read_table(p)["text"] if len(read_table(p)) else []:
                m = rx.search(str(text))
                if m:
                    return m
        assert proc.poll() is None, f"app exited ({proc.returncode}) before {pattern!r}: {states(folder)}"
        time.sleep(0.1)
    raise AssertionError(f"no event {pattern!r} within {timeout:.0f} s: {states(folder)}")


def test_ground_station_confirms_then_withdraws_on_px4(px4: PX4Sitl, log_dir: Path) -> None:
    gcs = GroundStation(px4)
    proc = start_app(px4, log_dir, "app.engage=confirm", "app.synthetic.motion=stationary",
                     "app.synthetic.distance=35", "app.takeoff_altitude=6", "app.confirm.command=0")
    try:
        folder = flight_folder(log_dir, timeout=60)
        own = _event(folder, r"ground-station confirm: command 31010 to (\d+)/(\d+)", proc, 90)
        target = (int(own[1]), int(own[2]))
        _event(folder, "candidate awaiting confirmation", proc, 90)
        t_shown = time.monotonic()
        time.sleep(2.0)  # shown, nobody confirms: PX4 keeps holding
        assert "ENGAGE" not in states(folder), states(folder)
        t_confirm = time.monotonic()
        before = gcs.modes_since(t_shown)  # PX4's reports while the candidate waited
        assert gcs.command(target, 1.0) == 0  # ACCEPTED
        wait_state(folder, "ENGAGE", proc, 15)
        t_off = gcs.wait_mode(OFFBOARD, t_confirm, 15)  # PX4's own report: it flies our setpoints
        assert gcs.command(target, 0.0) == 0  # the withdraw, ACCEPTED
        t_hold = gcs.wait_mode(HOLD, t_off, 15)
        rc, out = finish(proc, timeout=90)
        # PX4 still reports HOLD, armed, after the app has exited (true of the vehicle, not just the log)
        t_end = time.monotonic()
        gcs.wait_mode(HOLD, t_end, 10)
        after = [(m, armed) for t, m, armed in gcs.modes if t >= t_end]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        gcs.close()
    f = read_flight(folder)
    path = f.state_path()
    assert rc == 25 and f.summary["outcome"] == "SAFE_HOLD", (rc, f.summary, out)
    assert "ENGAGE" in path and path[-1] == "SAFE_HOLD", path
    ev = [str(e) for e in f["events"]["text"]]
    i_conf = next(i for i, e in enumerate(ev) if "ground-station confirm from 255/190: ACCEPTED" in e)
    assert any("ground-station withdraw from 255/190: ACCEPTED" in e for e in ev[i_conf:]), ev
    assert any("withdrawn from the ground station" in e for e in ev[i_conf:]), ev
    assert any("withdrew the confirmation" in str(r["reason"]) for r in f.states), f.states
    # PX4: never OFFBOARD while the candidate waited; OFFBOARD after the confirm, HOLD after the withdraw
    assert before and OFFBOARD not in before, before
    assert t_confirm < t_off < t_hold
    assert f.summary.get("gates_passed", 0) == 0  # withdrawn before the gate
    assert after[0] == (HOLD, True), f"after the app exited PX4 reports {after[0]}, the app said SAFE_HOLD (armed)"
    print(f"PX4 OFFBOARD {t_off - t_confirm:.2f} s after the confirm was sent, HOLD {t_hold - t_off:.2f} s after "
          f"OFFBOARD was reported (withdraw sent at once)")
