"""The flight core: what every loop needs per camera frame, built from the config in one place.

One pure, clock-driven object around the engagement (companion/engagement.py): the PN controller it steers,
the in-flight hover-thrust estimate (companion/hover.py), the tracker reset at a new engagement phase and the
count of confirmed passes. The flight app, shadow mode, replay and the in-process simulator are thin loops
around it (source -> perceive -> ``FlightCore.step`` -> sink), so none of them can compute something the
others do not::

    frame + box ----------------+
    attitude at capture --------+--> FrameInput --> FlightCore.step --> CoreStep
    baro, link events, IMU -----+                                        (decision: phase, setpoint, events;
                                                                          reset_tracker; passes; hover)

It sees no position, no velocity, no truth (``FrameInput``'s fields are the proof) and no wall clock: the
caller brings the frame's capture time and the time it is processed (``t_now``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from companion.engagement import Decision, Engagement, EngagementParams, LinkEvent, Phase, Steering
from companion.hover import HoverEstimate, HoverThrustEstimator, thrust_specific_force, use_hover_thrust
from perception.fastinit import fast_init
from perception.types import BoundingBox

if TYPE_CHECKING:
    from companion.config import Config


# Phase.commanding's phases, as a tuple (membership by identity: no property call, every frame).
_COMMANDING = tuple(p for p in Phase if p.commanding)


@fast_init
@dataclass(frozen=True, slots=True)
class ImuReading:
    """One accelerometer sample: its time (same clock as the frames) and the specific force, body FRD, m/s^2."""

    t: float
    accel_frd: np.ndarray


@fast_init
@dataclass(frozen=True, slots=True)
class FrameInput:
    """Everything the core may know of one camera frame."""

    t: float  # capture time, s (any monotonic clock)
    box: BoundingBox | None  # the tracker's box, None when there is none
    q_wxyz_ned_frd: np.ndarray  # attitude estimate at capture time
    baro_rel_alt: float | None = None  # barometric altitude above the reference (take-off), m; None: unknown
    events: tuple[LinkEvent, ...] = ()  # link / pilot events since the last frame
    accel_frd: np.ndarray | None = None  # accelerometer for the controller (closing speed, drag), None: not used
    t_now: float | None = None  # when the frame is processed (its age = t_now - t), None: not known
    imu: ImuReading | None = None  # the newest IMU sample, for the hover-thrust estimate
    confirm: bool | None = None  # the operator's confirmation (app.engage confirm, companion/confirm.py); None: auto


@fast_init
@dataclass(frozen=True, slots=True)
class CoreStep:
    decision: Decision
    # The tracker must drop its target: a new engagement phase began (RECOVER: the passed gate), or the engagement
    # refused its box several frames in a row (it holds another object; EngagementParams.drop_tracker_after).
    reset_tracker: bool = False
    # The tracker must look past its candidate: verification refused it several frames in a row at ACQUIRE
    # (perception/pipeline.py ``refuse``).
    refuse_candidate: bool = False
    passes_confirmed: int = 0
    hover: HoverEstimate | None = None  # a new hover-thrust estimate taken this step (for the log)
    hover_input: tuple[float, float] | None = None  # (commanded thrust, specific force up m/s^2) behind it

    def tell_tracker(self, perception: object) -> None:
        """What this step asks of the perception that made its box (a pipeline, or a camera holding one): look past
        a refused candidate, or forget the target (a passed gate, another object held). Every loop calls this;
        perception without a tracker has neither method."""
        if self.refuse_candidate and (refuse := getattr(perception, "refuse", None)) is not None:
            refuse()
        elif self.reset_tracker and (reset := getattr(perception, "reset", None)) is not None:
            reset()
        if (acquiring := getattr(perception, "acquiring", None)) is not None:
            acquiring(self.decision.phase is Phase.ACQUIRE)  # other candidates weighed at full resolution


@dataclass
class FlightCore:
    """Controller + engagement + hover estimate, stepped once per frame. Pure."""

    cfg: Config
    controller: Steering
    engagement: Engagement
    hover_estimator: HoverThrustEstimator | None = None
    _hover_u: float | None = field(default=None, repr=False)  # the thrust commanded since the last setpoint

    @classmethod
    def from_config(cls, cfg: Config, hover_thrust: float | None = None,
                    controller: Steering | None = None) -> FlightCore:
        """The core for ``cfg``; ``hover_thrust``: the autopilot's (MPC_THR_HOVER) instead of the airframe's;
        ``controller``: another steering (the simulator's ablations), else ``PNController.from_config(cfg)``."""
        from companion.controller import PNController

        if controller is None:
            controller = PNController.from_config(cfg)
            if hover_thrust is not None:
                controller = controller.with_hover_thrust(hover_thrust, cfg.airframe.thrust_to_weight)
        p = getattr(controller, "p", None)
        if p is not None and hasattr(p, "hover_thrust"):  # the controller's thrust model (the autopilot's hover)
            params = EngagementParams.from_config(cfg, hover_thrust=p.hover_thrust, f_min=p.guidance.f_min,
                                                  f_max=p.guidance.f_max)
        else:  # an ablation wrapper or the baseline: the airframe's numbers
            params = EngagementParams.from_config(cfg)
        core = cls(cfg, controller, Engagement.from_config(cfg, controller, params))
        core.hover_estimator = core._new_hover_estimator()
        return core

    def _new_hover_estimator(self) -> HoverThrustEstimator | None:
        p = getattr(self.controller, "p", None)
        if not self.cfg.hover.estimate or p is None or not hasattr(p, "hover_thrust"):
            return None  # off, or a steering without a hover thrust (the velocity-based baseline)
        return HoverThrustEstimator(p.hover_thrust, self.cfg.hover)

    # -- the step --------------------------------------------------------------------------------------
    def step(self, inp: FrameInput) -> CoreStep:
        d = self.engagement.step(inp.t, inp.box, inp.q_wxyz_ned_frd, inp.baro_rel_alt, inp.events,
                                 accel_frd=inp.accel_frd, t_now=inp.t_now, confirm=inp.confirm)
        hover = hover_input = None
        if d.setpoint is not None and d.phase in _COMMANDING:
            a_up = None
            if inp.imu is not None and self.hover_estimator is not None:
                # The frame's attitude (capture time) with the newest IMU sample: the tilt moves little between.
                a_up = thrust_specific_force(inp.imu.accel_frd, self.engagement.frame_attitude(), self.cfg.hover)
                if self._hover_u is not None:
                    hover_input = (self._hover_u, a_up)
            hover = self._hover_update(inp.imu, d.setpoint.thrust, a_up)
        reset = (d.changed and d.phase is Phase.RECOVER) or self.engagement.drop_tracker
        eng = self.engagement
        # Positional (the field order of CoreStep): keywords cost a fast_init __init__ a dict per frame. No pass
        # yet: 0 confirmed, without the count's generator (every frame until the first pass).
        return CoreStep(d, reset, eng.refuse_candidate, eng.passes_confirmed if eng.passes else 0, hover,
                        hover_input if hover is not None else None)

    def _hover_update(self, imu: ImuReading | None, thrust: float, a_up: float | None) -> HoverEstimate | None:
        """hover.estimate: the IMU's specific force against the thrust commanded since the last setpoint; the
        controller, the pass and the recovery fly with the estimate from then on."""
        h, est = self.hover_estimator, None
        if h is not None:
            if imu is not None and self._hover_u is not None and a_up is not None:
                est = h.update(imu.t, self._hover_u, a_up)  # the thrust's specific force (FRD -z, drag removed)
                if est is not None:
                    use_hover_thrust(self.controller, est.hover_thrust, self.cfg.airframe.thrust_to_weight,
                                     self.engagement)
            self._hover_u = thrust
        return est

    def restart(self) -> None:
        """A fresh engagement after one ended (shadow mode: the pilot may fly the gates again). The hover
        thrust learnt so far stays; the controller's filters start again."""
        self.controller.reset()
        self.engagement = Engagement.from_config(self.cfg, self.controller, self.engagement.params)

    # -- what the loops read ---------------------------------------------------------------------------
    @property
    def phase(self) -> Phase:
        return self.engagement.phase

    @property
    def passes_confirmed(self) -> int:
        return self.engagement.passes_confirmed

    @property
    def hover_thrust(self) -> float:
        return self.engagement.params.hover_thrust
