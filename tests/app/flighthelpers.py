"""Helpers of the flight-app tests: a real simulated PX4 on 127.0.0.1 that the real mavsdk talks to.

Scenarios are short on purpose (take-off to 5 m at 3 m/s, gate 25 m away): a whole flight with
landing takes ~20 s, a fault flight ~10 s.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from companion.config import Config, load_config

FAST_PX4 = {"MPC_TKO_SPEED": 3.0, "MPC_LAND_SPEED": 1.5}
FLIGHT_TIMEOUT = 90.0  # s: no flight in these tests may take longer (every wait has a timeout)

BASE_OVERRIDES = [
    "app.camera=synthetic",
    "app.synthetic.render=geometric",
    "app.synthetic.motion=linear_fast",
    "app.synthetic.distance=25",
    "app.takeoff_altitude=5",
    "log.plot=false",
    "link.connect_timeout=10",
    "link.command_timeout=3",
    "sim.seed=7",
]


def make_config(tmp_path: Path, url: str, *overrides: str) -> Config:
    return load_config([Path(__file__).resolve().parents[2] / "config" / "app.yaml"],
                       [*BASE_OVERRIDES, f"link.url={url}", f"log.directory={tmp_path / 'flights'}", *overrides])


async def wait_state(app: Any, name: str, timeout: float = 30.0) -> None:
    """Wait until the app's state machine is in (or has passed through) ``name``."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not any(h.dst.value == name for h in app.sm.history):
        if loop.time() > deadline:
            raise TimeoutError(f"app never reached {name} (state {app.sm.state.value})")
        await asyncio.sleep(0.02)


def run_flight(cfg: Config, alongside: Callable[[Any], Awaitable[None]] | None = None) -> tuple[Any, Path, dict]:
    from companion.app.session import fly

    errors: list[BaseException] = []

    async def side(app: Any) -> None:
        try:
            await alongside(app)  # type: ignore[misc]
        except asyncio.CancelledError:
            raise
        except BaseException as e:  # surfaced after the flight: a broken fault injection fails the test
            errors.append(e)

    async def main() -> tuple[Any, Path, dict]:
        return await asyncio.wait_for(
            fly(cfg, plot=False, handle_signals=False, alongside=side if alongside is not None else None),
            FLIGHT_TIMEOUT)

    result = asyncio.run(main())
    if errors:
        raise errors[0]
    return result


def pilot_takes_off(sim, altitude: float) -> None:
    """A pilot (here a ground station over MAVLink, as QGroundControl would) arms and takes off, then POSCTL."""
    from pymavlink import mavutil

    sim.set_param("MIS_TAKEOFF_ALT", altitude)
    gcs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{sim.port}", source_system=255, source_component=190)
    try:
        gcs.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        gcs.mav.command_long_send(1, 1, mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        assert sim.wait_for(lambda: sim.armed, timeout=5.0)
        # param7 NaN: PX4 climbs to MIS_TAKEOFF_ALT above home (param7 would be an AMSL altitude).
        gcs.mav.command_long_send(1, 1, mavutil.mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, math.nan, math.nan,
                                  math.nan, math.nan)
        assert sim.wait_event("mode:HOLD:takeoff_done", timeout=20.0) is not None
        time.sleep(0.5)
        sim.pilot_takeover("POSCTL")  # the pilot hovers in position mode, sticks centred
    finally:
        gcs.close()


def fly_rendered(tmp: Path, first_seed: int, mount_pitch_error: float, good: Callable[[Path, dict], bool],
                 tries: int = 3) -> Path:
    """A flight of the app on the simulated PX4 with the synthetic camera's rendered frames through the shipped
    detector (linear slow gate; the camera truly mounted ``mount_pitch_error`` deg off its configured pitch). The
    tools reading such logs are under test, not the flight: one that ``good(folder, summary)`` rejects (a rendered
    flight once engaged for only 4 frames in ~8, once missed the ring by 7 cm) is flown again, on a fresh simulated
    PX4 (the one that landed is disarming: a second take-off on it was refused), ``tries`` times at most."""
    from companion.sim.px4 import SimPX4

    folder = None
    for k in range(tries):
        px4 = SimPX4(load_config([], [f"sim.seed={first_seed + k}"]), px4_params=FAST_PX4)
        px4.start()
        try:
            cfg = make_config(tmp / f"try{k}", px4.url_for_mavsdk, "app.synthetic.render=image",
                              "app.synthetic.motion=linear_slow", f"sim.camera.mount_error.pitch={mount_pitch_error}")
            _, folder, summary = run_flight(cfg)
        finally:
            px4.stop()
        if good(Path(folder), summary):
            break
    assert folder is not None
    return Path(folder)
