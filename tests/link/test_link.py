"""VehicleLink through the real mavsdk 4 library over UDP on localhost, against the simulated PX4."""

from __future__ import annotations

import asyncio
import math
import re

import numpy as np
import pytest
from linkkit import TRUE_HOVER, connected_link, flying_link, run, setpoint
from scipy.spatial.transform import Rotation

from companion.app.link import VehicleLink
from companion.app.linkerrors import (
    ArmDenied,
    CommandTimeout,
    LinkLost,
    OffboardDenied,
    OffboardLost,
    TakeoffFailed,
)
from companion.config import Config
from companion.frames import R_ned_frd_from_enu_flu
from companion.sim.px4 import SimPX4


def _angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    return math.degrees(Rotation.from_matrix(R_a.T @ R_b).magnitude())


@pytest.mark.timeout(60)
def test_connect_health_params_and_telemetry(sim: SimPX4, cfg: Config) -> None:
    async def body() -> None:
        async with await connected_link(sim, cfg) as link:
            # The autopilot's MPC_THR_HOVER wins over the config's 0.5.
            assert cfg.airframe.hover_thrust != pytest.approx(TRUE_HOVER)
            assert await link.hover_thrust() == pytest.approx(TRUE_HOVER, abs=1e-6)
            assert link.hover_thrust_source == "autopilot"
            assert await link.read_param("COM_OF_LOSS_T") == pytest.approx(1.0)
            await asyncio.sleep(0.3)
            assert link.flight_mode == "HOLD" and link.armed is False and link.landed_state == "ON_GROUND"
            # Attitude estimate = truth within the configured estimate error (bias + noise, ~0.3 deg each).
            R_true = R_ned_frd_from_enu_flu(Rotation.from_quat(sim.truth().q).as_matrix())
            assert _angle_deg(link.attitude.R_ned_frd, R_true) < 3.0
            # At rest the accelerometer reads the ground's push: -g along body down.
            assert link.imu.accel_frd == pytest.approx([0.0, 0.0, -9.81], abs=0.3)
            assert np.linalg.norm(link.imu.gyro_frd) < math.radians(2.0)
            assert link.baro_altitude == pytest.approx(0.0, abs=0.6)
            assert link.position_for_log is not None and np.allclose(link.position_for_log.position_ned, 0.0, atol=1e-3)
            assert link.link_ok

    run(body)


@pytest.mark.timeout(60)
def test_hover_thrust_falls_back_to_config_when_implausible(cfg: Config) -> None:
    with SimPX4(cfg, px4_params={"MPC_THR_HOVER": 0.99}) as sim:
        async def body() -> None:
            async with await connected_link(sim, cfg) as link:
                assert await link.hover_thrust() == cfg.airframe.hover_thrust
                assert link.hover_thrust_source == "config"

        run(body)


@pytest.mark.timeout(90)
def test_arm_takeoff_hold_land_disarm(sim: SimPX4, cfg: Config) -> None:
    async def body() -> None:
        async with await flying_link(sim, cfg, altitude=4.0) as link:
            assert sim.armed and sim.mode == "HOLD" and link.flight_mode == "HOLD"
            assert link.landed_state == "IN_AIR"
            p0 = sim.truth().p
            assert p0[2] == pytest.approx(4.0, abs=0.3)
            await asyncio.sleep(1.0)
            p1 = sim.truth().p
            assert np.linalg.norm(p1 - p0) < 0.3  # PX4's HOLD holds
            # Barometric altitude above take-off agrees with truth (bias cancels, noise 0.1 m).
            assert link.baro_altitude == pytest.approx(p1[2], abs=0.6)
            await link.land()
            await link.wait_landed_and_disarm(timeout=30.0)
            assert link.armed is False and not sim.armed
            assert sim.truth().on_ground and not sim.truth().ground_contact
            assert sim.wait_event("disarm:auto_land", 1.0) is not None

    run(body, 80)


@pytest.mark.timeout(60)
def test_a_takeoff_that_does_not_finish_says_how_high_it_got(cfg: Config) -> None:
    """PX4 climbing slower than the take-off timeout allows (PX4 SITL under load once took > 30 s to 6 m): the
    error names the altitude reached, by the barometer, which agrees with the simulator's truth."""
    with SimPX4(cfg, px4_params={"MPC_TKO_SPEED": 0.5}) as sim:
        async def body() -> None:
            async with await connected_link(sim, cfg) as link:
                await link.hover_thrust(timeout=3.0)
                await link.arm()
                with pytest.raises(TakeoffFailed) as e:
                    await link.takeoff(6.0, timeout=4.0)
                msg = str(e.value)
                assert msg.startswith("takeoff to 6.0 m not finished (waited 4.0 s; mode TAKEOFF"), msg
                m = re.search(r"; (-?\d+\.\d) m above the arming point by the barometer$", msg)
                assert m is not None, msg
                # 0.5 m/s from the command (the 4 s count from PX4's TAKEOFF): off the ground, far from 6 m
                assert 0.3 < float(m[1]) < 4.5, msg
                assert float(m[1]) == pytest.approx(sim.truth().p[2], abs=0.6), (msg, sim.truth().p)

        run(body, 50)


@pytest.mark.timeout(90)
def test_offboard_attitude_setpoints_fly_as_commanded(sim: SimPX4, cfg: Config) -> None:
    async def body() -> None:
        async with await flying_link(sim, cfg) as link:
            for roll, pitch, yaw in ((8.0, -6.0, 40.0), (-5.0, 4.0, -20.0)):
                sp = setpoint(link, roll, pitch, yaw)
                if not link.offboard_active:
                    await link.start_offboard(sp)
                    assert sim.mode == "OFFBOARD"
                v_start = None
                for i in range(45):  # 1.5 s at 30 Hz, as the control loop would
                    await link.set_setpoint(sp)
                    await asyncio.sleep(1 / 30)
                    if i == 10:  # attitude settled (tau 0.15 s): from here the tilt accelerates it
                        v_start = link.position_for_log.velocity_ned[:2].copy()
                # Truth ENU/FLU -> NED/FRD by hand (swap x/y and flip z; flip body y/z), then scipy's ZYX Euler.
                P, F = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1.0]]), np.diag([1.0, -1.0, -1.0])
                R_true = P @ Rotation.from_quat(sim.truth().q).as_matrix() @ F
                y, p, r = Rotation.from_matrix(R_true).as_euler("ZYX", degrees=True)
                assert (r, p, y) == pytest.approx((roll, pitch, yaw), abs=1.5)
                # The vehicle accelerates where the tilt points the thrust (NED, built here with scipy, not frames.py):
                # thrust axis = -z_body; its horizontal part is the direction of the horizontal acceleration.
                thrust_dir = -Rotation.from_euler("ZYX", [yaw, pitch, roll], degrees=True).apply([0, 0, 1.0])
                a_dir = thrust_dir[:2] / np.linalg.norm(thrust_dir[:2])
                dv = link.position_for_log.velocity_ned[:2] - v_start
                cos_angle = float(np.dot(dv, a_dir) / np.linalg.norm(dv))
                assert cos_angle > math.cos(math.radians(20.0))
                assert link.position_for_log.position_ned[2] == pytest.approx(-sim.truth().p[2], abs=0.2)
            await link.stop_offboard()
            assert sim.mode == "HOLD" and link.flight_mode == "HOLD"
            assert not link.offboard_active

    run(body, 80)


@pytest.mark.timeout(60)
def test_deny_arming_raises_arm_denied(sim: SimPX4, cfg: Config) -> None:
    sim.deny_arming = True

    async def body() -> None:
        async with await connected_link(sim, cfg) as link:
            with pytest.raises(ArmDenied, match="arm refused by the autopilot: COMMAND_DENIED"):
                await link.arm()
            assert not sim.armed

    run(body)


@pytest.mark.timeout(60)
def test_deny_offboard_raises_offboard_denied(sim: SimPX4, cfg: Config) -> None:
    async def body() -> None:
        async with await flying_link(sim, cfg) as link:
            sim.deny_offboard = True
            with pytest.raises(OffboardDenied, match="offboard refused: COMMAND_DENIED"):
                await link.start_offboard(setpoint(link))
            assert sim.mode == "HOLD" and not link.offboard_active
            with pytest.raises(OffboardLost):
                await link.set_setpoint(setpoint(link))

    run(body, 50)


@pytest.mark.timeout(60)
def test_silenced_autopilot_gives_command_timeout_and_close_does_not_hang(sim: SimPX4, cfg: Config) -> None:
    async def body() -> None:
        link = await connected_link(sim, cfg)
        sim.silence_commands(True)
        with pytest.raises(CommandTimeout, match="arm: no answer from the autopilot"):
            await link.arm(timeout=8.0)
        assert not sim.armed and sim.wait_event("silenced:400", 1.0) is not None
        # A command still waiting for its ACK while we close: close() lets it time out, then destroys.
        pending = asyncio.create_task(link.hold(timeout=8.0))
        await asyncio.sleep(0.1)
        await link.close()
        assert not link._inflight
        assert link.events[-1][1:] == ("closed", {})
        with pytest.raises(CommandTimeout):
            await pending

    run(body, 50)


@pytest.mark.timeout(60)
def test_drop_link_fires_failsafe_and_link_lost(sim: SimPX4, cfg: Config) -> None:
    async def body() -> None:
        async with await flying_link(sim, cfg) as link:
            sp = setpoint(link)
            await link.start_offboard(sp)

            async def control_loop() -> Exception:
                while True:  # 30 Hz fresh setpoints until the link says stop
                    try:
                        await link.set_setpoint(sp)
                    except Exception as e:
                        return e
                    await asyncio.sleep(1 / 30)

            loop = asyncio.create_task(control_loop())
            await asyncio.sleep(0.3)
            sim.drop_link(True)
            # The vehicle stops hearing setpoints (MAVSDK's resends are lost too): PX4's failsafe -> HOLD.
            ev = await asyncio.to_thread(sim.wait_event, "failsafe:offboard_loss", 5.0)
            assert ev is not None
            t_sp = sim.last_setpoint()[0]
            assert ev[0] - t_sp >= sim.param("COM_OF_LOSS_T") - 1e-9
            # The app side notices the silence: the control loop gets LinkLost.
            err = await asyncio.wait_for(loop, cfg.link.link_lost_timeout + 3.0)
            assert isinstance(err, LinkLost) and "vehicle link lost: no telemetry" in str(err)
            assert not link.link_ok
            sim.drop_link(False)
            await link.wait_link_ok(5.0)
            # PX4's default (COM_OBL_RC_ACT 0, no RC): the fallback shows POSCTL, descends and lands.
            assert any(e == "mode:POSCTL:failsafe" for _, e in sim.events)
            with pytest.raises(OffboardLost):  # and the app never goes back to OFFBOARD by itself
                await link.set_setpoint(sp)
            await link._wait_until(lambda: link.armed is False, 20.0, "auto-disarm after the fallback landing")
            assert sim.landed and not sim.armed
            # PX4 1.15 then shows Offboard again, disarmed, and refuses to arm until another mode is set.
            await link.wait_mode("OFFBOARD", 3.0)
            with pytest.raises(ArmDenied, match="Resolve system health failures first"):
                await link.arm(timeout=3.0)
            await link.hold()
            await link._wait_until(lambda: not link._health_problems(), 5.0, "pre-flight checks pass again")
            assert [e for e in link.events if e[1] == "link_lost"]
            assert [e for e in link.events if e[1] == "link_restored"]

    run(body, 50)


@pytest.mark.timeout(60)
def test_pilot_takeover_is_seen_and_never_overridden(sim: SimPX4, cfg: Config) -> None:
    async def body() -> None:
        async with await flying_link(sim, cfg) as link:
            sp = setpoint(link, pitch=-5.0)
            await link.start_offboard(sp)
            for _ in range(10):
                await link.set_setpoint(sp)
                await asyncio.sleep(1 / 30)
            sim.pilot_takeover("POSCTL")
            # The control loop goes on (PX4 shows the change in its next 1 Hz heartbeat) until the link refuses.
            with pytest.raises(OffboardLost, match="now POSCTL"):
                for _ in range(60):
                    await link.set_setpoint(sp)
                    await asyncio.sleep(1 / 30)
            assert link.flight_mode == "POSCTL"
            await link.stop_offboard()  # must not command HOLD over the pilot
            await asyncio.sleep(1.0)
            assert sim.mode == "POSCTL"
            t_takeover = next(t for t, what in sim.events if what == "mode:POSCTL:pilot")
            assert not [w for t, w in sim.events if t > t_takeover and w.startswith("mode:")]
            assert [e for e in link.events if e[1] == "offboard_lost"]
            assert np.linalg.norm(sim.truth().v) < 3.0  # POSCTL brakes and holds

    run(body, 50)


@pytest.mark.timeout(60)
def test_watchdog_hands_over_to_hold_when_setpoints_stop(sim: SimPX4, cfg: Config) -> None:
    async def body() -> None:
        async with await flying_link(sim, cfg) as link:
            await link.start_offboard(setpoint(link))
            n0 = sim.setpoint_count
            # The control loop goes quiet. MAVSDK alone would keep resending, and PX4's failsafe would never
            # fire; the link's watchdog stops offboard instead.
            await link.wait_mode("HOLD", cfg.safety.perception_stall_timeout + 3.0)
            assert sim.wait_event("mode:HOLD:command", 1.0) is not None
            assert sim.wait_event("failsafe:offboard_loss", 0.0) is None
            assert sim.setpoint_count > n0  # setpoints kept flowing without fresh control output
            assert [e for e in link.events if e[1] == "watchdog"]
            with pytest.raises(OffboardLost, match="setpoint watchdog"):
                await link.set_setpoint(setpoint(link))

    run(body, 50)


@pytest.mark.timeout(30)
def test_bad_setpoints_and_urls_are_one_line_errors(sim: SimPX4, cfg: Config) -> None:
    async def body() -> None:
        async with await connected_link(sim, cfg) as link:
            with pytest.raises(ValueError, match="non-finite value refused"):
                await link.start_offboard(setpoint(link, thrust=math.nan))
            with pytest.raises(ValueError, match="need roll_deg, pitch_deg, yaw_deg, thrust"):
                await link.set_setpoint(object())
        bad = VehicleLink.from_config(cfg)
        from companion.app.linkerrors import ConnectFailed

        with pytest.raises(ConnectFailed, match=r"no autopilot heard on udpin://127\.0\.0\.1:9 within 0\.5 s"):
            await bad.connect("udpin://127.0.0.1:9", timeout=0.5)
        await bad.close()
        exposed = VehicleLink.from_config(cfg)
        with pytest.raises(ConnectFailed, match=r"refused, the URL makes mavsdk bind 0\.0\.0\.0"):
            await exposed.connect("udpout://127.0.0.1:9", timeout=0.5)
        await exposed.close()

    run(body, 25)


@pytest.mark.timeout(60)
def test_loop_guard_hands_over_when_the_event_loop_stalls(sim: SimPX4, cfg: Config) -> None:
    """Sync code blocks the event loop: no asyncio watchdog can run, MAVSDK keeps resending the last
    setpoint (so PX4's own failsafe never fires), and the link's guard thread must stop offboard."""
    import time

    async def body() -> None:
        async with await flying_link(sim, cfg) as link:
            await link.start_offboard(setpoint(link))
            t_stall = sim.time
            time.sleep(2.0 * cfg.safety.perception_stall_timeout + 1.5)  # the whole loop is stuck here
            ev = sim.wait_event("mode:HOLD:command", 0.0, since=t_stall)
            assert ev is not None  # it happened while the loop was still blocked
            assert sim.wait_event("failsafe:offboard_loss", 0.0) is None
            await asyncio.sleep(0.1)  # the guard's report reaches the loop
            assert [e for e in link.events if e[1] == "loop_guard"]
            with pytest.raises(OffboardLost, match="loop guard"):
                await link.set_setpoint(setpoint(link))

    run(body, 50)


@pytest.mark.timeout(60)
def test_loop_guard_covers_a_stall_while_the_switch_to_offboard_is_pending(sim: SimPX4, cfg: Config) -> None:
    """The loop stalls after the first setpoint went out but before PX4's 1 Hz heartbeat confirmed OFFBOARD:
    MAVSDK already resends that setpoint and PX4 flies it, so the guard must watch from the first setpoint on."""
    import time

    async def body() -> None:
        async with await flying_link(sim, cfg) as link:
            start = asyncio.create_task(link.start_offboard(setpoint(link)))
            for _ in range(250):  # the loop must run for the switch to go out
                if sim.wait_event("mode:OFFBOARD:command", 0.0) is not None:
                    break
                await asyncio.sleep(0.02)
            assert sim.wait_event("mode:OFFBOARD:command", 0.0) is not None  # the switch is under way
            assert not start.done()  # ... and not confirmed yet (the heartbeat comes at 1 Hz)
            t_stall = sim.time
            time.sleep(2.0 * cfg.safety.perception_stall_timeout + 1.5)  # the whole loop is stuck here
            assert sim.wait_event("mode:HOLD:command", 0.0, since=t_stall) is not None  # while still blocked
            with pytest.raises(OffboardLost, match="loop guard"):
                await start
            kinds = [e[1] for e in link.events]
            assert "loop_guard" in kinds and "offboard_started" not in kinds
            assert sim.mode == "HOLD"

    run(body, 50)


@pytest.mark.timeout(30)
def test_failed_preflight_gives_not_healthy_naming_the_check(sim: SimPX4, cfg: Config) -> None:
    from companion.app.linkerrors import NotHealthy

    sim.fail_preflight = True

    async def body() -> None:
        link = VehicleLink.from_config(cfg)
        try:
            await link.connect(sim.url_for_mavsdk, timeout=5.0)
            with pytest.raises(NotHealthy, match=r"not ready after 2\.0 s: armable \(preflight checks\)$"):
                await link.wait_healthy(timeout=2.0)
            with pytest.raises(ArmDenied, match="COMMAND_DENIED"):
                await link.arm()
            sim.fail_preflight = False
            await link.wait_healthy(timeout=5.0)
        finally:
            await link.close()

    run(body, 25)


@pytest.mark.timeout(30)
def test_unusable_url_is_connect_failed(cfg: Config) -> None:
    from companion.app.linkerrors import ConnectFailed

    async def body() -> None:
        link = VehicleLink.from_config(cfg)
        with pytest.raises(ConnectFailed, match="cannot open connection 'udpin://localhost:14599'"):
            await link.connect("udpin://localhost:14599", timeout=1.0)
        await link.close()

    run(body, 20)


@pytest.mark.timeout(30)
def test_listening_mavsdk_finds_a_sim_that_sends_to_it(cfg: Config) -> None:
    """The default link.url is udpin:// (mavsdk listens, as for PX4 SITL): remote_port makes the sim send there."""
    from companion.netports import free_udp_port

    listen_port = free_udp_port()  # for mavsdk to bind
    with SimPX4(cfg, remote_port=listen_port) as sim:
        async def body() -> None:
            async with VehicleLink.from_config(cfg) as link:
                await link.connect(f"udpin://127.0.0.1:{listen_port}", timeout=5.0)
                await link.wait_healthy(timeout=10.0)
                assert await link.hover_thrust() == pytest.approx(sim.param("MPC_THR_HOVER"), abs=1e-6)

        run(body, 25)


def test_attitude_history_interpolates_like_slerp() -> None:
    """Frames are paired with the attitude at their capture time; checked against scipy's Slerp."""
    from scipy.spatial.transform import Rotation, Slerp

    from companion.app.telemetry import AttitudeHistory

    rots = Rotation.from_euler("ZYX", [[0, 0, 0], [3, -2, 1], [5, -4, 3], [6, -5, 2]], degrees=True)
    ts = [10.0, 10.02, 10.04, 10.06]
    hist = AttitudeHistory()
    for t, r in zip(ts, rots, strict=True):
        x, y, z, w = r.as_quat()
        hist.add(t, (-1.0 if t == 10.04 else 1.0) * np.array([w, x, y, z]))  # a sign flip must not matter
    hist.add(10.05, np.array([1.0, 0.0, 0.0, 0.0]))  # out of order: ignored
    ref = Slerp(ts, rots)
    for t in (10.0, 10.01, 10.033, 10.05, 10.06):
        q = hist.at(t)
        got = Rotation.from_quat([q[1], q[2], q[3], q[0]])
        assert (got * ref(t).inv()).magnitude() < 1e-5
    first = hist.at(9.0)
    assert np.allclose(first, [1.0, 0.0, 0.0, 0.0])  # before the span: the first sample
    x, y, z, w = rots[-1].as_quat()
    assert np.allclose(hist.at(11.0), [w, x, y, z])  # after the span: the newest
    assert AttitudeHistory().at(1.0) is None
