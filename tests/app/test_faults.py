"""Fault flights through the real mavsdk over UDP: each ends in its named safe state, with its reason
in the log and as the exit code, and the log intact up to the fault."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from flighthelpers import make_config, run_flight, wait_state

from companion.app.states import Reason
from companion.flightlog import read_flight

pytestmark = pytest.mark.timeout(120)


def _end(folder):
    f = read_flight(folder)
    last = f.states[-1]
    return f, last["to_state"], last["reason"]


def _check_log_intact(f, until_state: str) -> None:
    """Every topic readable; telemetry and setpoints cover the flight up to the fault."""
    t_fault = next(float(r["t"]) for r in f.states if r["to_state"] == until_state)
    tel = f["telemetry"]
    assert len(tel) > 10 and tel["t"].max() >= t_fault - 0.2
    assert all(t.truncated_rows == 0 for t in f.tables.values())
    assert f.summary["exit_code"] == Reason[f.summary["reason"]].value


def test_arm_denied(sim, tmp_path):
    sim.deny_arming = True
    reason, folder, _ = run_flight(make_config(tmp_path, sim.url_for_mavsdk))
    f, end, why = _end(folder)
    assert reason is Reason.ARM_DENIED and end == "ABORT_NOT_ARMED"
    assert f.state_path() == ["CONNECT", "PREFLIGHT", "ARM", "ABORT_NOT_ARMED"]
    assert "arm" in why.lower() and f.summary["exit_code"] == 17
    assert not sim.armed and any(e.startswith("arm_denied") for _, e in sim.events)


def test_command_timeout_on_arm(sim, tmp_path):
    sim.silence_commands(True)
    reason, folder, _ = run_flight(make_config(tmp_path, sim.url_for_mavsdk, "link.command_timeout=1.5"))
    f, end, why = _end(folder)
    assert reason is Reason.COMMAND_TIMEOUT and end == "ABORT_NOT_ARMED", why
    assert f.state_path()[-2:] == ["ARM", "ABORT_NOT_ARMED"]
    assert "no answer" in why and not sim.armed


def test_offboard_denied(sim, tmp_path):
    sim.deny_offboard = True
    reason, folder, _ = run_flight(make_config(tmp_path, sim.url_for_mavsdk))
    f, end, why = _end(folder)
    assert reason is Reason.OFFBOARD_DENIED and end == "SAFE_HOLD", why
    assert f.state_path()[-3:] == ["ENGAGE", "HANDBACK", "SAFE_HOLD"]
    assert sim.mode == "HOLD" and sim.armed and not sim.landed
    assert any(e.startswith("offboard_denied") for _, e in sim.events)
    _check_log_intact(f, "HANDBACK")


def _after_engage(action, delay: float = 1.0):
    async def side(app) -> None:
        await wait_state(app, "ENGAGE")
        await asyncio.sleep(delay)
        action()

    return side


def test_link_loss_mid_flight(sim, tmp_path):
    reason, folder, _ = run_flight(make_config(tmp_path, sim.url_for_mavsdk),
                                   _after_engage(lambda: sim.drop_link(True)))
    f, end, why = _end(folder)
    assert reason is Reason.LINK_LOST and end == "SAFE_FAILSAFE_LINK", why
    assert f.state_path()[-2:] == ["ENGAGE", "SAFE_FAILSAFE_LINK"]
    # PX4's own offboard-loss failsafe took over (we stopped streaming; nothing reached it anyway).
    assert sim.wait_event("failsafe:offboard_loss", timeout=5.0) is not None
    _check_log_intact(f, "SAFE_FAILSAFE_LINK")


def test_pilot_takeover_mid_engagement(sim, tmp_path):
    reason, folder, _ = run_flight(make_config(tmp_path, sim.url_for_mavsdk),
                                   _after_engage(lambda: sim.pilot_takeover("POSCTL")))
    f, end, why = _end(folder)
    assert reason is Reason.PILOT_TAKEOVER and end == "SAFE_PILOT", why
    assert "POSCTL" in why
    # We stopped commanding: the pilot's mode stands, no mode command of ours after the takeover.
    ev = [e for _, e in sim.events]
    i = next(i for i, e in enumerate(ev) if e.startswith("mode:POSCTL"))
    assert not [e for e in ev[i + 1:] if e.startswith("mode:")], ev[i:]
    assert sim.mode == "POSCTL"
    n0 = sim.setpoint_count
    import time

    time.sleep(0.5)
    assert sim.setpoint_count == n0  # mavsdk is gone: no resends either
    _check_log_intact(f, "SAFE_PILOT")


@pytest.mark.parametrize(
    ("fault", "reason", "text"),
    [
        ("stall", Reason.PERCEPTION_STALL, "no fresh setpoint"),
        ("lose_target", Reason.TARGET_LOST, "no usable box"),
        ("nan_box", Reason.TARGET_LOST, "no usable box"),
    ],
)
def test_perception_faults_hand_over_to_hold(sim, tmp_path, fault, reason, text):
    cfg = make_config(tmp_path, sim.url_for_mavsdk, f"app.synthetic.fault={fault}", "app.synthetic.fault_after=1.5")
    got, folder, _ = run_flight(cfg)
    f, end, why = _end(folder)
    assert got is reason and end == "SAFE_HOLD", why
    assert f.state_path()[-3:] == ["ENGAGE", "HANDBACK", "SAFE_HOLD"]
    hb = next(r["reason"] for r in f.states if r["to_state"] == "HANDBACK")
    assert text in hb
    assert sim.mode == "HOLD" and sim.armed
    sp = f["setpoints"]
    for c in ("roll_deg", "pitch_deg", "yaw_deg", "thrust"):
        assert np.isfinite(sp[c]).all()  # a NaN box never becomes a NaN setpoint
    if fault == "nan_box":
        rej = [r for r in f["los"]["rejected"] if isinstance(r, str) and r.startswith("invalid box")]
        assert len(rej) >= 10
        assert any("nan" in r for r in rej) and any("-40" in r for r in rej) and any("5000" in r for r in rej)
        assert (f["detections"]["valid"] == 0).sum() >= len(rej)
    if fault == "stall":
        # The camera stopped: the last detection is >= stall timeout before the hand-over.
        t_hb = next(float(r["t"]) for r in f.states if r["to_state"] == "HANDBACK")
        assert t_hb - f["detections"]["t"].max() >= cfg.safety.perception_stall_timeout - 0.05
    _check_log_intact(f, "HANDBACK")


def test_los_jump_is_rejected_and_the_flight_goes_on(sim, tmp_path):
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.synthetic.fault=los_jump", "app.synthetic.fault_after=1.5")
    reason, folder, _ = run_flight(cfg)
    f, end, why = _end(folder)
    assert reason is Reason.OK and end == "SAFE_LANDED", why
    assert "PASS" in f.state_path()
    t_pass = next(float(r["t"]) for r in f.states if r["to_state"] == "PASS")
    # The two injected frames (the box on the far side of the image, back to back) never reached the controller:
    # the target lock (companion/targetlock.py) rejected them as another object, one event for the spell.
    det = f["detections"]
    ok = det["valid"] == 1
    t_det, cx = det["t_frame"][ok], det["cx"][ok]
    jumped = [i for i in range(5, len(cx)) if t_det[i] < t_pass - 0.5 and abs(cx[i] - np.median(cx[i - 5:i])) > 150]
    assert len(jumped) == 2 and t_det[jumped[1]] - t_det[jumped[0]] < 0.1, jumped
    ev = f["events"]
    rej = [(t, x) for t, x in zip(ev["t"], ev["text"], strict=True) if "box rejected" in str(x) and t < t_pass - 0.5]
    assert len(rej) == 1 and "not the engaged gate: line of sight" in rej[0][1], rej
    los = f["los"]
    for i in jumped:
        k = int(np.argmin(np.abs(los["t_frame"] - t_det[i])))
        assert los["rejected"][k] == "no box", (t_det[i], los["rejected"][k])
    # The LOS filter saw no jump away from the gate (near it, a box cut by the image border may jump).
    jumps = [t for t, r in zip(los["t"], los["rejected"], strict=True)
             if isinstance(r, str) and r.startswith("LOS jump") and t < t_pass - 0.5]
    assert jumps == []


def test_altitude_floor(sim, tmp_path):
    # Floor above the take-off altitude: the first engaged frame is already below it.
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "safety.altitude_floor=7")
    reason, folder, _ = run_flight(cfg)
    f, end, why = _end(folder)
    assert reason is Reason.ALTITUDE_FLOOR and end == "SAFE_HOLD", why
    assert "below the floor 7.0 m" in why
    assert sim.mode == "HOLD"
    # Independent check: the truth the sim logged says the vehicle really was below 7 m at the abort.
    t_hb = next(float(r["t"]) for r in f.states if r["to_state"] == "HANDBACK")
    tr = f["truth"]
    assert -tr["d"][np.searchsorted(tr["t"], t_hb) - 1] < 7.0


def test_exception_in_perception(sim, tmp_path):
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.synthetic.fault=exception", "app.synthetic.fault_after=1.5")
    reason, folder, _ = run_flight(cfg)
    f, end, why = _end(folder)
    assert reason is Reason.EXCEPTION and end == "SAFE_HOLD", why
    assert "RuntimeError: injected perception failure" in why
    assert f.state_path()[-3:] == ["ENGAGE", "HANDBACK", "SAFE_HOLD"]
    assert sim.mode == "HOLD"
    _check_log_intact(f, "HANDBACK")


def test_max_engagement_time(sim, tmp_path):
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "safety.max_engagement_time=1.0")
    reason, folder, _ = run_flight(cfg)
    f, end, why = _end(folder)
    assert reason is Reason.MAX_ENGAGEMENT and end == "SAFE_HOLD", why
    t_hb = next(float(r["t"]) for r in f.states if r["to_state"] == "HANDBACK")
    # The limit runs on the engagement's clock, the frames' capture times (the state log's times add each
    # frame's processing latency, a few ms that differ between the two frames): from the frame that engaged
    # to the last frame perceived before the hand-back.
    sp = f["setpoints"]
    t_engaged = float(sp["t_frame"][np.asarray(sp["state"]) == "ENGAGE"].min())
    det = f["detections"]
    t_last = float(det["t_frame"][det["t"] <= t_hb].max())
    assert 1.0 < t_last - t_engaged <= 1.5
    assert sim.mode == "HOLD"


def test_no_autopilot_is_connect_failed(tmp_path):
    import socket

    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))  # a free port: nobody sends MAVLink there
    port = s.getsockname()[1]
    s.close()
    try:
        cfg = make_config(tmp_path, f"udpin://127.0.0.1:{port}", "link.connect_timeout=2")
        reason, folder, _ = run_flight(cfg)
    finally:
        s.close()
    f, end, why = _end(folder)
    assert reason is Reason.CONNECT_FAILED and end == "ABORT_NOT_ARMED", why
    assert f.state_path() == ["CONNECT", "ABORT_NOT_ARMED"] and "no autopilot" in why


def test_no_target_in_view_lands(sim, tmp_path):
    # The virtual gate is 60 m to the side: never in view. Nothing to engage -> land where we are.
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.synthetic.lateral_offset=60", "app.acquire_timeout=1.5")
    reason, folder, _ = run_flight(cfg)
    f, end, why = _end(folder)
    assert reason is Reason.NO_TARGET and end == "SAFE_LANDED", why
    assert f.state_path()[-4:] == ["TAKEOFF", "ACQUIRE", "LAND", "SAFE_LANDED"]
    assert "no stable track within 1.5 s" in f.states[-2]["reason"]
    assert (f["detections"]["valid"] == 0).all() and len(f["setpoints"]) == 0
    assert not sim.armed and sim.landed


def test_handover_unanswered_falls_back_to_px4_failsafe(sim, tmp_path):
    """Target lost, but PX4 answers no command: stop streaming so PX4's own offboard-loss failsafe acts."""
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.synthetic.fault=lose_target",
                      "app.synthetic.fault_after=1.5", "link.command_timeout=1.0")

    async def silence(app) -> None:
        await wait_state(app, "ENGAGE")
        await asyncio.sleep(1.0)
        sim.silence_commands(True)

    reason, folder, _ = run_flight(cfg, silence)
    f, end, why = _end(folder)
    assert reason is Reason.TARGET_LOST and end == "SAFE_FAILSAFE_LINK", why
    assert "offboard stop failed" in why and "no answer" in why
    assert f.state_path()[-3:] == ["ENGAGE", "HANDBACK", "SAFE_FAILSAFE_LINK"]
    assert sim.wait_event("failsafe:offboard_loss", timeout=5.0) is not None
    # PX4's default (COM_OBL_RC_ACT 0, no RC): Position-mode fallback, which descends and lands.
    assert sim.wait_event("mode:POSCTL:failsafe", timeout=5.0) is not None


def test_land_after_abort(sim, tmp_path):
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.synthetic.fault=lose_target", "app.synthetic.fault_after=1.0",
                      "safety.land_after_abort=true")
    reason, folder, _ = run_flight(cfg)
    f, end, why = _end(folder)
    assert reason is Reason.TARGET_LOST and end == "SAFE_LANDED", why
    assert f.state_path()[-4:] == ["ENGAGE", "HANDBACK", "LAND", "SAFE_LANDED"]
    assert f.summary["exit_code"] == Reason.TARGET_LOST.value  # landed safely, but the flight failed
    assert not sim.armed and sim.landed


# --------------------------------------------------------------- every named state true (issue 10 part 4)
def _in_state(state: str, action, delay: float = 0.0):
    async def side(app) -> None:
        await wait_state(app, state)
        await asyncio.sleep(delay)
        action(app)

    return side


def test_pilot_takeover_during_takeoff_is_safe_pilot(sim, tmp_path):
    async def side(app) -> None:
        # In PX4's TAKEOFF (not before the take-off command, which would take the vehicle back from the pilot).
        ev = await asyncio.get_running_loop().run_in_executor(None, sim.wait_event, "mode:TAKEOFF", 30.0)
        assert ev is not None
        await asyncio.sleep(0.5)
        sim.pilot_takeover("POSCTL")

    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.takeoff_altitude=8")
    reason, folder, _ = run_flight(cfg, side)
    f, end, why = _end(folder)
    assert reason is Reason.PILOT_TAKEOVER and end == "SAFE_PILOT", why
    assert f.summary["exit_code"] == 15
    assert "flight mode changed to POSCTL during TAKEOFF" in why and "the pilot has the vehicle in POSCTL" in why
    assert f.state_path()[-2:] == ["TAKEOFF", "SAFE_PILOT"]
    ev = [e for _, e in sim.events]
    i = ev.index("mode:POSCTL:pilot")
    assert not [e for e in ev[i + 1:] if e.startswith(("mode:", "command:"))], ev[i:]  # we commanded nothing more
    assert sim.mode == "POSCTL"


def test_pilot_takeover_during_land_is_noticed(sim, tmp_path):
    # Nothing to engage (gate 60 m to the side): the app lands; the pilot takes over during its landing.
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.synthetic.lateral_offset=60", "app.acquire_timeout=1.5")
    reason, folder, _ = run_flight(cfg, _in_state("LAND", lambda app: sim.pilot_takeover("POSCTL"), 1.5))
    f, end, why = _end(folder)
    assert reason is Reason.PILOT_TAKEOVER and end == "SAFE_PILOT", why
    assert "flight mode changed to POSCTL during LAND" in why
    t_pilot = next(t for t, e in sim.events if e == "mode:POSCTL:pilot")
    t_end = float(f.states[-1]["t"])
    t_land = float(next(r["t"] for r in f.states if r["to_state"] == "LAND"))
    # Noticed within PX4's 1 Hz heartbeat + 0.5 s, not at the landing timeout (60 s).
    sim_to_log = t_land - next(t for t, e in sim.events if e == "land")
    assert t_end - (t_pilot + sim_to_log) < 2.5
    assert sim.armed and not sim.landed and sim.mode == "POSCTL"


def test_forced_disarm_during_engage_is_noticed(sim, tmp_path):
    reason, folder, _ = run_flight(make_config(tmp_path, sim.url_for_mavsdk),
                                   _in_state("ENGAGE", lambda app: sim.force_disarm(), 0.8))
    f, end, why = _end(folder)
    assert reason is Reason.DISARMED and end == "DISARMED", why
    assert f.summary["exit_code"] == 28 and "vehicle disarmed during ENGAGE" in why
    assert "PX4 holds" not in why
    t_kill = next(t for t, e in sim.events if e == "disarm:force")
    # Setpoints stop: no setpoint reaches PX4 more than 2 s (heartbeat + monitor) after the disarm.
    assert sim.last_setpoint()[0] - t_kill < 2.0
    _check_log_intact(f, "DISARMED")


def test_sigint_during_takeoff_commands_and_confirms_hold(sim, tmp_path):
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.takeoff_altitude=8")
    reason, folder, _ = run_flight(cfg, _in_state("TAKEOFF", lambda app: app.trip(Reason.SIGNAL, "SIGINT received"),
                                                  1.5))
    _f, end, why = _end(folder)
    assert reason is Reason.SIGNAL and end == "SAFE_HOLD", why
    assert why == "SIGINT received; PX4 holds"
    ev = [e for _, e in sim.events]
    assert "mode:HOLD:command" in ev and "mode:HOLD:takeoff_done" not in ev  # our Hold, before the top
    assert sim.mode == "HOLD" and sim.truth().p[2] < 7.5


def test_silenced_commands_never_claim_hold(sim, tmp_path):
    """Abort in TAKEOFF while PX4 answers nothing: Hold is commanded but not seen; the state says what is."""
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.takeoff_altitude=8", "link.command_timeout=1.0")

    def silence_then_abort(app) -> None:
        sim.silence_commands(True)
        app.trip(Reason.SIGNAL, "SIGINT received")

    reason, folder, _ = run_flight(cfg, _in_state("TAKEOFF", silence_then_abort, 1.0))
    _f, end, why = _end(folder)
    assert reason is Reason.SIGNAL and end == "AUTOPILOT", why
    assert "PX4 holds" not in why and "Hold not confirmed" in why and "PX4 flies in TAKEOFF" in why
    assert any(e.startswith("silenced:176") for _, e in sim.events)  # our DO_SET_MODE(HOLD) went unanswered


def test_start_while_airborne_is_refused(tmp_path):
    from companion.config import load_config
    from companion.sim.dynamics import QuadState
    from companion.sim.px4 import SimPX4

    cfg0 = load_config([], ["sim.seed=7"])
    s0 = QuadState(p=np.array([0.0, 0.0, 6.0]), on_ground=False, f_th=9.81)  # hovering at 6 m, armed
    with SimPX4(cfg0, initial_state=s0) as sim:
        reason, folder, _ = run_flight(make_config(tmp_path, sim.url_for_mavsdk))
        f, end, why = _end(folder)
        assert reason is Reason.VEHICLE_BUSY and end == "REFUSED", why
        assert f.summary["exit_code"] == 26
        assert "vehicle found armed, landed state IN_AIR, mode HOLD: refusing to arm or take off" in why
        assert f.state_path() == ["CONNECT", "PREFLIGHT", "REFUSED"]
        flight_cmds = ("command:400", "command:22", "command:176", "command:21")  # arm, take-off, mode, land
        assert not [e for _, e in sim.events if e.startswith(flight_cmds)]  # not one flight command sent
        assert sim.armed and sim.mode == "HOLD"


def test_unsafe_offboard_loss_failsafe_is_refused_before_arming(tmp_path):
    from companion.config import load_config
    from companion.sim.px4 import SimPX4

    with SimPX4(load_config([], ["sim.seed=7"]), px4_params={"COM_OBL_RC_ACT": 7}) as sim:
        reason, folder, _ = run_flight(make_config(tmp_path, sim.url_for_mavsdk))
        f, end, why = _end(folder)
        assert reason is Reason.UNSAFE_FAILSAFE and end == "ABORT_NOT_ARMED", why
        assert f.summary["exit_code"] == 27
        assert "COM_OBL_RC_ACT = 7 (Disarm) is not a safe end" in why
        assert not sim.armed and "arm" not in [e for _, e in sim.events]
        assert any("PX4 failsafe if the app dies" in str(t) for t in f["events"]["text"])


def test_vehicle_found_disarmed_in_offboard_is_put_in_hold_first(sim, tmp_path):
    """After PX4's offboard-loss fallback landing the vehicle sits disarmed in OFFBOARD and fails pre-flight."""
    sim.set_param("COM_DISARM_PRFLT", 2.0)  # after the offboard loss (1 s), as on the ground in PX4
    gcs = _raw_gcs(sim)
    try:
        gcs.command(400, 1.0)  # arm
        for _ in range(5):
            gcs.attitude_setpoint([1.0, 0.0, 0.0, 0.0], 0.2)
        gcs.command(176, 1.0, 6.0)  # OFFBOARD; then the setpoints stop: failsafe, fallback, disarm
        assert sim.wait_event("mode:OFFBOARD:offboard_loss_landed", 10.0) is not None
    finally:
        gcs.close()
    sim.set_param("COM_DISARM_PRFLT", 10.0)
    assert sim.mode == "OFFBOARD" and not sim.armed
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.synthetic.lateral_offset=60", "app.acquire_timeout=1.0")
    reason, folder, _ = run_flight(cfg)
    f, end, why = _end(folder)
    assert reason is Reason.NO_TARGET and end == "SAFE_LANDED", why  # it flew: pre-flight passed after HOLD
    texts = [str(t) for t in f["events"]["text"]]
    assert any("found disarmed in OFFBOARD" in t for t in texts) and any("HOLD confirmed" in t for t in texts)


def _raw_gcs(sim):
    import socket as _socket

    from pymavlink.dialects.v20 import common as mavlink

    class _Gcs:
        def __init__(self) -> None:
            self.sock = _socket.socket(_socket.AF_INET, _socket.SOCK_DGRAM)
            self.sock.bind(("127.0.0.1", 0))
            self.mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)

        def _send(self, msg) -> None:
            self.sock.sendto(msg.pack(self.mav), ("127.0.0.1", sim.port))
            self.mav.seq = (self.mav.seq + 1) % 256

        def command(self, cmd: int, *p: float) -> None:
            import math as _m

            params = [*p, *[_m.nan] * (7 - len(p))]
            self._send(self.mav.command_long_encode(1, 1, cmd, 0, *params))

        def attitude_setpoint(self, q, thrust: float) -> None:
            self._send(self.mav.set_attitude_target_encode(0, 1, 1, 0b111, q, 0.0, 0.0, 0.0, thrust))

        def close(self) -> None:
            self.sock.close()

    return _Gcs()


def test_nan_attitude_in_flight_is_a_named_abort(sim, tmp_path):
    """PX4's attitude turns NaN mid-engagement: it never reaches the controller; persisting, the engagement
    ends as TELEMETRY_INVALID with a confirmed hand-over (it was an EXCEPTION before)."""

    async def corrupt(app) -> None:
        await wait_state(app, "ENGAGE")
        await asyncio.sleep(0.5)
        sim.corrupt_attitude(True)

    reason, folder, _ = run_flight(make_config(tmp_path, sim.url_for_mavsdk), corrupt)
    sim.corrupt_attitude(False)
    f, end, why = _end(folder)
    assert reason is Reason.TELEMETRY_INVALID and end == "SAFE_HOLD", why
    assert f.summary["exit_code"] == 32 and "attitude samples rejected within 1 s" in why
    assert "non-finite quaternion" in why
    assert f.state_path()[-3:] == ["ENGAGE", "HANDBACK", "SAFE_HOLD"]
    tel = f["telemetry"]
    assert np.isfinite(tel["qw"].astype(float)).all()
    sp = f["setpoints"]
    assert all(np.isfinite(sp[c]).all() for c in ("roll_deg", "pitch_deg", "yaw_deg", "thrust"))
    assert sim.mode == "HOLD"


def test_abort_during_land_commands_and_confirms_hold(sim, tmp_path):
    """SIGINT while the app lands (nothing to engage): Hold is commanded and seen before SAFE_HOLD is named."""
    cfg = make_config(tmp_path, sim.url_for_mavsdk, "app.synthetic.lateral_offset=60", "app.acquire_timeout=1.0")
    reason, folder, _ = run_flight(cfg, _in_state("LAND", lambda app: app.trip(Reason.SIGNAL, "SIGINT received"),
                                                  1.5))
    f, end, why = _end(folder)
    assert reason is Reason.SIGNAL and end == "SAFE_HOLD", why
    assert why == "SIGINT received; PX4 holds" and f.state_path()[-2:] == ["LAND", "SAFE_HOLD"]
    ev = [e for _, e in sim.events]
    assert "mode:HOLD:command" in ev[ev.index("mode:LAND:command"):]  # our Hold, after our LAND
    assert sim.mode == "HOLD" and sim.armed and not sim.landed


def test_non_finite_setpoint_never_leaves_the_app(sim, tmp_path):
    """Upstream computes a NaN roll mid-engagement: the link's envelope refuses it (nothing sent) and the
    flight ends as SETPOINT_INVALID with a confirmed hand-over."""
    import math
    from types import SimpleNamespace

    async def corrupt(app) -> None:
        await wait_state(app, "ENGAGE")
        await asyncio.sleep(0.5)
        send = app.link.set_setpoint

        async def nan_roll(sp) -> None:
            await send(SimpleNamespace(roll_deg=math.nan, pitch_deg=sp.pitch_deg, yaw_deg=sp.yaw_deg,
                                       thrust=sp.thrust))

        app.link.set_setpoint = nan_roll

    reason, folder, _ = run_flight(make_config(tmp_path, sim.url_for_mavsdk), corrupt)
    f, end, why = _end(folder)
    assert reason is Reason.SETPOINT_INVALID and end == "SAFE_HOLD", why
    assert f.summary["exit_code"] == 29 and "non-finite value refused" in why
    assert f.state_path()[-3:] == ["ENGAGE", "HANDBACK", "SAFE_HOLD"]
    assert any("envelope" in str(t) and "refused" in str(t) for t in f["events"]["text"])
    _, q, thrust = sim.last_setpoint()
    assert np.isfinite(q).all() and math.isfinite(thrust)
    assert sim.mode == "HOLD"


def test_heartbeat_from_another_system_does_not_end_the_flight(sim, tmp_path):
    """The issue's probe: a HEARTBEAT (POSCTL, armed) from another system during ENGAGE used to force
    SAFE_PILOT. Now it changes nothing: the flight passes the gate and lands (exit 0)."""
    import socket as _socket

    from pymavlink.dialects.v20 import common as mavlink

    async def spoof(app) -> None:
        await wait_state(app, "ENGAGE")
        sock = _socket.socket(_socket.AF_INET, _socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", 0))
        mav = mavlink.MAVLink(None, srcSystem=2, srcComponent=1)
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        try:
            for _ in range(40):
                msg = mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base, 3 << 16,
                                           mavlink.MAV_STATE_ACTIVE, 3)
                sock.sendto(msg.pack(mav), ("127.0.0.1", sim.remote_port))
                mav.seq = (mav.seq + 1) % 256
                await asyncio.sleep(0.05)
        finally:
            sock.close()

    reason, folder, _ = run_flight(make_config(tmp_path, sim.url_for_mavsdk), spoof)
    f, end, why = _end(folder)
    assert reason is Reason.OK and end == "SAFE_LANDED", why
    assert f.summary["exit_code"] == 0 and "PASS" in f.state_path()
    assert "POSCTL" not in set(f["telemetry"]["flight_mode"])
