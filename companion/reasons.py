"""Why a flight (or an engagement) ended: one code per outcome, the process exit code.

Pure: the engagement core (companion/engagement.py) names its ends with these, the app's state machine
(companion/app/states.py) carries them to the exit code.
"""

from __future__ import annotations

import enum


class Reason(enum.IntEnum):
    """Why the flight ended; the value is the process exit code (1 = crash, 2 = config error are taken)."""

    OK = 0  # gate(s) passed (or an intercept pulled up and cleared), handed back, landed, disarmed
    NO_TARGET = 10  # no stable track within acquire_timeout
    TARGET_LOST = 11
    PERCEPTION_STALL = 12  # watchdog: no fresh control output
    ALTITUDE_FLOOR = 13
    MAX_ENGAGEMENT = 14
    PILOT_TAKEOVER = 15
    LINK_LOST = 16
    ARM_DENIED = 17
    OFFBOARD_DENIED = 18
    COMMAND_TIMEOUT = 19
    CONNECT_FAILED = 20
    PREFLIGHT_FAILED = 21
    EXCEPTION = 22
    SIGNAL = 23  # SIGTERM / SIGINT: orderly hand-over
    CAMERA_FAILED = 24
    NOT_CONFIRMED = 25  # the operator did not confirm the pre-flight summary (companion/app/preflight.py)
    VEHICLE_BUSY = 26  # armed or in the air at start (start=takeoff): refused
    UNSAFE_FAILSAFE = 27  # PX4's offboard-loss failsafe would not end in a safe mode: refused before arming
    DISARMED = 28  # the vehicle was disarmed in flight by someone else
    SETPOINT_INVALID = 29  # upstream produced a non-finite setpoint: nothing sent, handed over
    # The flight ended normally but not as claimed (companion/app/outcome.py):
    GATE_MISSED = 30  # ground truth: a gate plane crossed outside the radius, or fewer gates than passes claimed
    PASS_NOT_CONFIRMED = 31  # no ground truth: a pass ended on its timeout, without evidence the gate is behind
    TELEMETRY_INVALID = 32  # attitude/telemetry rejected (non-finite, out of range, spoofed) persistently
    AUTOPILOT_MODE = 33  # PX4 changed the mode on its own (failsafe land, return, ...): not the pilot, not us
    # An intercept (app.on_close: pull_up) judged by ground truth (companion/app/outcome.py); a cleared one is OK:
    INTERCEPT_IMPACT = 34  # the pull-up came within outcome.IMPACT_DISTANCE of the target's box: it hit
    TARGET_MISSED = 35  # cleared, but the track before the pull-up would have crossed outside the target's box
