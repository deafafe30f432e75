"""Helpers for the vehicle-link tests: a raw MAVLink client, async runners, setpoints.

Everything talks over real UDP sockets on 127.0.0.1; the simulated PX4 binds a free port of its
own, so tests can run in parallel (pytest -n).
"""

from __future__ import annotations

import asyncio
import math
import socket
import time
from collections.abc import Callable, Coroutine
from types import SimpleNamespace
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from companion.app.link import VehicleLink
from companion.config import Config
from companion.sim.px4 import SimPX4

# The vehicle's true hover thrust differs from the config's 0.5 so reading MPC_THR_HOVER shows.
TRUE_HOVER = 0.37
# Faster than PX4's defaults so the suite stays short; the behaviour is the same.
FAST_PX4 = {"MPC_TKO_SPEED": 3.0, "MPC_LAND_SPEED": 0.8, "COM_DISARM_LAND": 0.5, "MIS_TAKEOFF_ALT": 3.0}


def run(coro_fn: Callable[[], Coroutine[Any, Any, Any]], timeout: float = 60.0) -> Any:
    """Run one async test body with an overall timeout (the pytest-timeout mark is the backstop)."""

    async def main() -> Any:
        return await asyncio.wait_for(coro_fn(), timeout)

    return asyncio.run(main())


async def connected_link(sim: SimPX4, cfg: Config, **kw: Any) -> VehicleLink:
    link = VehicleLink.from_config(cfg, **kw)
    await link.connect(sim.url_for_mavsdk, timeout=5.0)
    await link.wait_healthy(timeout=10.0)
    return link


async def flying_link(sim: SimPX4, cfg: Config, altitude: float = 3.0, **kw: Any) -> VehicleLink:
    link = await connected_link(sim, cfg, **kw)
    await link.hover_thrust(timeout=3.0)
    await link.arm()
    await link.takeoff(altitude, timeout=20.0)
    return link


def setpoint(link: VehicleLink, roll: float = 0.0, pitch: float = 0.0, yaw: float | None = None,
             thrust: float | None = None) -> Any:
    """A setpoint as the controller makes them (duck-typed: roll/pitch/yaw deg NED/FRD + thrust 0..1).

    Default yaw: the current one; default thrust: the true hover thrust over the tilt (level flight).
    """
    if yaw is None:
        R = link.attitude.R_ned_frd
        yaw = math.degrees(math.atan2(R[1, 0], R[0, 0]))
    if thrust is None:
        thrust = TRUE_HOVER / (math.cos(math.radians(roll)) * math.cos(math.radians(pitch)))
    return SimpleNamespace(roll_deg=roll, pitch_deg=pitch, yaw_deg=yaw, thrust=thrust)


class RawGcs:
    """A bare pymavlink client over UDP: sends exactly what a test says, nothing is resent."""

    def __init__(self, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.addr = ("127.0.0.1", port)
        self.mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)

    def send(self, msg: Any) -> None:
        self.sock.sendto(msg.pack(self.mav), self.addr)
        self.mav.seq = (self.mav.seq + 1) % 256

    def heartbeat(self) -> None:
        self.send(self.mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3))

    def command(self, cmd: int, *params: float) -> None:
        p = [*params, *[math.nan] * (7 - len(params))]
        self.send(self.mav.command_long_encode(1, 1, cmd, 0, *p))

    def attitude_setpoint(self, q_wxyz: list[float], thrust: float) -> None:
        self.send(self.mav.set_attitude_target_encode(0, 1, 1, 0b111, q_wxyz, 0.0, 0.0, 0.0, thrust))

    def recv(self, pred: Callable[[Any], bool], timeout: float) -> Any:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                data, _ = self.sock.recvfrom(65536)
            except TimeoutError:
                continue
            for m in self.mav.parse_buffer(data) or []:
                if pred(m):
                    return m
        return None

    def drain(self) -> None:
        """Throw away everything already queued (old telemetry), so the next recv() is fresh."""
        self.sock.setblocking(False)
        try:
            while True:
                self.sock.recvfrom(65536)
        except BlockingIOError:
            pass
        finally:
            self.sock.settimeout(0.05)

    def ack(self, cmd: int, timeout: float = 2.0) -> int | None:
        m = self.recv(lambda m: m.get_type() == "COMMAND_ACK" and m.command == cmd, timeout)
        return None if m is None else m.result

    def close(self) -> None:
        self.sock.close()
