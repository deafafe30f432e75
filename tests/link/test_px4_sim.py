"""The simulated PX4 on its own, driven by a bare pymavlink client (no MAVSDK, so nothing is resent)."""

from __future__ import annotations

import json
import math
import socket
import subprocess
import sys

import numpy as np
import pytest
from linkkit import TRUE_HOVER, RawGcs
from pymavlink.dialects.v20 import common as mavlink

from companion.config import Config
from companion.sim.px4 import SimPX4

LEVEL = [1.0, 0.0, 0.0, 0.0]
OFFBOARD = (mavlink.MAV_CMD_DO_SET_MODE, 1.0, 6.0, 0.0)


@pytest.mark.timeout(30)
def test_offboard_needs_setpoints_and_fails_safe_when_they_stop(sim: SimPX4, gcs: RawGcs) -> None:
    sim.set_param("COM_OBL_RC_ACT", 5)  # Hold (PX4's default 0 is tested through mavsdk in test_link.py)
    gcs.command(*OFFBOARD)
    assert gcs.ack(mavlink.MAV_CMD_DO_SET_MODE) == mavlink.MAV_RESULT_DENIED
    assert sim.mode == "HOLD"
    assert sim.wait_event("offboard_denied:no_setpoints", 1.0) is not None

    gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    assert gcs.ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM) == mavlink.MAV_RESULT_ACCEPTED
    for _ in range(5):
        gcs.attitude_setpoint(LEVEL, 0.2)
    assert sim.wait_for(lambda: sim.setpoint_count >= 5, 2.0)
    gcs.command(*OFFBOARD)
    assert gcs.ack(mavlink.MAV_CMD_DO_SET_MODE) == mavlink.MAV_RESULT_ACCEPTED
    # The next 1 Hz heartbeat (none extra on the change, as PX4) reports it the PX4 way: custom_mode = 6 << 16.
    # Setpoints keep coming meanwhile (else the offboard-loss failsafe may beat the heartbeat).
    hb = None
    for _ in range(60):
        gcs.attitude_setpoint(LEVEL, 0.2)
        hb = gcs.recv(lambda m: m.get_type() == "HEARTBEAT" and m.custom_mode == 6 << 16, 0.05)
        if hb is not None:
            break
    assert hb is not None and hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert hb.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_PX4 and hb.get_srcComponent() == 1
    assert sim.wait_event("mode:OFFBOARD:command", 1.0) is not None

    # Setpoints stop (nothing resends them): the failsafe fires no earlier than COM_OF_LOSS_T after the last.
    t_last, _, _ = sim.last_setpoint()
    ev = sim.wait_event("failsafe:offboard_loss", 5.0)
    assert ev is not None
    assert ev[0] - t_last >= sim.param("COM_OF_LOSS_T") - 1e-9
    assert sim.wait_event("mode:HOLD:failsafe", 1.0) is not None
    assert sim.mode == "HOLD"


@pytest.mark.timeout(30)
def test_attitude_setpoint_is_flown_in_offboard(cfg: Config, gcs: RawGcs, sim: SimPX4) -> None:
    """SET_ATTITUDE_TARGET (NED/FRD wxyz) becomes the vehicle's true attitude (checked in ENU/FLU truth)."""
    from scipy.spatial.transform import Rotation

    gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    assert gcs.ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM) == mavlink.MAV_RESULT_ACCEPTED
    # Yaw 30 deg (NED: from north toward east), pitch 10 deg nose up, enough thrust to lift off.
    r_ned = Rotation.from_euler("ZYX", [30.0, 10.0, 0.0], degrees=True)
    x, y, z, w = r_ned.as_quat()
    gcs.attitude_setpoint([w, x, y, z], 0.45)
    gcs.command(*OFFBOARD)
    assert gcs.ack(mavlink.MAV_CMD_DO_SET_MODE) == mavlink.MAV_RESULT_ACCEPTED
    for _ in range(40):  # 1 s at 40 Hz
        gcs.attitude_setpoint([w, x, y, z], 0.45)
        gcs.recv(lambda m: False, 0.025)
    s = sim.truth()
    assert not s.on_ground and s.p[2] > 0.1  # thrust above hover (TRUE_HOVER) lifts it
    # Independent check: body x (forward) in ENU must point 30 deg east of north, 10 deg up.
    fwd = Rotation.from_quat(s.q).apply([1.0, 0.0, 0.0])
    heading_from_north = math.degrees(math.atan2(fwd[0], fwd[1]))
    elevation = math.degrees(math.asin(fwd[2]))
    assert heading_from_north == pytest.approx(30.0, abs=1.0)
    assert elevation == pytest.approx(10.0, abs=1.0)
    assert TRUE_HOVER < 0.45


@pytest.mark.timeout(20)
def test_params_read_set_and_int_encoding(sim: SimPX4, gcs: RawGcs) -> None:
    gcs.send(gcs.mav.param_request_read_encode(1, 1, b"MPC_THR_HOVER", -1))
    m = gcs.recv(lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "MPC_THR_HOVER", 2.0)
    assert m is not None and m.param_value == pytest.approx(TRUE_HOVER, abs=1e-6)
    assert m.param_type == mavlink.MAV_PARAM_TYPE_REAL32
    # PX4 sends INT32 parameters bytewise inside the float field.
    gcs.send(gcs.mav.param_request_read_encode(1, 1, b"NAV_RCL_ACT", -1))
    m = gcs.recv(lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "NAV_RCL_ACT", 2.0)
    assert m is not None and m.param_type == mavlink.MAV_PARAM_TYPE_INT32
    assert int(np.array([m.param_value], "<f4").view("<i4")[0]) == 2  # PX4 1.15 SIH: Return
    gcs.send(gcs.mav.param_set_encode(1, 1, b"COM_OF_LOSS_T", 0.4, mavlink.MAV_PARAM_TYPE_REAL32))
    m = gcs.recv(lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "COM_OF_LOSS_T", 2.0)
    assert m is not None and m.param_value == pytest.approx(0.4)
    assert sim.param("COM_OF_LOSS_T") == pytest.approx(0.4)


@pytest.mark.timeout(20)
def test_switches_deny_arming_and_silence(sim: SimPX4, gcs: RawGcs) -> None:
    sim.deny_arming = True
    gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    assert gcs.ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM) == mavlink.MAV_RESULT_DENIED
    assert not sim.armed
    sim.deny_arming = False
    sim.silence_commands(True)
    gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    assert gcs.ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, timeout=1.0) is None
    assert not sim.armed and sim.wait_event("silenced:400", 1.0) is not None
    sim.silence_commands(False)
    gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    assert gcs.ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM) == mavlink.MAV_RESULT_ACCEPTED
    assert sim.armed


@pytest.mark.timeout(20)
def test_drop_link_silences_both_directions(sim: SimPX4, gcs: RawGcs) -> None:
    assert gcs.recv(lambda m: m.get_type() == "ATTITUDE_QUATERNION", 2.0) is not None
    sim.drop_link(True)
    gcs.recv(lambda m: False, 0.2)  # let in-flight datagrams drain
    assert gcs.recv(lambda m: True, 0.5) is None
    gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    gcs.recv(lambda m: False, 0.3)
    assert not sim.armed
    sim.drop_link(False)
    gcs.heartbeat()
    assert gcs.recv(lambda m: m.get_type() == "ATTITUDE_QUATERNION", 2.0) is not None


def test_port_is_exclusive(sim: SimPX4) -> None:
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    other.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as MAVSDK's udpin listener does
    try:
        with pytest.raises(OSError):
            other.bind(("127.0.0.1", sim.port))
    finally:
        other.close()
    # mavsdk listens on 127.0.0.1 where the sim sends (as with PX4 SITL): nothing binds every interface.
    assert sim.url_for_mavsdk == f"udpin://127.0.0.1:{sim.remote_port}"


def test_unknown_px4_param_is_one_clear_error() -> None:
    with pytest.raises(ValueError, match="unknown PX4 parameter 'MPC_THR_HOVR'"):
        SimPX4(px4_params={"MPC_THR_HOVR": 0.4})


@pytest.mark.timeout(30)
def test_process_entry_point_prints_port_obeys_stdin_and_sigterm() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "companion.sim.px4", "--port", "0", "--param", "MPC_THR_HOVER=0.44"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        line = proc.stdout.readline()  # the process prints its port first thing
        assert line.startswith("PORT "), line + proc.stderr.read()
        port = int(line.split()[1])
        gcs = RawGcs(port)
        gcs.heartbeat()
        gcs.send(gcs.mav.param_request_read_encode(1, 1, b"MPC_THR_HOVER", -1))
        m = gcs.recv(lambda m: m.get_type() == "PARAM_VALUE", 3.0)
        assert m is not None and m.param_value == pytest.approx(0.44, abs=1e-6)
        proc.stdin.write("deny_arming 1\n")
        proc.stdin.flush()
        assert proc.stdout.readline().strip() == "OK"
        gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
        assert gcs.ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM) == mavlink.MAV_RESULT_DENIED
        proc.stdin.write("wait_event arm_denied 5\n")
        proc.stdin.flush()
        assert proc.stdout.readline().split()[2] == "arm_denied:switch"
        proc.stdin.write("events\n")
        proc.stdin.flush()
        line = proc.stdout.readline()
        assert line.startswith("EVENTS ")
        assert "arm_denied:switch" in [what for _, what in json.loads(line[len("EVENTS "):])]
        proc.stdin.write("bogus\n")
        proc.stdin.flush()
        assert proc.stdout.readline().startswith("ERROR unknown command 'bogus'")
        gcs.close()
        proc.terminate()
        assert proc.wait(timeout=10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=5)


@pytest.mark.timeout(40)
def test_takeoff_and_hold_against_wind() -> None:
    """The sim's own HOLD (PX4's position controller stand-in) holds position in a steady 3 m/s wind."""
    from companion.sim.config import SimConfig, WindConfig

    cfg = Config(sim=SimConfig(seed=3, wind=WindConfig(mean=[3.0, -1.0, 0.0])))
    with SimPX4(cfg, px4_params={"MPC_TKO_SPEED": 3.0, "MIS_TAKEOFF_ALT": 3.0}) as sim:
        gcs = RawGcs(sim.port)
        gcs.heartbeat()
        gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
        assert gcs.ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM) == mavlink.MAV_RESULT_ACCEPTED
        gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF)
        assert gcs.ack(mavlink.MAV_CMD_NAV_TAKEOFF) == mavlink.MAV_RESULT_ACCEPTED
        assert sim.wait_event("mode:HOLD:takeoff_done", 15.0) is not None
        t0 = sim.time
        assert sim.wait_for(lambda: sim.time > t0 + 6.0, 15.0)
        s = sim.truth()
        assert s.p == pytest.approx([0.0, 0.0, 3.0], abs=0.4)
        assert np.linalg.norm(s.v) < 0.3
        # Holding still, thrust must cancel the drag of the wind: f = (lin + quad |w|) w pushes downwind, so
        # the thrust axis leans upwind by a / g (QuadParams' documented drag law, computed here by hand).
        from scipy.spatial.transform import Rotation

        from companion.sim.dynamics import QuadParams

        qp = QuadParams.from_config(cfg)
        wind = np.array([3.0, -1.0, 0.0])
        a_drag = (qp.drag_lin + qp.drag_quad * np.linalg.norm(wind)) * wind / qp.mass
        thrust = np.array([-a_drag[0], -a_drag[1], 9.81])
        up = Rotation.from_quat(s.q).apply([0.0, 0.0, 1.0])
        assert up == pytest.approx(thrust / np.linalg.norm(thrust), abs=0.004)
        assert up[0] < -0.005 and up[1] > 0.0
        gcs.close()


@pytest.mark.timeout(40)
def test_airborne_start_holds_and_streams_pose_for_the_synthetic_camera(cfg: Config) -> None:
    """A scenario starting in the air starts armed in HOLD; LOCAL_POSITION_NED / HIL_STATE_QUATERNION
    carry the true pose (NED by hand: north = ENU y, east = ENU x, down = -ENU z) at the telemetry rate."""
    from companion.sim.dynamics import QuadState

    start = QuadState(p=np.array([2.0, -1.0, 10.0]), v=np.array([4.0, 0.0, 0.0]), on_ground=False)
    with SimPX4(cfg, initial_state=start, noise=False) as sim:
        assert sim.armed and sim.mode == "HOLD"
        gcs = RawGcs(sim.port)
        gcs.heartbeat()
        assert sim.wait_for(lambda: sim.time > 6.0, 20.0)
        s = sim.truth()
        assert not s.on_ground and np.linalg.norm(s.v) < 0.5 and s.p[2] == pytest.approx(10.0, abs=0.5)
        assert abs(s.p[1] + 1.0) < 0.5  # it braked along x, kept y
        gcs.heartbeat()  # the sim forgets clients silent for 5 s, as a heartbeat-less GCS would be dead
        gcs.drain()
        lp = gcs.recv(lambda m: m.get_type() == "LOCAL_POSITION_NED", 2.0)
        s = sim.truth()
        assert [lp.x, lp.y, lp.z] == pytest.approx([s.p[1], s.p[0], -s.p[2]], abs=0.05)
        n0 = sim.time
        stamps = set()
        while sim.time < n0 + 1.0:
            m = gcs.recv(lambda m: m.get_type() == "HIL_STATE_QUATERNION", 1.0)
            stamps.add(m.time_usec)
        assert len(stamps) >= 30  # >= 30 Hz of ground truth, as the synthetic camera needs
        gcs.drain()
        m = gcs.recv(lambda m: m.get_type() == "HIL_STATE_QUATERNION", 1.0)
        s = sim.truth()
        from companion.sim.px4.model import HOME_ALT, HOME_LAT

        assert m.lat * 1e-7 == pytest.approx(HOME_LAT + math.degrees(s.p[1] / 6_378_137.0), abs=1e-6)
        assert m.alt * 1e-3 == pytest.approx(HOME_ALT + s.p[2], abs=0.1)
        # ATTITUDE_QUATERNION is body FRD -> NED, scalar first: its body x / body down (FRD z) must be the
        # truth's body x / minus body z (FLU), re-expressed by hand from ENU to NED.
        from scipy.spatial.transform import Rotation

        gcs.drain()
        aq = gcs.recv(lambda m: m.get_type() == "ATTITUDE_QUATERNION", 1.0)
        s = sim.truth()
        R_att = Rotation.from_quat([aq.q2, aq.q3, aq.q4, aq.q1]).as_matrix()
        R_true = Rotation.from_quat(s.q).as_matrix()

        def enu_to_ned(v: np.ndarray) -> list[float]:
            return [v[1], v[0], -v[2]]

        assert R_att[:, 0] == pytest.approx(enu_to_ned(R_true[:, 0]), abs=2e-3)
        assert R_att[:, 2] == pytest.approx(enu_to_ned(-R_true[:, 2]), abs=2e-3)
        gcs.close()


def test_initial_mode_must_be_a_position_mode() -> None:
    with pytest.raises(ValueError, match="initial_mode must be one of POSCTL, HOLD"):
        SimPX4(initial_mode="OFFBOARD")
