"""What PX4 does if the app dies: its failsafe parameters, read at pre-flight, reported and judged.

When the app stops streaming setpoints (crash, SIGKILL, a dead link) PX4 waits ``COM_OF_LOSS_T`` seconds,
flying the last setpoint, then switches to ``COM_OBL_RC_ACT``. PX4 v1.15 (measured with SITL SIH,
no RC): ``COM_OF_LOSS_T`` 1 s, ``COM_OBL_RC_ACT`` 0 (Position mode); with no manual control the
Position-mode fallback descends and lands ("Failsafe activated: Autopilot disengaged, switching to
Position mode"; heartbeat POSCTL; landed and disarmed 13 s later from 5 m), after which the vehicle
sits disarmed with navigation state Offboard and refuses to arm until another mode is set.

``judge`` is pure: parameter values in, (report line, list of problems) out.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

# PX4 v1.15 names (checked against the SITL build: all present), with their type for the param protocol.
FAILSAFE_PARAMS: dict[str, str] = {
    "COM_OF_LOSS_T": "float",  # s without offboard setpoints before the offboard-loss failsafe
    "COM_OBL_RC_ACT": "int",  # offboard-loss action
    "COM_RC_IN_MODE": "int",  # where manual control comes from (RC, MAVLink joystick, both, none)
    "NAV_RCL_ACT": "int",  # manual-control (RC) loss action
    "COM_RCL_EXCEPT": "int",  # bitmask: modes in which RC loss is ignored (bit 2: Offboard)
    "COM_RC_LOSS_T": "float",  # s without manual control before RC loss
    "NAV_DLL_ACT": "int",  # GCS data-link loss action
    "COM_DL_LOSS_T": "int",  # s without GCS heartbeat before data-link loss
    "COM_FAIL_ACT_T": "float",  # s PX4 holds before it starts a failsafe action (1.15)
}

OBL_ACTIONS = {0: "Position mode", 1: "Altitude mode", 2: "Manual mode", 3: "Return", 4: "Land", 5: "Hold",
               6: "Terminate", 7: "Disarm"}
# Actions after which an unattended vehicle ends on the ground or holding in the air. Position and Altitude
# hold with centred sticks, and without manual control PX4 falls back to a descent and landing.
SAFE_OBL = frozenset({0, 1, 3, 4, 5})
RC_IN_MODES = {0: "RC only", 1: "MAVLink joystick only", 2: "RC and joystick, with fallback",
               3: "RC or joystick, first one kept", 4: "no manual control"}
NAV_ACTIONS = {0: "disabled", 1: "Hold", 2: "Return", 3: "Land", 5: "Terminate", 6: "Disarm"}


def _name(table: Mapping[int, str], v: float | None) -> str:
    if v is None or not math.isfinite(v):
        return "unread"
    return table.get(int(v), f"unknown value {v:g}")


def judge(values: Mapping[str, float | None], max_loss_time: float) -> tuple[str, list[str]]:
    """(one report line, problems). No problems: offboard loss ends in a safe mode within max_loss_time."""
    t = values.get("COM_OF_LOSS_T")
    act = values.get("COM_OBL_RC_ACT")
    problems: list[str] = []
    if t is None or act is None:
        missing = [k for k in ("COM_OF_LOSS_T", "COM_OBL_RC_ACT") if values.get(k) is None]
        problems.append(f"could not read {', '.join(missing)}: what PX4 does if the app dies is unknown")
    else:
        if not (math.isfinite(t) and 0.0 < t <= max_loss_time):
            problems.append(f"COM_OF_LOSS_T = {t:g} s: PX4 would fly the last setpoint that long "
                            f"(limit safety.max_offboard_loss_time = {max_loss_time:g} s)")
        if int(act) not in SAFE_OBL:
            problems.append(f"COM_OBL_RC_ACT = {int(act)} ({_name(OBL_ACTIONS, act)}) is not a safe end "
                            f"for an unattended vehicle (safe: {', '.join(OBL_ACTIONS[a] for a in sorted(SAFE_OBL))})")
    rc = values.get("COM_RC_IN_MODE")
    no_rc = rc is not None and int(rc) == 4
    fallback = " (without manual control PX4 descends and lands)" if act is not None and int(act) in (0, 1, 2) else ""
    line = (f"PX4 failsafe if the app dies: offboard loss after COM_OF_LOSS_T = {_fmt(t)} s -> COM_OBL_RC_ACT = "
            f"{_fmt(act)} ({_name(OBL_ACTIONS, act)}){fallback}; manual control COM_RC_IN_MODE = {_fmt(rc)} "
            f"({_name(RC_IN_MODES, rc)}{', RC loss never triggers' if no_rc else ''}); RC loss NAV_RCL_ACT = "
            f"{_fmt(values.get('NAV_RCL_ACT'))} ({_name(NAV_ACTIONS, values.get('NAV_RCL_ACT'))}) after "
            f"COM_RC_LOSS_T = {_fmt(values.get('COM_RC_LOSS_T'))} s, COM_RCL_EXCEPT = "
            f"{_fmt(values.get('COM_RCL_EXCEPT'))}; data-link loss NAV_DLL_ACT = {_fmt(values.get('NAV_DLL_ACT'))} "
            f"({_name(NAV_ACTIONS, values.get('NAV_DLL_ACT'))}) after COM_DL_LOSS_T = "
            f"{_fmt(values.get('COM_DL_LOSS_T'))} s; COM_FAIL_ACT_T = {_fmt(values.get('COM_FAIL_ACT_T'))} s")
    return line, problems


def _fmt(v: float | None) -> str:
    return "?" if v is None else f"{v:g}"


# The mode PX4's heartbeat shows for each offboard-loss action (mavsdk FlightMode names).
OBL_MODES = {0: "POSCTL", 1: "ALTCTL", 2: "MANUAL", 3: "RETURN_TO_LAUNCH", 4: "LAND", 5: "HOLD"}
DEFAULT_OF_LOSS_T = 1.0  # s, PX4 v1.15's default, when the parameter could not be read


def offboard_loss_explains(mode: str, gap_s: float, values: Mapping[str, float | None],
                           px4_failsafe: str | None = None) -> str | None:
    """Why leaving OFFBOARD for ``mode`` was PX4's own offboard-loss failsafe, not a pilot (None: no evidence).

    Evidence: PX4 said so (its failsafe event, ``px4_failsafe``: the text), or our setpoints stopped for at least
    COM_OF_LOSS_T (``gap_s``: the longest recent gap in the link or in our own loop) and the mode is the one
    COM_OBL_RC_ACT selects. A pilot flipping a switch after a short gap is possible, but without manual control
    PX4 descends and lands in that mode either way: the line names what PX4 does, which holds in both cases.
    """
    t = values.get("COM_OF_LOSS_T")
    t = DEFAULT_OF_LOSS_T if t is None or not math.isfinite(t) else float(t)
    act = values.get("COM_OBL_RC_ACT")
    act_i = None if act is None or not math.isfinite(act) else int(act)
    action = (f"COM_OBL_RC_ACT = {act_i} ({_name(OBL_ACTIONS, act)})" if act_i is not None
              else "its offboard-loss action")
    fallback = ("; with no manual control PX4 descends and lands" if act_i in (0, 1, 2) or act_i is None else "")
    if px4_failsafe:
        return f"PX4's offboard-loss failsafe ({px4_failsafe}): {action}, not a pilot{fallback}"
    expected = OBL_MODES.get(act_i) if act_i is not None else None
    if gap_s >= t and (expected is None or expected == mode):
        return (f"PX4's offboard-loss failsafe: no setpoints for {gap_s:.1f} s >= COM_OF_LOSS_T = {t:g} s, "
                f"{action} -> {mode}, not a pilot{fallback}")
    return None
