"""Shadow mode computes what a flight would send, bit for bit.

The same recorded frames (boxes from the geometric camera along a flown approach, with the attitude, the
accelerometer and the barometer of each instant) go through the flight app's frame loop, whose commands a
vehicle captures, and through shadow mode's session on the read-only vehicle. Every setpoint the flight sent
must equal the setpoint shadow computed for the same frame, to the last bit.

The vehicle here replays a recording: the real link against a simulated PX4 cannot give two runs the same
attitude samples and timings, and bit-for-bit needs exactly the same inputs. Everything between the vehicle and
the setpoint is the app's own code.
"""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from companion.app.camera import Frame
from companion.app.flight import FlightApp
from companion.app.shadow import ReadOnlyLink, _Session
from companion.app.states import State
from companion.app.telemetry import AttitudeHistory, AttitudeSample, BaroSample, ImuSample
from companion.config import load_config
from companion.flightlog import FlightLog
from companion.frames import R_ned_frd_from_enu_flu, quat_wxyz_from_R
from companion.sim.camera import GeometricCamera
from perception.los import CameraModel

pytestmark = pytest.mark.timeout(120)

RATE = 30.0
GROUND_BARO = 488.0  # m above sea level: the barometer's raw reading on the ground
LATENCY = 0.004  # s from capture to processing, the same for every frame (the frame's age)


@dataclass
class Sample:
    t: float
    box: Any
    q_wxyz: np.ndarray  # NED/FRD
    accel_frd: np.ndarray
    baro_raw: float


def recording(cfg: Any, seconds: float = 5.0) -> list[Sample]:
    """An approach at 9 m/s on a gate 25 m ahead, 1.2 m to the side, with a roll wobble and a pitch that
    changes: the boxes a detector-like camera (1 px noise, clipped to the image) gives of the gate."""
    rng = np.random.default_rng(11)
    cam = GeometricCamera(CameraModel.from_config(cfg.camera), 1.0, 0.0, 2.0, rng, True)
    gate, normal = np.array([25.0, 1.2, 10.5]), np.array([-1.0, 0.0, 0.0])  # ENU
    out = []
    for k in range(int(seconds * RATE)):
        t = 100.0 + k / RATE
        tau = k / RATE
        p = np.array([9.0 * tau, 0.3 * tau, 10.0 + 0.1 * math.sin(tau)])
        roll, pitch, yaw = 4.0 * math.sin(2 * math.pi * 0.8 * tau), -8.0 + 3.0 * tau, 2.0 * math.sin(tau)
        R_enu_flu = Rotation.from_euler("ZYX", [yaw, -pitch, roll], degrees=True).as_matrix()
        box = cam.capture(t, p, R_enu_flu, gate, normal, 1.0)
        q = quat_wxyz_from_R(R_ned_frd_from_enu_flu(R_enu_flu))
        acc = np.array([0.8 * math.sin(3 * tau), 0.3 * math.cos(2 * tau), -9.81 - 0.5 * math.sin(tau)])
        out.append(Sample(t, box, q, acc, GROUND_BARO + p[2] + 0.05 * math.sin(7 * tau)))
    return out


class RecordedVehicle:
    """The vehicle as its telemetry was recorded: each frame read moves it to that frame's instant. Commands
    change the mode and arming the way PX4 answers them, and are captured."""

    def __init__(self, samples: list[Sample]) -> None:
        self.samples = samples
        self.attitude_history = AttitudeHistory()
        self.attitude: AttitudeSample | None = None
        self.imu: ImuSample | None = None
        self.baro: BaroSample | None = None
        self.flight_mode, self.armed, self.landed_state = "HOLD", True, "IN_AIR"
        self.link_ok, self.telemetry_age, self.offboard_active = True, 0.0, False
        self.sent: list[tuple[float, Any]] = []  # (frame time, setpoint) of every setpoint sent
        self.now = 0.0

    def advance(self, s: Sample) -> None:
        self.now = s.t
        self.attitude_history.add(s.t, s.q_wxyz)
        self.attitude = AttitudeSample(s.q_wxyz, s.t, s.t)
        self.imu = ImuSample(s.accel_frd, np.zeros(3), s.t, s.t)
        self.baro = BaroSample(s.baro_raw - GROUND_BARO, s.baro_raw, s.t)

    # commands (the flight's; shadow's read-only wrapper refuses them)
    async def start_offboard(self, sp: Any, timeout: float | None = None) -> None:
        self.sent.append((self.now, sp))
        self.flight_mode, self.offboard_active = "OFFBOARD", True

    async def set_setpoint(self, sp: Any) -> None:
        self.sent.append((self.now, sp))

    async def stop_offboard(self, timeout: float | None = None) -> None:
        self.flight_mode, self.offboard_active = "HOLD", False
        self.attitude = AttitudeSample(np.array([1.0, 0.0, 0.0, 0.0]), self.now, self.now)  # Hold has it level

    def check_link(self) -> None:
        pass  # a recording's link never drops

    async def land(self, timeout: float | None = None) -> None:
        self.flight_mode = "LAND"

    async def wait_landed_and_disarm(self, timeout: float | None = None) -> None:
        self.armed, self.landed_state = False, "ON_GROUND"

    async def close(self) -> None:
        pass


class RecordedCamera:
    """The recorded frames, in order, each moving the vehicle to its instant first; at the end ``on_end``."""

    def __init__(self, samples: list[Sample], vehicle: RecordedVehicle, on_end: Any = None) -> None:
        self.samples, self.vehicle, self.on_end, self.k = samples, vehicle, on_end, 0

    async def read(self) -> Frame:
        await asyncio.sleep(0)  # a real camera yields to the event loop while it waits for a frame
        if self.k >= len(self.samples):
            if self.on_end is not None:
                self.on_end()
            await asyncio.Event().wait()  # no more frames
        s = self.samples[self.k]
        self.vehicle.advance(s)
        self.k += 1
        return Frame(self.k - 1, s.t, box=s.box)

    def close(self) -> None:
        pass


class RecordedPerception:
    """The recorded box of each frame; counts tracker resets and keeps the attitude each frame was given."""

    def __init__(self) -> None:
        self.resets = 0
        self.attitudes: list[tuple[float, ...] | None] = []

    def process(self, frame: Frame, attitude: Any = None) -> Any:
        self.attitudes.append(None if attitude is None else tuple(attitude))
        return frame.box

    def reset(self) -> None:
        self.resets += 1


def _clock(vehicle: RecordedVehicle):
    return lambda: vehicle.now + LATENCY


def fly_recording(cfg: Any, samples: list[Sample], tmp_path: Any) -> tuple[RecordedVehicle, FlightApp]:
    vehicle = RecordedVehicle(samples)
    log = FlightLog.create(tmp_path / "flight", {}, flush_interval=10.0)
    app = FlightApp(cfg, vehicle, RecordedCamera(samples, vehicle), RecordedPerception(), log, stderr=None)
    app.clock = _clock(vehicle)
    app._baro0 = GROUND_BARO  # the reference the pre-flight takes on the ground
    for st in (State.CONNECT, State.PREFLIGHT, State.ARM, State.TAKEOFF, State.ACQUIRE):
        app.sm.go(st, "recorded flight")
    asyncio.run(asyncio.wait_for(app._fly(), 60.0))
    log.close({})
    return vehicle, app


def shadow_recording(cfg: Any, samples: list[Sample], tmp_path: Any) -> tuple[list, _Session]:
    vehicle = RecordedVehicle(samples)
    log = FlightLog.create(tmp_path / "shadow", {}, flush_interval=10.0)
    computed: list[tuple[float, Any]] = []

    async def main() -> _Session:
        stop = asyncio.Event()
        session = _Session(cfg, ReadOnlyLink(vehicle), log, None, clock=_clock(vehicle),
                           on_setpoint=lambda t, sp: computed.append((t, sp)))
        session.camera = RecordedCamera(samples, vehicle, on_end=stop.set)
        session.perception = RecordedPerception()
        await session.run(stop, None)
        return session

    session = asyncio.run(asyncio.wait_for(main(), 60.0))
    log.close({})
    return computed, session


@pytest.mark.parametrize("overrides", [[], ["hover.estimate=true"]], ids=["default", "hover-estimate"])
def test_shadow_computes_what_the_flight_sends(tmp_path, overrides):
    cfg = load_config([], ["app.acquire_frames=5", "app.engage=auto", "safety.altitude_reference=488", *overrides])
    samples = recording(cfg)
    vehicle, app = fly_recording(cfg, samples, tmp_path)
    computed, session = shadow_recording(cfg, samples, tmp_path)

    # The flight engaged, flew the gate and handed back: the comparison covers every phase that commands.
    states = [h.dst for h in app.sm.history]
    assert State.ENGAGE in states and State.PASS in states and State.RECOVER in states, states
    assert len(vehicle.sent) > 30
    # Every setpoint sent, in order, is the one shadow computed for the same frame: bit for bit.
    n = len(vehicle.sent)
    assert len(computed) >= n
    for (t_f, sp_f), (t_s, sp_s) in zip(vehicle.sent, computed[:n], strict=True):
        assert t_f == t_s
        assert (sp_f.roll_deg, sp_f.pitch_deg, sp_f.yaw_deg, sp_f.thrust) == (
            sp_s.roll_deg, sp_s.pitch_deg, sp_s.yaw_deg, sp_s.thrust)
        assert np.array_equal(sp_f.R_ned_frd, sp_s.R_ned_frd)
    # The rest of the wiring agrees too: the tracker reset at the pass, the confirmed passes.
    assert app.perception.resets == session.perception.resets >= 1
    # Perception is given the attitude the core rotates with (its track follows the camera's rotation), in both.
    given = [a for a in app.perception.attitudes if a is not None]
    assert len(given) >= n and given[:n] == [a for a in session.perception.attitudes if a is not None][:n]
    assert app.stats.gates_passed == session.stats["passes"] == 1
    if cfg.hover.estimate:
        assert app.core.hover_thrust != cfg.airframe.hover_thrust  # the estimate moved, in both
        assert session.core.hover_thrust == app.core.hover_thrust
