"""The last line before a setpoint leaves the app: finite, inside the tilt envelope, above the thrust floor.

Whatever computed it (PN, pass, recover, a future controller, a bug), ``SetpointEnvelope.check`` is
applied by the vehicle link to every setpoint it sends (``set_setpoint``, ``start_offboard``):

* any non-finite value -> ``ValueError`` (the link turns it into a named abort, SETPOINT_INVALID:
  there is no safe way to guess what a NaN meant, so nothing is sent and the app hands over to HOLD);
* the thrust axis tilted more than ``airframe.max_tilt`` from vertical -> the same tilt direction at
  ``max_tilt`` (roll and pitch recomputed; yaw kept), a clamp reported as an event;
* thrust below ``airframe.thrust_min`` (a quad at 0 falls) or above 1 -> clamped, reported.

Pure: numbers in, numbers out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Checked:
    roll_deg: float
    pitch_deg: float
    yaw_deg: float
    thrust: float
    clamped: str  # "" when the setpoint passed unchanged, else what was clamped


TILT_ROUNDING_DEG = 1e-3  # a setpoint this close above max_tilt is rounding (Euler angles in degrees), not an event


def tilt_deg(roll_deg: float, pitch_deg: float) -> float:
    """Angle of the thrust axis from vertical for a ZYX (yaw, pitch, roll) attitude: cos = cos(roll) cos(pitch)."""
    c = math.cos(math.radians(roll_deg)) * math.cos(math.radians(pitch_deg))
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


class SetpointEnvelope:
    def __init__(self, max_tilt_deg: float, thrust_min: float) -> None:
        if not (0.0 < max_tilt_deg < 90.0 and 0.0 <= thrust_min < 1.0):
            raise ValueError(f"envelope: max_tilt {max_tilt_deg} deg, thrust_min {thrust_min} out of range")
        self.max_tilt = float(max_tilt_deg)
        self.thrust_min = float(thrust_min)

    def check(self, roll_deg: float, pitch_deg: float, yaw_deg: float, thrust: float) -> Checked:
        vals = (roll_deg, pitch_deg, yaw_deg, thrust)
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in vals):
            raise ValueError(f"setpoint: non-finite value refused (roll, pitch, yaw, thrust = {vals})")
        notes = []
        tilt = tilt_deg(roll_deg, pitch_deg)
        if tilt > self.max_tilt:
            # Thrust axis in the yaw frame: (sin p cos r, -sin r, cos p cos r). Keep its horizontal direction,
            # set its angle from vertical to max_tilt, and read roll and pitch back from it.
            r, p = math.radians(roll_deg), math.radians(pitch_deg)
            phi = math.atan2(-math.sin(r), math.sin(p) * math.cos(r))
            tm = math.radians(self.max_tilt)
            new_r = -math.asin(math.sin(tm) * math.sin(phi))
            new_p = math.atan2(math.sin(tm) * math.cos(phi), math.cos(tm))
            if tilt > self.max_tilt + TILT_ROUNDING_DEG:  # the solver's own setpoints sit exactly on the limit
                notes.append(f"tilt {tilt:.1f} deg > airframe.max_tilt {self.max_tilt:.1f} deg "
                             f"(roll {roll_deg:.1f} -> {math.degrees(new_r):.1f}, pitch {pitch_deg:.1f} -> "
                             f"{math.degrees(new_p):.1f})")
            roll_deg, pitch_deg = math.degrees(new_r), math.degrees(new_p)
        if thrust < self.thrust_min - 1e-9:
            notes.append(f"thrust {thrust:.3f} < airframe.thrust_min {self.thrust_min:.3f}")
        if thrust < self.thrust_min:
            thrust = self.thrust_min
        if thrust > 1.0 + 1e-9:
            notes.append(f"thrust {thrust:.3f} > 1")
        if thrust > 1.0:
            thrust = 1.0
        yaw = math.remainder(yaw_deg, 360.0)
        return Checked(float(roll_deg), float(pitch_deg), float(yaw), float(thrust), "; ".join(notes))
