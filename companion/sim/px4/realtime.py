"""The simulated PX4 in real time: ``SimPX4`` runs the autopilot model and its MAVLink wire on one thread.

The thread steps the model (companion/sim/px4/model.py) at wall-clock pace, sends the telemetry due
(companion/sim/px4/wire.py) and reads datagrams until the next tick; everything it touches is
under the model's lock, which the public methods here take too (so tests may call them from any thread).
"""

from __future__ import annotations

import copy
import math
import select
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from companion.sim.dynamics import QuadParams, QuadState
from companion.sim.px4.model import Px4Model
from companion.sim.px4.wire import MavlinkWire


class SimPX4:
    """Simulated PX4 autopilot + quadrotor, real time, own thread; MAVLink 2 over UDP on 127.0.0.1."""

    SYSID, COMPID = MavlinkWire.SYSID, MavlinkWire.COMPID

    def __init__(
        self,
        config: Any = None,
        *,
        port: int = 0,
        remote_port: int | None = 0,
        params: QuadParams | None = None,
        px4_params: Mapping[str, float] | None = None,
        initial_state: QuadState | None = None,
        initial_mode: str = "HOLD",
        heartbeat_hz: float = 1.0,
        telemetry_hz: float = 50.0,
        noise: bool = True,
    ) -> None:
        if config is None:
            from companion.config import Config

            config = Config()
        self._model = Px4Model(config, params=params, px4_params=px4_params, initial_state=initial_state,
                               initial_mode=initial_mode, noise=noise)
        self.quad_params = self._model.quad_params
        self._port_req = int(port)
        self._wire = MavlinkWire(self._model, remote_port=remote_port, heartbeat_hz=heartbeat_hz,
                                 telemetry_hz=telemetry_hz)
        self._model.out = self._wire
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.overruns = 0  # physics steps skipped because the thread fell behind real time
        self._busy = 0.0  # s of CPU-bound work in the sim thread (for stats())
        self._t0_mono = math.nan

    # ---------------------------------------------------------------------------------- lifecycle
    def start(self) -> SimPX4:
        if self._thread is not None:
            return self
        if not 0 <= self._port_req <= 65535:
            raise ValueError(f"SimPX4: port {self._port_req} is not a UDP port (0-65535)")
        self._wire.open(self._port_req)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"SimPX4:{self.port}", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None
        self._wire.close()

    def __enter__(self) -> SimPX4:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def port(self) -> int:
        if self._wire.sock is None:
            raise RuntimeError("SimPX4.port: not started")
        return self._wire.sock.getsockname()[1]

    @property
    def remote_port(self) -> int | None:
        """The port on 127.0.0.1 the sim sends to (mavsdk listens there), None without one."""
        return None if self._wire.remote is None else self._wire.remote[1]

    @property
    def url_for_mavsdk(self) -> str:
        if self._wire.remote is not None:
            return f"udpin://127.0.0.1:{self._wire.remote[1]}"
        return f"udpout://127.0.0.1:{self.port}"

    # ------------------------------------------------------------------------------- observation
    def truth(self) -> QuadState:
        with self._model.lock:
            return copy.deepcopy(self._model.quad.state)

    @property
    def mode(self) -> str:
        with self._model.lock:
            return self._model.mode

    @property
    def armed(self) -> bool:
        with self._model.lock:
            return self._model.armed

    @property
    def landed(self) -> bool:
        with self._model.lock:
            return self._model.quad.state.on_ground

    @property
    def time(self) -> float:
        with self._model.lock:
            return self._model.t

    @property
    def events(self) -> list[tuple[float, str]]:
        with self._model.lock:
            return list(self._model.events)

    @property
    def setpoint_count(self) -> int:
        """Attitude setpoints received so far."""
        with self._model.lock:
            return self._model.sp_count

    def last_setpoint(self) -> tuple[float, np.ndarray | None, float]:
        """(sim time received, commanded attitude xyzw body FLU -> ENU, normalised thrust)."""
        m = self._model
        with m.lock:
            q = None if m.sp_q_enu_flu is None else m.sp_q_enu_flu.copy()
            return m.sp_time, q, m.sp_thrust

    def stats(self) -> dict[str, float]:
        """Load of the sim thread: wall and sim time, busy fraction, skipped physics steps."""
        with self._model.lock:
            wall = time.monotonic() - self._t0_mono if math.isfinite(self._t0_mono) else 0.0
            return {"wall_s": wall, "sim_s": self._model.t, "busy_fraction": self._busy / wall if wall > 0 else 0.0,
                    "overruns": float(self.overruns), "physics_hz": 1.0 / self._model.dt}

    def monotonic_of(self, t_sim: float) -> float:
        """time.monotonic() at which the sim clock read ``t_sim`` (same host: for latency measurements)."""
        return self._t0_mono + t_sim

    def last_setpoint_rx_monotonic(self) -> float:
        """time.monotonic() when the last attitude setpoint arrived (NaN before the first)."""
        with self._model.lock:
            return self._model.sp_rx_mono

    def wait_for(self, predicate: Callable[[], bool], timeout: float) -> bool:
        """Block until predicate() (evaluated under the sim's lock after each physics tick) or timeout."""
        deadline = time.monotonic() + timeout
        with self._model.cond:
            while not predicate():
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._model.cond.wait(min(left, 0.05))
        return True

    def wait_event(self, prefix: str, timeout: float, since: float = -math.inf) -> tuple[float, str] | None:
        """The first event at or after ``since`` whose text starts with ``prefix``, or None at timeout."""
        found: list[tuple[float, str]] = []

        def pred() -> bool:
            for ev in self._model.events:
                if ev[0] >= since and ev[1].startswith(prefix):
                    found.append(ev)
                    return True
            return False

        return found[0] if self.wait_for(pred, timeout) else None

    def param(self, name: str) -> float:
        with self._model.lock:
            return self._model.params[name][0]

    def set_param(self, name: str, value: float) -> None:
        with self._model.lock:
            self._model.set_param(name, value)

    # ------------------------------------------------------------------------------------ switches
    @property
    def deny_arming(self) -> bool:
        return self._model.deny_arming

    @deny_arming.setter
    def deny_arming(self, on: bool) -> None:
        self._model.deny_arming = on

    @property
    def deny_offboard(self) -> bool:
        return self._model.deny_offboard

    @deny_offboard.setter
    def deny_offboard(self, on: bool) -> None:
        self._model.deny_offboard = on

    @property
    def fail_preflight(self) -> bool:
        """SYS_STATUS reports the preflight checks failed; arming is refused."""
        return self._model.fail_preflight

    @fail_preflight.setter
    def fail_preflight(self, on: bool) -> None:
        self._model.fail_preflight = on

    def drop_link(self, on: bool) -> None:
        """On: every datagram in either direction is lost (radio out of range)."""
        with self._model.lock:
            self._wire.drop_link(on)

    def silence_commands(self, on: bool) -> None:
        """On: COMMAND_LONG/COMMAND_INT are received but neither executed nor acknowledged."""
        with self._model.lock:
            self._wire.silence_commands(on)

    def corrupt_attitude(self, on: bool) -> None:
        """On: ATTITUDE_QUATERNION carries NaN (an estimator failure, or a corrupted link)."""
        with self._model.lock:
            self._wire.corrupt_attitude(on)

    def set_rc(self, channels_us: list[int] | None) -> None:
        """An RC transmitter: RC_CHANNELS at 10 Hz with these PWM values (us, channel 1 first); None: no RC."""
        with self._model.lock:
            self._wire.set_rc(channels_us)

    def set_gcs(self, on: bool) -> None:
        """A ground station on PX4's GCS link: on, its HEARTBEAT reaches the app at 1 Hz (PX4 forwards it)."""
        with self._model.lock:
            self._wire.set_gcs(on)

    def gcs_command(self, command: int, param1: float, target: tuple[int, int] = (1, 195)) -> None:
        """The ground station's COMMAND_LONG to ``target`` (default: mavsdk's companion ids), forwarded by PX4."""
        with self._model.lock:
            self._wire.gcs_command(command, param1, target)

    @property
    def gcs_acks(self) -> list[tuple[int, int]]:
        """(command, MAV_RESULT) of the COMMAND_ACKs sent to the ground station."""
        with self._model.lock:
            return list(self._wire.gcs_acks)

    def force_disarm(self) -> None:
        """The kill switch (or a forced disarm from a ground station): motors off wherever the vehicle is."""
        with self._model.lock:
            self._model.force_disarm()

    def pilot_takeover(self, mode: str = "POSCTL") -> None:
        """The pilot flips the mode switch: PX4 leaves OFFBOARD and holds position (POSCTL/HOLD) or lands."""
        with self._model.lock:
            self._model.pilot_takeover(mode)

    # ------------------------------------------------------------------------------ thread loop
    def _run(self) -> None:
        t0 = self._t0_mono = time.monotonic()
        steps = 0
        model, wire = self._model, self._wire
        assert wire.sock is not None
        sock = wire.sock
        while not self._stop.is_set():
            now = time.monotonic() - t0
            due = int(now / model.dt)
            if due - steps > 50:  # fell far behind (machine busy): skip rather than spiral
                self.overruns += due - steps - 1
                steps = due - 1
            busy0 = time.perf_counter()
            with model.lock:
                while steps < due:
                    model.physics_step()
                    steps += 1
                wire.send_telemetry()
                model.cond.notify_all()
            busy1 = time.perf_counter()
            wait = (steps + 1) * model.dt - (time.monotonic() - t0)
            try:
                ready, _, _ = select.select([sock], [], [], max(0.0, wait))
            except (OSError, ValueError):
                break
            busy2 = time.perf_counter()
            if ready:
                wire.receive_all(sock)
            self._busy += (busy1 - busy0) + (time.perf_counter() - busy2)
