"""A simulated PX4: a MAVLink 2 endpoint (pymavlink) around the quadrotor simulator.

It behaves like PX4 where this app depends on it, so the real ``mavsdk`` library can fly it over
UDP on localhost. Run in-process (``SimPX4``, a context manager with its own thread) or as a
separate process (``python -m companion.sim.px4 --port 0``: prints ``PORT <n>`` on stdout, reads
switch commands from stdin, stops on SIGTERM/SIGINT or ``quit``).

Public API (names are stable; the flight app and its tests rely on them)::

    SimPX4(config=None, *, port=0, remote_port=0, params=None, px4_params=None, initial_state=None,
           initial_mode="HOLD", heartbeat_hz=1.0, telemetry_hz=50.0, noise=True)
    (an initial_state in the air starts armed, holding in initial_mode: HOLD or POSCTL)
    .start() / .stop() / context manager
    .port, .remote_port, .url_for_mavsdk ("udpin://127.0.0.1:REMOTE", as with PX4 SITL on 14540;
    remote_port=None: "udpout://127.0.0.1:PORT", which makes mavsdk bind 0.0.0.0)
    .truth() -> QuadState copy (ground truth, ENU/FLU)
    .mode (str: POSCTL, HOLD, TAKEOFF, LAND, OFFBOARD), .armed, .landed, .time (sim s)
    .events -> list[(t, what)] copy; .wait_event(prefix, timeout, since=-inf) / .wait_for(pred, timeout)
    .param(name) / .set_param(name, value)
    .setpoint_count, .last_setpoint() -> (t, q_xyzw ENU/FLU, thrust), .stats(), .monotonic_of(t_sim)
    switches: .deny_arming, .deny_offboard, .fail_preflight (bool attributes), .drop_link(on), .silence_commands(on),
              .pilot_takeover(mode="POSCTL"), .force_disarm(), .corrupt_attitude(on)
    process stdin (one reply line each): deny_arming 0|1, deny_offboard 0|1, fail_preflight 0|1,
              drop 0|1, silence 0|1,
              takeover MODE, kill, nan_attitude 0|1, param NAME VALUE, state, events, wait_event PREFIX SECONDS, quit

Events (``what`` strings, ``kind:detail``): ``mode:<MODE>:<why>`` (why = command, failsafe,
takeoff_done, pilot, offboard_loss_landed), ``mode_denied:<main>.<sub>``, ``arm``, ``disarm:<why>`` (command,
force, auto_land, auto_preflight, failsafe), ``arm_denied:<why>`` (switch, preflight, in_air, health),
``offboard_denied:<why>`` (no_setpoints, switch), ``failsafe:offboard_loss``, ``takeoff``, ``land``, ``touchdown``,
``command:<id>``, ``silenced:<id>``, ``param_set:<NAME>``, ``link:dropped``, ``link:restored``.

Like PX4 v1.15 SITL (each point checked against the real build in ../shared/px4-sitl, SIH quad):
HEARTBEAT at 1 Hz and nothing extra on a change, so a mode or arming change is seen 0.2-1.0 s after
it happens (``heartbeat_hz`` is a test switch; the default is PX4's); PX4's failsafe defaults
(``COM_OF_LOSS_T`` 1 s, ``COM_OBL_RC_ACT`` 0 = Position mode, ``COM_RC_IN_MODE`` 1, no RC connected:
the offboard-loss fallback reports POSCTL in the heartbeat, descends at ``MPC_LAND_SPEED`` and lands,
auto-disarms, then shows OFFBOARD again and refuses to arm ("Resolve system health failures first")
until another mode is commanded); PX4 *events* (MAVLink EVENT with PX4's own event ids and
arguments, decoded by companion/app/px4events.py) for arming, disarming, take-off, landing,
failsafes and refusals, besides a few STATUSTEXT lines. Like PX4 SITL it sends to a fixed port on
127.0.0.1 (``remote_port``; 0 picks a free one) so mavsdk listens with ``udpin://127.0.0.1:PORT``
(``url_for_mavsdk``) and nothing binds all interfaces; its own socket binds 127.0.0.1 only.

Where it departs from PX4 (on purpose): its own modes (takeoff, hold, position, land) fly a
cascaded P (position) / PI (velocity) controller on ground truth with the true hover thrust (PX4
flies its EKF and a hover-thrust estimate); the attitude estimate, IMU and barometer come from
companion/sim/sensors.py (truth + per-run bias + noise). OFFBOARD needs an attitude setpoint
(SET_ATTITUDE_TARGET) in the last ``COM_OF_LOSS_T``; other setpoint types are ignored. Besides
``remote_port`` it answers whoever sent it a datagram in the last 5 s (MAVSDK heartbeats every
second); a client that stays silent longer is forgotten. No RC: ``NAV_RCL_ACT`` is never triggered.

Modules: ``model`` (the autopilot's behaviour: parameters, modes, arming, failsafes, own-mode flight),
``wire`` (MAVLink I/O: the socket, decoding, telemetry), ``realtime`` (``SimPX4``: the thread and
clock, the thread-safe public face), ``cli`` (the process entry point), ``bench`` (a benchmark with
the flight app's link).
"""

from companion.sim.px4.model import DEFAULT_PX4_PARAMS
from companion.sim.px4.realtime import SimPX4

__all__ = ["DEFAULT_PX4_PARAMS", "SimPX4"]
