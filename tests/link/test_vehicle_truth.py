"""What the link believes must be what PX4 reports: spoofed and impossible MAVLink is kept out, PX4's
events are heard, setpoints leave inside the envelope, links never listen on every interface.

Spoofers are raw pymavlink sockets on 127.0.0.1 sending to the port mavsdk listens on (the one the
simulated PX4 sends to, as PX4 SITL does).
"""

from __future__ import annotations

import asyncio
import math
import socket
import time

import numpy as np
import pytest
from linkkit import connected_link, flying_link, run, setpoint
from pymavlink.dialects.v20 import common as mavlink
from scipy.spatial.transform import Rotation

from companion.app.envelope import SetpointEnvelope, tilt_deg
from companion.app.failsafe import judge
from companion.app.link import VehicleLink
from companion.app.linkerrors import ConnectFailed, SetpointRejected, WrongAutopilot
from companion.app.px4events import EventDecoder
from companion.app.telemetry import attitude_problem
from companion.config import Config, load_config
from companion.configbase import ConfigError
from companion.sim.px4 import SimPX4

POSCTL_ARMED = (mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 3 << 16)


class Spoofer:
    """Sends MAVLink as (sysid, compid) from its own socket to where mavsdk listens."""

    def __init__(self, port: int, sysid: int, compid: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.addr = ("127.0.0.1", port)
        self.mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)

    def send(self, msg: mavlink.MAVLink_message) -> None:
        self.sock.sendto(msg.pack(self.mav), self.addr)
        self.mav.seq = (self.mav.seq + 1) % 256

    def heartbeat_posctl_armed(self) -> None:
        base, custom = POSCTL_ARMED
        self.send(self.mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base, custom,
                                            mavlink.MAV_STATE_ACTIVE, 3))

    def attitude(self, q_wxyz: list[float], t_ms: int) -> None:
        self.send(self.mav.attitude_quaternion_encode(t_ms, *q_wxyz, 0.0, 0.0, 0.0, [0.0, 0.0, 0.0, 0.0]))

    def close(self) -> None:
        self.sock.close()


async def _spoof_for(seconds: float, action) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        action()
        await asyncio.sleep(0.02)


def test_heartbeat_from_another_system_changes_nothing(sim: SimPX4, cfg: Config) -> None:
    async def body() -> None:
        async with await connected_link(sim, cfg) as link:
            assert link.flight_mode == "HOLD" and link.armed is False
            spoof = Spoofer(sim.remote_port, sysid=2, compid=1)  # another vehicle, or an attacker's
            try:
                await _spoof_for(2.0, spoof.heartbeat_posctl_armed)
            finally:
                spoof.close()
            assert link.flight_mode == "HOLD" and link.armed is False
            assert not [e for e in link.events if e[1] == "mode" and e[2]["new"] == "POSCTL"]
            assert not [e for e in link.events if e[1] == "armed"]

    run(body, 30)


def test_attitude_from_another_component_never_reaches_the_controller(sim: SimPX4, cfg: Config) -> None:
    async def body() -> None:
        async with await connected_link(sim, cfg) as link:
            spoof = Spoofer(sim.remote_port, sysid=1, compid=2)  # same system, not the autopilot component
            upside_down = [0.0, 1.0, 0.0, 0.0]
            try:
                await _spoof_for(1.0, lambda: spoof.attitude(upside_down, 10**7))
            finally:
                spoof.close()
            R = link.attitude.R_ned_frd
            assert R[2, 2] > 0.9  # still PX4's level attitude, never the spoofed one
            assert min(r[2, 2] for r in (Rotation.from_quat(np.roll(q, -1)).as_matrix()
                                         for q in list(link.attitude_history._q))) > 0.9
            rej = [e for e in link.events if e[1] == "telemetry_rejected"]
            assert rej and "from component 2, not 1" in rej[0][2]["why"]

    run(body, 30)


def test_nan_attitude_is_rejected_and_persisting_rejects_are_reported(sim: SimPX4, cfg: Config) -> None:
    async def body() -> None:
        async with await connected_link(sim, cfg) as link:
            spoof = Spoofer(sim.remote_port, sysid=1, compid=1)  # even from the autopilot's own ids
            t_ms = int(sim.time * 1000) + 5
            try:
                await _spoof_for(0.5, lambda: spoof.attitude([math.nan, math.nan, 0.0, 0.0], t_ms))
            finally:
                spoof.close()
            await asyncio.sleep(0.1)
            assert np.isfinite(link.attitude.q_wxyz).all() and link.attitude.R_ned_frd[2, 2] > 0.9
            rej = [e for e in link.events if e[1] == "telemetry_rejected"]
            assert rej and "non-finite quaternion" in rej[0][2]["why"]
            inv = [e for e in link.events if e[1] == "telemetry_invalid"]
            assert len(inv) == 1 and inv[0][2]["count"] >= cfg.safety.telemetry_reject_limit

    run(body, 30)


def test_attitude_plausibility_rules() -> None:
    level = np.array([1.0, 0.0, 0.0, 0.0])
    assert attitude_problem([1.0, 0.0, 0.0, 0.0], 1000, level, 980) is None
    assert "non-finite" in attitude_problem([math.nan, 0.0, 0.0, 0.0], 1000, None, None)
    assert "non-finite" in attitude_problem([None, 0.0, 0.0, 1.0], 1000, None, None)
    assert "norm 2.000" in attitude_problem([2.0, 0.0, 0.0, 0.0], 1000, None, None)
    assert "went back from 1000 to 123 ms" in attitude_problem([1.0, 0.0, 0.0, 0.0], 123, level, 1000)
    flipped = [0.0, 1.0, 0.0, 0.0]  # 180 deg roll in 20 ms
    assert "tilt jumped 180 deg in 20 ms" in attitude_problem(flipped, 1020, level, 1000)
    # A yaw step (PX4's EKF resets its heading in flight) is a real estimate, not a jump.
    yawed = [math.cos(math.radians(23.5)), 0.0, 0.0, math.sin(math.radians(23.5))]  # 47 deg yaw
    assert attitude_problem(yawed, 1020, level, 1000) is None
    # The same 180 deg over 2 s is a (fast) rotation, not a jump.
    assert attitude_problem(flipped, 3000, level, 1000) is None
    # q and -q are the same rotation.
    assert attitude_problem([-1.0, 0.0, 0.0, 0.0], 1020, level, 1000) is None


def test_connect_accepts_only_the_configured_system(sim: SimPX4) -> None:
    cfg = load_config([], ["link.system_id=7"])

    async def body() -> None:
        link = VehicleLink.from_config(cfg)
        with pytest.raises(WrongAutopilot, match=r"no autopilot with system id 7 \(link.system_id\).*heard "
                                                 r"system\(s\) \[1\]"):
            await link.connect(sim.url_for_mavsdk, timeout=2.5)
        await link.close()

    run(body, 20)


@pytest.mark.parametrize("url", ["udpout://127.0.0.1:14540", "udpin://0.0.0.0:14540", "udp://:14540"])
def test_links_on_every_interface_are_refused_unless_allowed(url: str) -> None:
    with pytest.raises(ConfigError, match=r"link\.allow_all_interfaces"):
        load_config([], [f"link.url={url}"])
    cfg = load_config([], ["link.allow_all_interfaces=true", f"link.url={url}"])
    assert cfg.link.url == url

    async def body() -> None:
        link = VehicleLink(load_config([], []).link)
        with pytest.raises(ConnectFailed, match="refused"):
            await link.connect(url, timeout=0.5)
        await link.close()

    run(body, 10)


def test_px4_events_reach_the_link(sim: SimPX4, cfg: Config) -> None:
    """PX4 1.15 speaks in events: the simulated PX4 sends PX4's own event ids, the link decodes them."""

    async def body() -> None:
        async with await flying_link(sim, cfg) as link:
            texts = [e[2]["text"] for e in link.events if e[1] == "px4_event"]
            assert "Armed by external command" in texts
            assert "Takeoff detected" in texts
            await link.land()
            await link.wait_landed_and_disarm(30.0)
            texts = [e[2]["text"] for e in link.events if e[1] == "px4_event"]
            assert "Landing detected" in texts and "Disarmed by landing" in texts

    run(body, 60)


def test_event_decoder_on_px4_messages() -> None:
    """Ids and argument bytes as PX4 v1.15 SITL sent them (captured with mavsdk mavlink_direct)."""
    d = EventDecoder.load()
    ev = d.decode({"id": 26266355, "log_levels": 102, "arguments": [4] + [0] * 39, "sequence": 61})
    assert (ev.name, ev.text, ev.level) == ("commander_armed_by", "Armed by external command", "info")
    ev = d.decode({"id": 20656071, "log_levels": 102, "arguments": [0, 0, 32, 64] + [0] * 36, "sequence": 63})
    assert ev.text == "Using default takeoff altitude: 2.50"
    ev = d.decode({"id": 31382480, "log_levels": 34, "arguments": [0, 0, 0, 0, 2] + [0] * 35, "sequence": 84})
    assert ev.text == "Failsafe activated: Autopilot disengaged, switching to Position mode" and ev.severe
    assert "not in the metadata" in d.decode({"id": 123, "arguments": []}).text


def test_setpoint_envelope_clamps_tilt_keeping_its_direction() -> None:
    env = SetpointEnvelope(50.0, 0.1)
    for roll, pitch in [(80.0, 0.0), (0.0, -75.0), (60.0, 40.0), (-45.0, 45.0), (170.0, 10.0)]:
        c = env.check(roll, pitch, 30.0, 0.6)
        assert "airframe.max_tilt" in c.clamped
        assert tilt_deg(c.roll_deg, c.pitch_deg) == pytest.approx(50.0, abs=1e-6)
        # Independent check with scipy: the thrust axis points the same way horizontally, yaw unchanged.
        z0 = Rotation.from_euler("ZYX", [30.0, pitch, roll], degrees=True).as_matrix()[:, 2]
        z1 = Rotation.from_euler("ZYX", [30.0, c.pitch_deg, c.roll_deg], degrees=True).as_matrix()[:, 2]
        if roll < 90:
            assert math.atan2(z0[1], z0[0]) == pytest.approx(math.atan2(z1[1], z1[0]), abs=1e-6)
        assert c.yaw_deg == 30.0
    ok = env.check(20.0, -30.0, 10.0, 0.5)
    assert ok.clamped == "" and (ok.roll_deg, ok.pitch_deg, ok.thrust) == (20.0, -30.0, 0.5)
    low = env.check(0.0, 0.0, 0.0, 0.0)
    assert low.thrust == 0.1 and "thrust_min" in low.clamped
    for bad in [(math.nan, 0, 0, 0.5), (0, math.inf, 0, 0.5), (0, 0, 0, math.nan)]:
        with pytest.raises(ValueError, match="non-finite"):
            env.check(*bad)


def test_link_sends_only_setpoints_inside_the_envelope(sim: SimPX4, cfg: Config) -> None:
    async def body() -> None:
        async with await flying_link(sim, cfg) as link:
            await link.start_offboard(setpoint(link))
            await link.set_setpoint(setpoint(link, roll=85.0, thrust=0.05))
            # Wait for this setpoint itself: a count would also see MAVSDK resending the level one before it.
            end = time.monotonic() + 2.0
            while sim.last_setpoint()[2] > 0.3 and time.monotonic() < end:
                await asyncio.sleep(0.01)
            _, q_xyzw, thrust = sim.last_setpoint()
            up = Rotation.from_quat(q_xyzw).as_matrix()[:, 2]  # body up in ENU
            assert math.degrees(math.acos(up[2])) == pytest.approx(cfg.airframe.max_tilt, abs=0.5)
            assert thrust == pytest.approx(cfg.airframe.thrust_min)
            clamp = [e for e in link.events if e[1] == "envelope"]
            assert clamp and clamp[0][2]["action"] == "clamped" and "max_tilt" in clamp[0][2]["why"]
            n1 = sim.setpoint_count
            with pytest.raises(SetpointRejected, match="non-finite"):
                await link.set_setpoint(setpoint(link, pitch=math.nan))
            assert [e for e in link.events if e[1] == "envelope" and e[2]["action"] == "refused"]
            _, q2, _ = sim.last_setpoint()
            assert np.isfinite(q2).all() and sim.setpoint_count >= n1  # nothing non-finite ever left
            await link.stop_offboard()

    run(body, 60)


def test_failsafe_judgement() -> None:
    px4 = {"COM_OF_LOSS_T": 1.0, "COM_OBL_RC_ACT": 0.0, "COM_RC_IN_MODE": 1.0, "NAV_RCL_ACT": 2.0,
           "COM_RCL_EXCEPT": 0.0, "COM_RC_LOSS_T": 0.5, "NAV_DLL_ACT": 0.0, "COM_DL_LOSS_T": 10.0,
           "COM_FAIL_ACT_T": 5.0}
    line, problems = judge(px4, 2.0)
    assert problems == []
    assert "COM_OBL_RC_ACT = 0 (Position mode) (without manual control PX4 descends and lands)" in line
    assert "NAV_RCL_ACT = 2 (Return)" in line
    _, problems = judge({**px4, "COM_OBL_RC_ACT": 7.0}, 2.0)
    assert problems and "COM_OBL_RC_ACT = 7 (Disarm) is not a safe end" in problems[0]
    _, problems = judge({**px4, "COM_OF_LOSS_T": 5.0}, 2.0)
    assert problems and "COM_OF_LOSS_T = 5 s" in problems[0]
    _, problems = judge({**px4, "COM_OBL_RC_ACT": None}, 2.0)
    assert problems and "could not read COM_OBL_RC_ACT" in problems[0]
