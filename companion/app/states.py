"""The flight app's one explicit state machine: states, allowed transitions, outcomes.

Normal flight::

    INIT -> CONNECT -> PREFLIGHT -> ARM -> TAKEOFF ----------+
                                 \\-> WAIT_PILOT (start=pilot) +-> ACQUIRE -> ENGAGE -> PASS -> RECOVER
    RECOVER -> ENGAGE (next gate tracked)  |  RECOVER -> HANDBACK -> LAND -> SAFE_LANDED

Every fault leaves for exactly one named safe state (terminal), with a ``Reason`` whose value is
the process exit code, so a script or systemd sees what happened without reading the log.
"""

from __future__ import annotations

import enum
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TextIO

from companion.reasons import Reason


class State(enum.Enum):
    INIT = "INIT"
    CONNECT = "CONNECT"
    PREFLIGHT = "PREFLIGHT"
    ARM = "ARM"
    TAKEOFF = "TAKEOFF"
    WAIT_PILOT = "WAIT_PILOT"  # start=pilot: the pilot arms and hovers, we wait
    ACQUIRE = "ACQUIRE"  # PX4 holds; we look for a stable track
    ENGAGE = "ENGAGE"  # offboard, PN
    PASS = "PASS"  # gate close: hold the last attitude until it leaves the view
    RECOVER = "RECOVER"  # offboard, level attitude, hover thrust
    HANDBACK = "HANDBACK"  # offboard stop -> PX4 HOLD
    LAND = "LAND"
    # Terminal safe states.
    SAFE_LANDED = "SAFE_LANDED"  # on the ground, disarmed
    SAFE_HOLD = "SAFE_HOLD"  # we stopped offboard; PX4 holds (pilot/operator decides what next)
    SAFE_PILOT = "SAFE_PILOT"  # the pilot took over; we stopped commanding and never re-enter offboard
    SAFE_FAILSAFE_LINK = "SAFE_FAILSAFE_LINK"  # link lost: we stopped streaming, PX4's own failsafe acts
    ABORT_NOT_ARMED = "ABORT_NOT_ARMED"  # never left the ground (connect/preflight/arm failed)
    # Terminal states that name what the autopilot reports when none of the above is true of the vehicle.
    REFUSED = "REFUSED"  # found armed or in the air at start (start=takeoff): the app commanded nothing
    DISARMED = "DISARMED"  # disarmed in flight, not by the app (kill switch, forced disarm, PX4)
    AUTOPILOT = "AUTOPILOT"  # PX4 flies a mode of its own (named in the reason); Hold was not confirmed

    @property
    def terminal(self) -> bool:
        return self in SAFE_STATES

    @property
    def offboard(self) -> bool:
        """States in which the app streams setpoints to PX4."""
        return self in (State.ENGAGE, State.PASS, State.RECOVER)


SAFE_STATES = frozenset(
    {State.SAFE_LANDED, State.SAFE_HOLD, State.SAFE_PILOT, State.SAFE_FAILSAFE_LINK, State.ABORT_NOT_ARMED,
     State.REFUSED, State.DISARMED, State.AUTOPILOT}
)


_NORMAL: dict[State, frozenset[State]] = {
    State.INIT: frozenset({State.CONNECT}),
    State.CONNECT: frozenset({State.PREFLIGHT}),
    State.PREFLIGHT: frozenset({State.ARM, State.WAIT_PILOT}),
    State.ARM: frozenset({State.TAKEOFF}),
    State.TAKEOFF: frozenset({State.ACQUIRE}),
    State.WAIT_PILOT: frozenset({State.ACQUIRE}),
    State.ACQUIRE: frozenset({State.ENGAGE, State.LAND}),
    # HANDBACK from any offboard state: an abort stops offboard (PX4 HOLD brakes) before the safe state.
    State.ENGAGE: frozenset({State.PASS, State.RECOVER, State.HANDBACK}),
    State.PASS: frozenset({State.RECOVER, State.HANDBACK}),
    State.RECOVER: frozenset({State.ENGAGE, State.HANDBACK}),
    State.HANDBACK: frozenset({State.LAND, State.SAFE_HOLD}),
    State.LAND: frozenset({State.SAFE_LANDED}),
}
# Before the vehicle is armed, a failure can only mean "not armed"; once it may fly, any safe state but that.
_GROUND = frozenset({State.INIT, State.CONNECT, State.PREFLIGHT, State.ARM})
_AIR_SAFE = SAFE_STATES - {State.ABORT_NOT_ARMED, State.REFUSED}

TRANSITIONS: dict[State, frozenset[State]] = {
    s: _NORMAL.get(s, frozenset()) | (
        frozenset() if s.terminal else
        (frozenset({State.ABORT_NOT_ARMED, State.SAFE_HOLD, State.SAFE_LANDED, State.AUTOPILOT, State.SAFE_PILOT,
                    State.DISARMED}) if s in _GROUND else _AIR_SAFE)
    )
    for s in State
}
# Found armed or airborne at pre-flight: refused before any command.
TRANSITIONS[State.PREFLIGHT] |= {State.REFUSED}
# Arming can succeed and the take-off then be refused: the vehicle is armed on the ground.
TRANSITIONS[State.ARM] |= {State.SAFE_LANDED}
# The link lost after an arm command went out and not back: PX4's arming state is unknown, and "not armed" would
# be a claim nobody can check (an ARM sent into an outage reaches PX4 when the link returns).
TRANSITIONS[State.ARM] |= {State.SAFE_FAILSAFE_LINK}


@dataclass(frozen=True)
class VehicleView:
    """What the autopilot last reported, for checking a terminal state's claim against it."""

    armed: bool | None
    mode: str | None
    landed: str | None
    link_ok: bool


def contradiction(dst: State, view: VehicleView, history: list[Transition]) -> str | None:
    """Why the vehicle's reported state contradicts what ``dst`` claims (None: it does not).

    "Not armed" after an arm command needs a live link that shows disarmed; "landed"/"disarmed" never holds of
    a vehicle reported armed. The other states name a mode the callers have just seen.
    """
    if dst is State.ABORT_NOT_ARMED:
        if view.armed is True:
            return "PX4 reports the vehicle armed"
        if any(h.dst is State.ARM for h in history) and not (view.link_ok and view.armed is False):
            return "an arm command was sent and no live telemetry shows the vehicle disarmed"
    if dst in (State.SAFE_LANDED, State.DISARMED) and view.armed is True:
        return "PX4 reports the vehicle armed"
    return None


class IllegalTransition(RuntimeError):
    """A programming error: the app tried a transition the table does not allow."""


@dataclass(frozen=True)
class Transition:
    t: float
    src: State
    dst: State
    reason: str


@dataclass
class StateMachine:
    """Holds the current state; every change goes through ``go`` and is reported to the sinks with a reason."""

    clock: Callable[[], float]
    sinks: list[Callable[[Transition], None]] = field(default_factory=list)
    stderr: TextIO | None = sys.stderr
    state: State = State.INIT
    history: list[Transition] = field(default_factory=list)
    outcome: Reason | None = None
    # What the autopilot reports now (None: nothing known yet); a terminal state it contradicts is refused.
    vehicle: Callable[[], VehicleView | None] | None = None

    def go(self, dst: State, reason: str, outcome: Reason | None = None) -> Transition:
        if dst not in TRANSITIONS[self.state]:
            raise IllegalTransition(f"state machine: {self.state.value} -> {dst.value} is not allowed ({reason})")
        view = self.vehicle() if self.vehicle is not None and dst.terminal else None
        why = contradiction(dst, view, self.history) if view is not None else None
        if why is not None:
            raise IllegalTransition(f"state machine: {dst.value} is not true of the vehicle: {why} ({reason})")
        tr = Transition(self.clock(), self.state, dst, reason)
        self.state = dst
        self.history.append(tr)
        if dst.terminal:
            self.outcome = outcome if outcome is not None else Reason.OK
        for sink in self.sinks:
            sink(tr)
        if self.stderr is not None and (dst.terminal or outcome is not None):
            code = ""
            if dst.terminal and self.outcome is not None:
                code = f" (exit {self.outcome.value} {self.outcome.name})"
            print(f"companion: {tr.src.value} -> {dst.value}: {reason}{code}", file=self.stderr, flush=True)
        return tr

    @property
    def done(self) -> bool:
        return self.state.terminal

    def path(self) -> list[State]:
        return [self.state if not self.history else self.history[0].src] + [h.dst for h in self.history]


# States before the vehicle may fly: a failure there can only mean "not armed" (or found armed).
GROUND_STATES = frozenset({State.INIT, State.CONNECT, State.PREFLIGHT, State.ARM})
# Modes a pilot selects (mavsdk FlightMode names); any other mode we did not ask for is PX4's own choice.
PILOT_MODES = frozenset({"POSCTL", "ALTCTL", "MANUAL", "STABILIZED", "ACRO", "RATTITUDE"})
# Modes the vehicle may show while the app is in a state; anything else is noticed (companion/app/states.py).
EXPECTED_MODES: dict[State, frozenset[str]] = {
    State.TAKEOFF: frozenset({"TAKEOFF", "HOLD"}),
    State.ACQUIRE: frozenset({"HOLD"}),
    State.ENGAGE: frozenset({"HOLD", "OFFBOARD"}),  # HOLD until PX4 confirms OFFBOARD at the first engage
    State.PASS: frozenset({"OFFBOARD"}),
    State.RECOVER: frozenset({"OFFBOARD"}),
    State.HANDBACK: frozenset({"OFFBOARD", "HOLD"}),
    State.LAND: frozenset({"LAND", "HOLD"}),  # HOLD until PX4 shows the LAND we commanded
}
