"""One frame of the vehicle loops, shared by the flight (companion/app/flight.py) and shadow mode
(companion/app/shadow.py): the core's input read from the vehicle, and the rows a step leaves in the log
(the detection and telemetry rows are companion/app/logrows.py's).

Both loops call these and nothing else between the camera and ``FlightCore.step``, so shadow computes what a
flight would send (tests/app/test_shadow_equals_flight.py checks it bit for bit).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from companion.core import CoreStep, FrameInput, ImuReading

if TYPE_CHECKING:
    from companion.flightlog import FlightLog
    from companion.vehicle import VehicleTelemetry


def attitude_at(vehicle: VehicleTelemetry, t: float) -> np.ndarray | None:
    """PX4's attitude estimate (NED/FRD wxyz) at a frame's capture time, not at its processing time: the box
    must be rotated to the world with the attitude the camera had when it saw it. None before any sample."""
    q = vehicle.attitude_history.at(t)
    if q is None and vehicle.attitude is not None:
        q = vehicle.attitude.q_wxyz
    return q


def frame_input(t: float, box: Any, vehicle: VehicleTelemetry, baro_rel_alt: float | None,
                t_now: float, q: np.ndarray | None) -> FrameInput | None:
    """The core's input for a frame captured at ``t`` and processed at ``t_now`` with ``q`` =
    :func:`attitude_at` the capture, looked up once for perception and the core (None: no attitude yet).
    The newest accelerometer sample (50 Hz) goes to the controller (closing speed, drag) and to the
    hover-thrust estimate."""
    if q is None:
        return None
    imu = vehicle.imu
    return FrameInput(t, box, q, baro_rel_alt, accel_frd=imu.accel_frd if imu is not None else None, t_now=t_now,
                      imu=ImuReading(imu.t_rx, imu.accel_frd) if imu is not None else None)


def log_inputs(log: FlightLog, inp: FrameInput, hover_thrust: float) -> None:
    """The core's input of one frame, as given to ``FlightCore.step`` (its box is the frame's detections row),
    and the hover thrust the core holds before the step: ``companion log rerun`` steps a core with them again."""
    t0, q, a, imu = log.t0, inp.q_wxyz_ned_frd, inp.accel_frd, inp.imu
    acc = (None, None, None) if a is None else (a[0], a[1], a[2])
    log.write("inputs", t_frame=inp.t - t0, qw=q[0], qx=q[1], qy=q[2], qz=q[3], baro_rel_m=inp.baro_rel_alt,
              acc_f=acc[0], acc_r=acc[1], acc_d=acc[2], t_imu=None if imu is None else imu.t - t0,
              t_now=None if inp.t_now is None else inp.t_now - t0,
              confirm=None if inp.confirm is None else int(inp.confirm), hover_thrust=hover_thrust)


def log_step(log: FlightLog, t_frame: float, step: CoreStep, state: str, ctrl_mode: str,
             latency_ms: float) -> None:
    """The rows of one core step: the controller's LOS and demand when it ran, the setpoint when there is
    one (``state``/``ctrl_mode``: the loop's labels), and a new hover-thrust estimate."""
    d = step.decision
    out: Any = d.control
    if out is not None:  # the controller ran (ENGAGE): its LOS and demand
        los = out.los_ned if out.los_ned is not None else (None, None, None)
        log.write("los", t_frame=t_frame, los_n=los[0], los_e=los[1], los_d=los[2], lambda_dot=out.lambda_dot,
                  a_n=float(np.linalg.norm(out.a_n)), demand_scale=out.demand_scale, rejected=out.rejected or "")
    sp = d.setpoint
    if sp is not None:
        log.write("setpoints", t_frame=t_frame, state=state, ctrl_mode=ctrl_mode, roll_deg=sp.roll_deg,
                  pitch_deg=sp.pitch_deg, yaw_deg=sp.yaw_deg, thrust=sp.thrust, latency_ms=latency_ms)
    e, x = step.hover, step.hover_input
    if e is not None and x is not None:
        log.write("hover", u_cmd=x[0], a_up=x[1], hover_thrust=e.hover_thrust, std=e.std, samples=e.samples)
