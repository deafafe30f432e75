"""The PX4 SITL tooling's own parts, without PX4: truth conversion and reader, instance choice, config, lookup.

These run everywhere (no ``px4`` marker); the flights against PX4 are in test_px4_flight.py / test_px4_faults.py.
"""

from __future__ import annotations

import math
import os
import socket
import stat
import time
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink2
from scipy.spatial.transform import Rotation

from companion.config import load_config
from companion.configbase import ConfigError
from companion.netports import free_udp_port
from companion.px4sitl.launcher import PX4Sitl, PX4SitlError, claim_instance, client_bin, find_sitl_dir, instance_ports
from companion.px4sitl.truth import SihTruth, hil_to_ned

ORIGIN = (454671160.0, -737578370.0, 32.34)  # SIH_LOC_* of the shared build (Montreal)


def test_flat_earth_matches_a_spherical_distance() -> None:
    # 30 m north, 40 m east, 5 m up of the origin, built with the spherical relations the other way round.
    lat0 = ORIGIN[0] * 1e-7
    lat = lat0 + math.degrees(30.0 / 6371000.0)
    lon = ORIGIN[1] * 1e-7 + math.degrees(40.0 / (6371000.0 * math.cos(math.radians(lat0))))
    p = hil_to_ned(lat * 1e7, lon * 1e7, (ORIGIN[2] + 5.0) * 1000.0, ORIGIN)
    np.testing.assert_allclose(p, [30.0, 40.0, -5.0], atol=0.02)  # 1e-7 deg ~ 1.1 cm
    # Haversine distance of the same two points agrees with the horizontal norm.
    dlat, dlon = math.radians(lat - lat0), math.radians(lon - ORIGIN[1] * 1e-7)
    a = math.sin(dlat / 2) ** 2 + math.cos(math.radians(lat0)) * math.cos(math.radians(lat)) * math.sin(dlon / 2) ** 2
    assert abs(2 * 6371000.0 * math.asin(math.sqrt(a)) - 50.0) < 0.05


def test_truth_reader_over_real_udp_interpolates_and_extrapolates() -> None:
    port = free_udp_port()
    truth = SihTruth(f"udpin:127.0.0.1:{port}", ORIGIN)
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    try:
        yaws = [0.0, 40.0]
        for k, yaw in enumerate(yaws):
            q = Rotation.from_euler("z", yaw, degrees=True).as_quat()  # x y z w
            lat = ORIGIN[0] + k * 1000  # 1e-4 deg north per sample = 11.1 m
            msg = mav.hil_state_quaternion_encode(0, [q[3], q[0], q[1], q[2]], 0, 0, 0, int(lat), int(ORIGIN[1]),
                                                  int(ORIGIN[2] * 1000 + 2000 * k), 500, 0, -100, 0, 0, 0, 0, 0)
            out.sendto(msg.pack(mav), ("127.0.0.1", port))
            deadline = time.monotonic() + 5.0
            while truth.received < k + 1:
                assert time.monotonic() < deadline, "the reader got nothing"
                time.sleep(0.01)
            time.sleep(0.05)
        a, b = truth._hist[0], truth._hist[1]
        np.testing.assert_allclose(a.position_ned, [0.0, 0.0, 0.0], atol=1e-6)
        np.testing.assert_allclose(b.position_ned[[1, 2]], [0.0, -2.0], atol=1e-3)
        assert abs(b.position_ned[0] - math.radians(1e-4) * 6371000.0) < 1e-3
        np.testing.assert_allclose(b.velocity_ned, [5.0, 0.0, -1.0])
        mid = truth.at(0.5 * (a.t_rx + b.t_rx))
        assert mid is not None
        np.testing.assert_allclose(mid.position_ned, 0.5 * (a.position_ned + b.position_ned), atol=1e-9)
        yaw_mid = Rotation.from_quat(np.roll(mid.q_wxyz, -1)).as_euler("ZYX", degrees=True)[0]
        assert abs(yaw_mid - 20.0) < 1e-6  # on the sphere, half way
        ahead = truth.at(b.t_rx + 0.02)
        np.testing.assert_allclose(ahead.position_ned, b.position_ned + 0.02 * b.velocity_ned, atol=1e-9)
        assert truth.latest() is b
    finally:
        out.close()
        truth.close()


def test_truth_origin_defaults_to_the_first_message() -> None:
    port = free_udp_port()
    truth = SihTruth(f"udpin:127.0.0.1:{port}")
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    try:
        msg = mav.hil_state_quaternion_encode(0, [1, 0, 0, 0], 0, 0, 0, 123456789, 98765432, 50000, 0, 0, 0, 0, 0,
                                              0, 0, 0)
        out.sendto(msg.pack(mav), ("127.0.0.1", port))
        s = truth.wait(5.0)
        np.testing.assert_allclose(s.position_ned, [0.0, 0.0, 0.0], atol=1e-9)
        assert truth.origin == (123456789.0, 98765432.0, 50.0)
    finally:
        out.close()
        truth.close()


def test_instance_choice_skips_busy_ports_and_held_instances() -> None:
    # Find an instance whose ports are free now, occupy one of its ports: it must be skipped.
    n, lock = claim_instance(range(10))
    lock.close()
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", instance_ports(n)["sih_remote"]))
    try:
        m, lock_m = claim_instance(range(n, 10))
        assert m != n
        # While we hold m, nobody else gets it.
        with pytest.raises(PX4SitlError, match="no free PX4 instance"):
            claim_instance([m])
        lock_m.close()
        with pytest.raises(PX4SitlError, match="no free PX4 instance"):
            claim_instance([n])
    finally:
        s.close()


def test_config_refuses_a_faster_sih_and_bad_parameter_names() -> None:
    with pytest.raises(ConfigError, match=r"px4\.speed_factor"):
        load_config([], ["px4.speed_factor=4"])
    with pytest.raises(ConfigError, match=r"px4\.params"):
        load_config([], ["px4.params={'sih mass': 2}"])
    cfg = load_config([], ["px4.params={'COM_OF_LOSS_T': 2}"])
    assert cfg.px4.params == {"COM_OF_LOSS_T": 2.0}


def test_profile_parameters_follow_the_config(tmp_path: Path) -> None:
    cfg = load_config([], ["airframe.hover_thrust=0.3", "px4.sih.mass=1.5"])
    (tmp_path / "bin").mkdir()
    (tmp_path / "etc" / "init.d-posix").mkdir(parents=True)
    (tmp_path / "etc" / "init.d-posix" / "rcS").write_text("")
    px4 = tmp_path / "bin" / "px4"
    px4.write_text("#!/bin/sh\n")
    px4.chmod(px4.stat().st_mode | stat.S_IXUSR)
    launcher = PX4Sitl.from_config(cfg, sitl_dir=tmp_path)
    assert launcher.params["SIH_MASS"] == 1.5
    assert launcher.params["MPC_THR_HOVER"] == 0.3  # the profile's hover thrust, so PX4's estimator is not clamped
    assert launcher.params["EKF2_GPS_DELAY"] == 0.0  # SIH's GPS has no delay
    assert launcher.params["SIH_T_MAX"] == 9.81


def test_sitl_lookup_names_what_is_missing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("PX4_SITL_DIR", raising=False)
    with pytest.raises(PX4SitlError, match="set PX4_SITL_DIR"):
        find_sitl_dir(None, "")
    monkeypatch.setenv("PX4_SITL_DIR", str(tmp_path))
    with pytest.raises(PX4SitlError, match=r"PX4_SITL_DIR = .*no PX4 binary"):
        find_sitl_dir(None, "")
    with pytest.raises(PX4SitlError, match=r"--px4-dir = .*no PX4 binary"):
        find_sitl_dir(tmp_path / "nothing", "")


def test_client_commands_made_executable(tmp_path: Path) -> None:
    # A build copied without its symlinks: bin/px4-param is a text file 'px4', not executable.
    b = tmp_path / "bin"
    b.mkdir()
    (b / "px4").write_text("#!/bin/sh\n")
    (b / "px4-param").write_text("px4")
    (b / "px4-alias.sh").write_text("alias param='px4-param'\n")
    out = client_bin(tmp_path)
    assert out != b
    assert os.path.realpath(out / "px4-param") == os.path.realpath(b / "px4")
    assert (out / "px4-alias.sh").read_text() == "alias param='px4-param'\n"
    assert client_bin(tmp_path) == out  # made once


def test_px4_run_score_from_a_flight_log(tmp_path: Path) -> None:
    """The PX4 table's per-run score, from a flight log written by the real FlightLog: a straight pass 0.3 m
    beside a stationary gate 20 m ahead, engaged at t = 1 s, at 10 m/s."""
    from companion.evaluation.px4 import score_flight
    from companion.flightlog import FlightLog

    t_now = [0.0]
    log = FlightLog(tmp_path / "f", {}, clock=lambda: t_now[0])
    log.state("ACQUIRE", "ENGAGE", "stable track", t=1.0)
    for k in range(0, 41):
        t = 1.0 + 0.1 * k
        t_now[0] = t
        n = 10.0 * (t - 1.0)
        log.write("truth", t=t, n=n, e=0.3, d=-10.0, vn=10.0, ve=0.0, vd=0.0)
        log.write("gate", t=t, k=1, gate_n=20.0, gate_e=0.0, gate_d=-10.0, normal_n=-1.0, normal_e=0.0,
                  normal_d=0.0, radius=1.0, visible=True)
        log.write("setpoints", t=t, t_frame=t, state="ENGAGE", ctrl_mode="pn",
                  roll_deg=10.0 * math.sin(2 * math.pi * t), pitch_deg=-20.0, yaw_deg=0.0, thrust=0.6, latency_ms=5.0)
    log.close({"outcome": "SAFE_HOLD", "reason": "OK", "gates_passed": 1,
               "frame_to_setpoint_ms": {"p50": 5.0, "p95": 6.0, "n": 41}})
    r = score_flight(tmp_path / "f", [0.25, 0.5, 1.0])
    assert r["crossed"]
    assert abs(r["t_gate_s"] - 2.0) < 1e-6  # 20 m at 10 m/s after ENGAGE
    assert abs(r["d_center_m"] - 0.3) < 1e-6
    assert r["success"] == {"0.25": False, "0.5": True, "1.0": True}
    assert r["failure"]["0.25"] == "missed"
    assert abs(r["top_speed_mps"] - 10.0) < 1e-9
    assert abs(r["roll_osc_amp_deg"] - 10.0) < 1.5 and abs(r["roll_osc_freq_hz"] - 1.0) < 0.15
    assert abs(r["max_tilt_deg"] - float(np.degrees(np.arccos(np.cos(np.radians(10)) * np.cos(np.radians(20)))))) < 0.5
    assert r["latency_p95_ms"] == 6.0


def test_sim_autopilot_px4_without_a_build_says_where_to_look(tmp_path: Path) -> None:
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "PX4_SITL_DIR"}
    r = subprocess.run([sys.executable, "-m", "companion.cli", "sim", "--autopilot", "px4", "--no-status",
                        "--set", f"log.directory={tmp_path}"], capture_output=True, text=True, env=env, timeout=60)
    assert r.returncode == 2
    assert "set PX4_SITL_DIR" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not any(tmp_path.iterdir())  # nothing flew, no flight log
