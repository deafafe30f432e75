"""The simulated PX4's behaviour: parameters, modes, arming, take-off/landing, failsafes, own-mode flight.

``Px4Model`` is the autopilot and its quadrotor with no socket and no thread: ``physics_step`` advances
it one tick, ``execute`` runs a vehicle command, ``accept_setpoint`` takes an offboard attitude
setpoint. What PX4 would say on the link (STATUSTEXT, PX4 events) goes to ``out`` (the MAVLink wire,
companion/sim/px4/wire.py). Its methods do not lock: callers hold ``lock`` (companion/sim/px4/realtime.py).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping
from typing import Any, Protocol

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from companion.sim.dynamics import G, QuadParams, Quadrotor, QuadState, matrix_to_quat, quat_to_matrix
from companion.sim.sensors import Sensors, Wind

# PX4 custom modes: custom_mode = (sub_mode << 24) | (main_mode << 16).
MODES: dict[str, tuple[int, int]] = {
    "POSCTL": (3, 0),
    "TAKEOFF": (4, 2),
    "HOLD": (4, 3),
    "LAND": (4, 6),
    "OFFBOARD": (6, 0),
}
_MODE_BY_CODE = {v: k for k, v in MODES.items()}
POSITION_MODES = ("POSCTL", "HOLD")

# PX4 v1.15 SITL SIH's values (read from the real build). (value, MAV_PARAM_TYPE).
REAL32, INT32 = mavlink.MAV_PARAM_TYPE_REAL32, mavlink.MAV_PARAM_TYPE_INT32
DEFAULT_PX4_PARAMS: dict[str, tuple[float, int]] = {
    "MPC_THR_HOVER": (0.5, REAL32),  # replaced by the vehicle's true hover thrust unless given
    "COM_OF_LOSS_T": (1.0, REAL32),
    "COM_OBL_RC_ACT": (0, INT32),  # 0 Position (no RC: descend and land), 3 Return, 4 Land, 5 Hold, 7 Disarm
    "COM_RC_IN_MODE": (1, INT32),  # SITL: MAVLink joystick only (none connected here)
    "NAV_RCL_ACT": (2, INT32),
    "COM_RCL_EXCEPT": (0, INT32),
    "COM_RC_LOSS_T": (0.5, REAL32),
    "NAV_DLL_ACT": (0, INT32),
    "COM_DL_LOSS_T": (10, INT32),
    "COM_FAIL_ACT_T": (5.0, REAL32),
    "MIS_TAKEOFF_ALT": (2.5, REAL32),
    "MPC_TKO_SPEED": (1.5, REAL32),
    "MPC_LAND_SPEED": (0.7, REAL32),
    "MPC_LAND_ALT2": (5.0, REAL32),  # below this, descend at MPC_LAND_SPEED (above: MPC_Z_VEL_MAX_DN)
    "MPC_XY_VEL_MAX": (12.0, REAL32),
    "MPC_Z_VEL_MAX_UP": (3.0, REAL32),
    "MPC_Z_VEL_MAX_DN": (1.5, REAL32),
    "MPC_TILTMAX_AIR": (45.0, REAL32),
    "MPC_THR_MIN": (0.12, REAL32),
    "COM_DISARM_LAND": (2.0, REAL32),
    "COM_DISARM_PRFLT": (10.0, REAL32),
}

# Home: PX4 SITL's default origin (Zurich); lat/lon from the local position by a flat-earth map.
HOME_LAT, HOME_LON, HOME_ALT = 47.397742, 8.545594, 488.0

LOG_INFO, LOG_WARNING, LOG_CRITICAL = 6, 4, 2  # external log level (low nibble; PX4 sends it twice)


def nan_to(x: float, default: float) -> float:
    return default if (x is None or not math.isfinite(x)) else float(x)


class Outbox(Protocol):
    """What the autopilot says on its own initiative (the MAVLink wire sends it)."""

    def statustext(self, text: str) -> None: ...

    def px4_event(self, name: str, level: int, *args: float) -> None: ...


class _NoLink:
    """The outbox of a model not (yet) on a link: says nothing."""

    def statustext(self, text: str) -> None:
        pass

    def px4_event(self, name: str, level: int, *args: float) -> None:
        pass


class _PositionController:
    """PX4-like cascaded controller for the autopilot's own modes: position P -> velocity PI -> accel.

    Output: attitude (xyzw, body FLU -> ENU) and normalised thrust, from ground truth.
    """

    K_POS_XY, K_POS_Z = 0.95, 1.0  # 1/s (PX4 MPC_XY_P, MPC_Z_P)
    K_VEL_XY, K_VEL_Z = 1.8, 4.0  # 1/s (PX4 MPC_XY_VEL_P_ACC, MPC_Z_VEL_P_ACC)
    K_I_XY, K_I_Z = 0.4, 2.0  # 1/s^2 (PX4 MPC_XY_VEL_I_ACC, MPC_Z_VEL_I_ACC): wind, hover-thrust error
    I_MAX = 3.0  # m/s^2, anti-windup

    def __init__(self) -> None:
        self._i = np.zeros(3)

    def command(
        self, s: QuadState, p_ref: np.ndarray, yaw: float, hover_thrust: float, params: Mapping[str, float],
        vz_override: float | None = None, dt: float = 0.0,
    ) -> tuple[np.ndarray, float]:
        v_xy_max = params["MPC_XY_VEL_MAX"]
        v_ref = np.empty(3)
        v_ref[:2] = self.K_POS_XY * (p_ref[:2] - s.p[:2])
        n = float(np.linalg.norm(v_ref[:2]))
        if n > v_xy_max:
            v_ref[:2] *= v_xy_max / n
        if vz_override is not None:
            v_ref[2] = vz_override
        else:
            v_ref[2] = float(np.clip(self.K_POS_Z * (p_ref[2] - s.p[2]),
                                     -params["MPC_Z_VEL_MAX_DN"], params["MPC_Z_VEL_MAX_UP"]))
        e = v_ref - s.v
        if not s.on_ground:
            self._i = np.clip(self._i + dt * e * (self.K_I_XY, self.K_I_XY, self.K_I_Z), -self.I_MAX, self.I_MAX)
        a = np.empty(3)
        a[:2] = self.K_VEL_XY * e[:2] + self._i[:2]
        a[2] = self.K_VEL_Z * e[2] + self._i[2] + G
        a[2] = max(a[2], 0.3 * G)  # never command a free fall
        # Tilt limit: scale the horizontal part so the thrust axis stays within MPC_TILTMAX_AIR.
        max_h = a[2] * math.tan(math.radians(params["MPC_TILTMAX_AIR"]))
        h = float(np.linalg.norm(a[:2]))
        if h > max_h:
            a[:2] *= max_h / h
        # Thrust axis along a, heading kept: body y = z_b x (cos yaw, sin yaw, 0), body x = y_b x z_b.
        # Plain floats: this runs at the physics rate and numpy's cross/scipy cost ~0.4 ms per call here.
        ax, ay, az = float(a[0]), float(a[1]), float(a[2])
        n = math.sqrt(ax * ax + ay * ay + az * az)
        zx, zy, zz = ax / n, ay / n, az / n
        cx, cy = math.cos(yaw), math.sin(yaw)
        yx, yy, yz = -zz * cy, zz * cx, zx * cy - zy * cx
        m = math.sqrt(yx * yx + yy * yy + yz * yz)
        yx, yy, yz = yx / m, yy / m, yz / m
        xx, xy, xz = yy * zz - yz * zy, yz * zx - yx * zz, yx * zy - yy * zx
        q = matrix_to_quat(np.array([[xx, yx, zx], [xy, yy, zy], [xz, yz, zz]]))
        thrust = n * hover_thrust / G
        return q, min(max(thrust, params["MPC_THR_MIN"]), 1.0)


class Px4Model:
    """Simulated PX4 autopilot + quadrotor: state machine and physics, stepped by its owner."""

    def __init__(
        self,
        config: Any,
        *,
        params: QuadParams | None = None,
        px4_params: Mapping[str, float] | None = None,
        initial_state: QuadState | None = None,
        initial_mode: str = "HOLD",
        noise: bool = True,
    ) -> None:
        self._cfg = config
        self.quad_params = params if params is not None else QuadParams.from_config(config)
        self.quad = Quadrotor(self.quad_params, initial_state)
        # Thread tick: at most 250 Hz (Python's budget); Quadrotor.step substeps to sim.rate inside a tick.
        self.dt = 1.0 / min(float(config.sim.rate), 250.0)
        self._rng = np.random.default_rng(int(config.sim.seed) + 4242)  # own stream: sim's other users
        sens = config.sim.sensors
        if not noise:  # perfect sensors: every noise and bias std zero
            sens = sens.model_copy(update=dict.fromkeys(type(sens).model_fields, 0.0))
        self.sensors = Sensors(sens, self._rng)
        self._wind = Wind(config.sim.wind, self._rng)

        self.params: dict[str, tuple[float, int]] = dict(DEFAULT_PX4_PARAMS)
        self.params["MPC_THR_HOVER"] = (self.quad_params.hover_thrust, REAL32)
        for name, value in (px4_params or {}).items():
            if name not in self.params:
                raise ValueError(f"SimPX4: unknown PX4 parameter {name!r} (known: {', '.join(self.params)})")
            self.params[name] = (float(value), self.params[name][1])

        self.lock = threading.RLock()
        self.cond = threading.Condition(self.lock)
        self.events: list[tuple[float, str]] = []
        self.out: Outbox = _NoLink()

        # Autopilot state (under lock).
        self.t = 0.0
        self.mode = "HOLD"
        self.armed = False
        self._armed_at = 0.0
        self._was_airborne = False
        self._landed_since: float | None = None
        self.sp_q_enu_flu: np.ndarray | None = None
        self.sp_thrust = 0.0
        self.sp_time = -math.inf
        self.sp_count = 0
        self.sp_rx_mono = math.nan
        self.cmd_q_enu_flu: np.ndarray | None = None  # the attitude and thrust commanded at the last tick
        self.cmd_thrust = 0.0
        s = self.quad.state
        self._hold_p = np.array(s.p, float)
        self._hold_yaw = self._yaw_of(s.q)
        self._takeoff_alt = 0.0
        if initial_mode not in POSITION_MODES:
            raise ValueError(f"SimPX4: initial_mode must be one of {', '.join(POSITION_MODES)} (got {initial_mode!r})")
        self.mode = initial_mode
        if not s.on_ground:  # a scenario that starts in the air starts armed and flying (else it would drop)
            self.armed = True
            self._was_airborne = True
        self._pos_ctrl = _PositionController()
        self.deny_arming = False
        self.deny_offboard = False
        self.fail_preflight = False  # SYS_STATUS reports the preflight checks failed; arming is refused
        self.obl_landed = False  # landed and disarmed by the offboard-loss fallback: refuses to arm (PX4 1.15)
        self._was_tko_detected = False
        self._obl_fallback = False  # flying the no-RC offboard-loss fallback (descend and land, shown as POSCTL)

    # ------------------------------------------------------------------------------ outside acts
    def set_param(self, name: str, value: float) -> None:
        if name not in self.params:
            raise KeyError(f"SimPX4: unknown PX4 parameter {name!r}")
        self.params[name] = (float(value), self.params[name][1])

    def force_disarm(self) -> None:
        """The kill switch (or a forced disarm from a ground station): motors off wherever the vehicle is."""
        if self.armed:
            self._disarm("force")

    def pilot_takeover(self, mode: str = "POSCTL") -> None:
        """The pilot flips the mode switch: PX4 leaves OFFBOARD and holds position (POSCTL/HOLD) or lands."""
        if mode not in ("POSCTL", "HOLD", "LAND"):
            raise ValueError(f"SimPX4.pilot_takeover: mode must be POSCTL, HOLD or LAND (got {mode!r})")
        self._set_mode(mode, "pilot")

    def accept_setpoint(self, q_enu_flu: np.ndarray, thrust: float, rx_mono: float) -> None:
        """An offboard attitude setpoint (xyzw body FLU -> ENU) arrived at time.monotonic() ``rx_mono``."""
        self.sp_q_enu_flu = q_enu_flu
        self.sp_thrust = min(max(float(thrust), 0.0), 1.0)
        self.sp_time = self.t
        self.sp_rx_mono = rx_mono
        self.sp_count += 1

    # --------------------------------------------------------------------------- internal: state
    def event(self, what: str) -> None:
        self.events.append((self.t, what))
        self.cond.notify_all()

    @staticmethod
    def _yaw_of(q_xyzw: np.ndarray) -> float:
        R = quat_to_matrix(q_xyzw)
        return math.atan2(R[1, 0], R[0, 0])  # heading of body x in ENU

    def _p(self, name: str) -> float:
        return self.params[name][0]

    def _set_mode(self, mode: str, why: str) -> None:
        if mode == self.mode:
            return
        s = self.quad.state
        if mode in POSITION_MODES or mode == "LAND":
            self._hold_p = np.array(s.p, float)
            self._hold_yaw = self._yaw_of(s.q)
        self.mode = mode
        self.event(f"mode:{mode}:{why}")
        if why in ("command", "pilot"):
            self.obl_landed = False  # another mode set: PX4's checks pass again
        # No heartbeat here: like PX4, the change shows at the next 1 Hz tick.

    def _arm(self) -> None:
        self.armed = True
        self._armed_at = self.t
        self._pos_ctrl = _PositionController()  # no integrator left over from the last flight
        self._was_airborne = False
        self._was_tko_detected = False
        self._landed_since = None
        self.event("arm")
        self.out.px4_event("commander_armed_by", LOG_INFO, 4)  # external command

    def _disarm(self, why: str) -> None:
        self.armed = False
        self.event(f"disarm:{why}")
        reason = {"auto_land": 6, "auto_preflight": 7, "failsafe": 14}.get(why, 4)
        self.out.px4_event("commander_disarmed_by", LOG_INFO, reason)
        if self.mode == "POSCTL" and self._obl_fallback:
            # PX4 1.15 after the offboard-loss landing: shows the user's mode (Offboard) again, refuses to arm.
            self._obl_fallback = False
            self.obl_landed = True
            self.mode = "OFFBOARD"
            self.event("mode:OFFBOARD:offboard_loss_landed")

    def _offboard_signal_ok(self) -> bool:
        return self.t - self.sp_time <= self._p("COM_OF_LOSS_T")

    # ---------------------------------------------------------------------------- physics + FSM
    def physics_step(self) -> None:
        q_cmd, thrust = self._control()
        self.cmd_q_enu_flu, self.cmd_thrust = q_cmd, thrust  # what PX4 streams as ATTITUDE_TARGET
        self.quad.step(self.dt, q_cmd, thrust, self._wind.step(self.dt))
        self.t += self.dt
        self._supervise()

    def _control(self) -> tuple[np.ndarray, float]:
        s = self.quad.state
        if not self.armed:
            return self._level_q(self._yaw_of(s.q)), 0.0
        mode = self.mode
        if mode == "OFFBOARD" and self.sp_q_enu_flu is not None:
            return self.sp_q_enu_flu, self.sp_thrust
        hover = self.quad_params.hover_thrust  # the converged hover-thrust estimate of a real PX4
        if s.on_ground and mode in ("HOLD", "POSCTL", "LAND"):
            return self._level_q(self._hold_yaw), self._p("MPC_THR_MIN")  # idle on the ground
        if mode == "TAKEOFF":
            ref = np.array([self._hold_p[0], self._hold_p[1], self._takeoff_alt])
            vz = min(self._pos_ctrl.K_POS_Z * (self._takeoff_alt - s.p[2]), self._p("MPC_TKO_SPEED"))
            return self._pos_ctrl.command(s, ref, self._hold_yaw, hover, self._param_values(), vz, self.dt)
        if mode == "LAND" or (mode == "POSCTL" and self._obl_fallback):
            ref = np.array([self._hold_p[0], self._hold_p[1], 0.0])
            slow = s.p[2] <= self._p("MPC_LAND_ALT2")
            vz = -self._p("MPC_LAND_SPEED") if slow else -self._p("MPC_Z_VEL_MAX_DN")
            return self._pos_ctrl.command(s, ref, self._hold_yaw, hover, self._param_values(), vz, self.dt)
        return self._pos_ctrl.command(s, self._hold_p, self._hold_yaw, hover, self._param_values(), None, self.dt)

    def _param_values(self) -> dict[str, float]:
        return {k: v[0] for k, v in self.params.items()}

    @staticmethod
    def _level_q(yaw: float) -> np.ndarray:
        return np.array([0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw)])

    def _supervise(self) -> None:
        """PX4's commander: failsafes, takeoff completion, landing detection, auto-disarm."""
        s = self.quad.state
        if self.armed and not s.on_ground:
            if not self._was_airborne:
                self._was_airborne = True
            self._landed_since = None
        if self.mode == "OFFBOARD" and self.armed and not self._offboard_signal_ok():
            self.event("failsafe:offboard_loss")
            act = int(self._p("COM_OBL_RC_ACT"))
            if act in (0, 1, 2):  # a manual-control mode, but no RC here: PX4 descends and lands
                self._set_mode("POSCTL", "failsafe")
                self._obl_fallback = True
                self.out.px4_event("commander_failsafe_enter_generic", LOG_CRITICAL, 0, 2 + act)
            elif act in (6, 7):
                self._set_mode("HOLD", "failsafe")
                self.out.px4_event("commander_failsafe_enter_generic", LOG_CRITICAL, 0, 10 if act == 6 else 9)
                self._disarm("failsafe")
            else:
                self._set_mode({3: "LAND", 4: "LAND"}.get(act, "HOLD"), "failsafe")
                self.out.px4_event("commander_failsafe_enter_generic", LOG_CRITICAL, 0, {3: 6, 4: 7}.get(act, 5))
        if self.mode == "TAKEOFF" and self.armed and not s.on_ground and not self._was_tko_detected:
            self._was_tko_detected = True
            self.out.px4_event("commander_takeoff_detected", LOG_INFO)
        if self.mode == "TAKEOFF" and s.p[2] >= self._takeoff_alt - 0.1:
            self._set_mode("HOLD", "takeoff_done")
            self._hold_p[2] = self._takeoff_alt  # PX4 loiters at the take-off altitude, not where it switched
        if self.armed and s.on_ground:
            if self._landed_since is None:
                self._landed_since = self.t
                if self._was_airborne:
                    self.event("touchdown")
                    self.out.px4_event("commander_landing_detected", LOG_INFO)
            if self._was_airborne and self.t - self._landed_since >= self._p("COM_DISARM_LAND"):
                self._disarm("auto_land")
            elif not self._was_airborne and self.t - self._armed_at >= self._p("COM_DISARM_PRFLT"):
                self._disarm("auto_preflight")

    # ------------------------------------------------------------------------- vehicle commands
    def execute(self, cmd: int, p: list[float]) -> int:
        """A vehicle command (arm/disarm, mode, take-off, land): its MAV_RESULT."""
        ok, denied = mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_DENIED
        s = self.quad.state
        if cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            force = nan_to(p[1], 0.0) == 21196.0
            if nan_to(p[0], 0.0) >= 0.5:
                if self.armed:
                    return ok
                if self.fail_preflight or self.obl_landed:
                    self.event("arm_denied:health" if self.obl_landed else "arm_denied:preflight")
                    self.out.px4_event("commander_arm_denied_resolve_failures", LOG_CRITICAL)  # no STATUSTEXT (PX4)
                    return denied
                if self.deny_arming:
                    self.event("arm_denied:switch")
                    self.out.statustext("Arming denied: preflight checks failed (simulated)")
                    return denied
                if not s.on_ground and not force:
                    self.event("arm_denied:in_air")
                    return denied
                self._arm()
                return ok
            if not self.armed:
                return ok
            if not s.on_ground and not force:
                self.out.px4_event("commander_disarm_denied_not_landed", LOG_CRITICAL)
                return denied
            self._disarm("force" if force else "command")
            return ok
        if cmd == mavlink.MAV_CMD_DO_SET_MODE:
            code = (int(nan_to(p[1], 0.0)), int(nan_to(p[2], 0.0)))
            mode = _MODE_BY_CODE.get(code)
            if mode is None and code[0] == 4 and code[1] == 0:
                mode = "HOLD"  # AUTO without a sub mode: PX4 picks its default (loiter here)
            if mode is None:
                self.event(f"mode_denied:{code[0]}.{code[1]}")
                return mavlink.MAV_RESULT_UNSUPPORTED
            return self._request_mode(mode)
        if cmd == mavlink.MAV_CMD_NAV_TAKEOFF:
            if not self.armed:
                self.out.statustext("Takeoff denied: disarmed")
                return denied
            alt_amsl = nan_to(p[6], math.nan)
            rel = alt_amsl - HOME_ALT if math.isfinite(alt_amsl) else self._p("MIS_TAKEOFF_ALT")
            self._takeoff_alt = max(rel, 0.5)
            self.event("takeoff")
            self._set_mode("TAKEOFF", "command")
            return ok
        if cmd == mavlink.MAV_CMD_NAV_LAND:
            self.event("land")
            self.out.px4_event("commander_landing_current_pos", LOG_INFO)
            return self._request_mode("LAND")
        return mavlink.MAV_RESULT_UNSUPPORTED

    def _request_mode(self, mode: str) -> int:
        s = self.quad.state
        if mode == "OFFBOARD":
            if self.deny_offboard:
                self.event("offboard_denied:switch")
                return mavlink.MAV_RESULT_DENIED
            if not self._offboard_signal_ok():
                self.event("offboard_denied:no_setpoints")
                self.out.statustext("Switching to Offboard is currently not available: no setpoints")
                return mavlink.MAV_RESULT_DENIED
        if mode == "TAKEOFF":
            if not self.armed:
                return mavlink.MAV_RESULT_DENIED
            self._takeoff_alt = self._p("MIS_TAKEOFF_ALT")
        if mode == "LAND" and s.on_ground and not self.armed:
            pass  # PX4 accepts LAND on the ground; nothing to do
        self._set_mode(mode, "command")
        return mavlink.MAV_RESULT_ACCEPTED
