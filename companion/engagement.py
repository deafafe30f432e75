"""The engagement: every decision between "a gate may be in view" and "hand the vehicle back", pure.

One object, stepped once per camera frame (the frame's capture time, its box or None, the attitude
estimate at that time, the barometric altitude above take-off, link/pilot events). It returns a
``Decision``: the phase, the setpoint to stream (or None: we do not command), the outcome when the
engagement ends, the reason of a phase change, and gate events. It sees no position, no velocity,
no truth: ``Engagement.step``'s signature is the proof. The flight app (companion/app/flight.py),
the in-process simulator (companion/sim/runner.py) and replay (companion/replay.py) all run it, so
every study measures the decisions that fly.

Phases::

    ACQUIRE --stable track (acquire_frames valid boxes in a row)--> ENGAGE     (PX4 holds until then)
    ACQUIRE --no stable track within acquire_timeout--> LAND (NO_TARGET)
    ENGAGE  --close (time-to-contact or box size; or the box lost when nearly close)--> PASS
                                                      (on_close=fly_through)
                                                 \\-> RECOVER (on_close=pull_up: nose up, brake, climb)
    PASS    --evidence: the box gone, or far smaller (the next gate behind)--> RECOVER, pass confirmed
            --pass_timeout without evidence--> RECOVER, pass NOT confirmed (never counted as passed)
    RECOVER --recover_time, next gate tracked (a new one)--> ENGAGE
            --recover_time--> HANDBACK (OK)
    ENGAGE / PASS / RECOVER --abort--> ABORT (TARGET_LOST, MAX_ENGAGEMENT, ALTITUDE_FLOOR,
                                              PILOT_TAKEOVER, LINK_LOST)

The pass flies straight (``guidance.straight_pass``): zero PN demand, the last PN attitude never held; with
the controller's drag estimate (accelerometer) the thrust cancels gravity and drag, so the velocity PN set
up is kept (a draggy vehicle otherwise loses its lateral speed in the pass), else level flight with the
optical axis on the last filtered LOS.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Literal, Protocol

import numpy as np

from companion import guidance
from companion.frames import R_from_euler_ned_deg, R_from_quat_wxyz, euler_ned_deg_from_R, swap_ned_enu
from companion.growthcheck import GrowthCheck, GrowthParams
from companion.guidance import Setpoint
from companion.limits import CloseDetector, SafetyLimits
from companion.pullup import PullUpParams, PullUpPlanner, arrest_loss
from companion.reasons import Reason
from companion.rival import RivalWatch
from companion.targetlock import TargetLock
from companion.verify import TargetVerifier, VerifyParams
from perception.fastinit import fast_init
from perception.types import BoundingBox

if TYPE_CHECKING:
    from companion.config import Config
    from companion.config_app import AppConfig, SafetyConfig


class Phase(enum.Enum):
    ACQUIRE = "ACQUIRE"  # PX4 holds; looking for a stable track
    ENGAGE = "ENGAGE"  # PN on the box
    PASS = "PASS"  # gate close: flying straight through it until it is behind
    RECOVER = "RECOVER"  # level, a little above hover thrust; maybe the next gate
    HANDBACK = "HANDBACK"  # end: stop commanding, PX4 holds (outcome OK)
    LAND = "LAND"  # end: never engaged (NO_TARGET); PX4 holds and lands
    ABORT = "ABORT"  # end: an abort decision (reason in Decision.reason)

    @property
    def done(self) -> bool:
        return self in (Phase.HANDBACK, Phase.LAND, Phase.ABORT)

    @property
    def commanding(self) -> bool:
        """Phases in which a setpoint is streamed (offboard)."""
        return self in (Phase.ENGAGE, Phase.PASS, Phase.RECOVER)


LinkEvent = Literal["offboard_lost", "disarmed", "link_lost"]
PassStatus = Literal["engaged", "confirmed", "not_confirmed", "pulled_up"]


class Steering(Protocol):
    """What the engagement needs of a controller: ``PNController`` (or an ablation wrapped like it)."""

    def step(self, t: float, box: BoundingBox | None, q_wxyz_ned_frd: np.ndarray,
             accel_frd: np.ndarray | None = None, t_now: float | None = None) -> object: ...

    def reset(self) -> None: ...

    @property
    def closing_rate(self) -> tuple[float, float] | None:
        """The closing-speed filter's (range rate, its std dev) in m/s, or None (no filter): the target lock's
        speed bound."""

    @property
    def closing_estimate(self) -> tuple[float, float, float | None] | None:
        """The closing-speed filter's (range m, range rate m/s, time of its last range from a box), or None."""


@fast_init
@dataclass(frozen=True, slots=True)
class EngagementParams:
    acquire_frames: int
    acquire_timeout: float  # s
    on_close: Literal["fly_through", "pull_up"]
    pass_timeout: float  # s; longest PASS without evidence
    recover_time: float  # s
    recover_thrust_scale: float
    pull_up_pitch: float  # deg
    next_gate: bool
    max_gates: int
    hover_thrust: float  # 0..1
    thrust_min: float  # 0..1
    f_min: float  # m/s^2, mass-normalised thrust limits (the straight pass stays inside)
    f_max: float
    width: int  # image size, px
    height: int
    max_tilt: float = math.pi / 2  # rad; the straight pass stays inside the airframe's tilt envelope
    pass_gone_frames: int = 3  # frames of evidence that the gate is behind
    pass_shrink: float = 0.5  # a box this much smaller than the pass's largest is another gate (behind)
    complete_boxes: bool = True  # boxes cut by one image border are completed to a round gate
    near_factor: float = 2.0  # the box lost within this factor of a close trigger: the pass has begun
    # ...and only if its last box spanned at least this much of the image width: a ring is lost as it fills the view.
    # Of 120 "lost while close" passes in PX4 SITL logs, 118 had a last box of >= 0.48 of the width; the two at 0.11
    # (a time-to-contact of 0.46-0.50 s read from a box jump, the gate leaving the top of the image 9 m out) were
    # claimed passes of gates never reached.
    lost_min_size: float = 0.25
    # ...where "its last box" is the largest of the gate's boxes in this window before the loss. A ring passed by a
    # slow vehicle leaves the view across a border: its cut box shrinks (0.81 -> 0.31 of the width in 0.2 s on
    # PX4's SIH quad), the lock rejects the last sliver, and the gate was never "close" by either trigger: 11 of 32
    # SIH flights through the gate ended TARGET_LOST, the vehicle coasting tilted behind it for 1 s.
    near_window: float = 0.5  # s
    # The engaged gate's boxes refused this many frames in a row (verification or lock): the tracker holds another
    # object, and is told to drop it (``drop_tracker``; 0 = never). Perception hands over one box a frame; on real
    # PX4 (x500, linear fast, runs 012 and 092 of a 100-run table) its track went to the ground below for 0.4-1.0 s
    # while the gate stayed in view, the lock refused every box, and the engagement ended TARGET_LOST.
    drop_tracker_after: int = 3
    pass_keeps_velocity: bool = True  # the pass cancels the measured drag (keeps the velocity) when it is known
    # A box edge this close to the image border is cut. A detector's edges are noisy (1 px in the simulator):
    # at 1 px a ring on the border was completed in one frame and not in the next, and its LOS jumped by tens of
    # pixels (roll-setpoint RMS rate 142 -> 99 deg/s on SIH, 156 -> 111 on the x500 with 3 px).
    cut_edge_px: float = 3.0
    frame_rate: float = 30.0  # Hz, the camera's configured rate (the close detector's window)
    # Close on the filter's dead-reckoned time-to-contact while the image gives it no range (app.close_reckoning),
    # for at most reckon_max s after its last range: the IMU's drift is not trusted longer.
    reckon_close: bool = False
    reckon_max: float = 1.0  # s
    reckon_ttc: float = 0.0  # s: close when the dead-reckoned time-to-contact is at most this...
    # ...to a sphere of this radius about the gate's centre, m (from_config: half the ring's radius). A pass off the
    # centre crosses the plane at a range of its offset, never 0: on the in-process SIH the closes that still came
    # more than 0.2 s after the crossing were such passes (5 of 88 at 0 m, 2 at half the radius).
    reckon_range: float = 0.0

    @classmethod
    def from_config(cls, cfg: Config, hover_thrust: float | None = None, f_min: float | None = None,
                    f_max: float | None = None) -> EngagementParams:
        """From the config; thrust numbers default to the airframe's (the app passes the autopilot's)."""
        a = cfg.app
        # A synthetic course has app.synthetic.count gates: what lies beyond is background, not a next gate (the
        # cap a field user sets with app.max_gates for a known course).
        max_gates = min(a.max_gates, a.synthetic.count) if a.camera == "synthetic" else a.max_gates
        return cls(a.acquire_frames, a.acquire_timeout, a.on_close, a.pass_timeout, a.recover_time,
                   a.recover_thrust_scale, a.pull_up_pitch, a.next_gate, max_gates,
                   cfg.airframe.hover_thrust if hover_thrust is None else hover_thrust, cfg.airframe.thrust_min,
                   cfg.airframe.f_min if f_min is None else f_min, cfg.airframe.f_max if f_max is None else f_max,
                   cfg.camera.width, cfg.camera.height, math.radians(cfg.airframe.max_tilt),
                   frame_rate=cfg.camera.rate, reckon_close=a.close_reckoning,
                   reckon_range=0.5 * cfg.guidance.gate_radius)


@dataclass
class GatePass:
    """One engaged gate, as the engagement saw it (the camera's evidence; truth is judged elsewhere)."""

    gate: int  # 1, 2, ... in engagement order
    t_engage: float
    status: PassStatus = "engaged"
    t_close: float | None = None
    t_end: float | None = None
    evidence: str = ""

    def as_dict(self) -> dict:
        return {"gate": self.gate, "status": self.status, "t_engage": self.t_engage, "t_close": self.t_close,
                "t_end": self.t_end, "evidence": self.evidence}


@fast_init
@dataclass(frozen=True, slots=True)
class Decision:
    t: float
    phase: Phase
    setpoint: Setpoint | None  # None: nothing to stream (ACQUIRE: PX4 holds; an end: stop commanding)
    control: object | None = None  # the controller's output when it ran (ENGAGE), for the log
    why: str = ""  # reason of the phase change in this step ("" if none)
    previous: Phase | None = None  # the phase before this step, when it changed
    reason: Reason | None = None  # the outcome of an end phase (OK, NO_TARGET, an abort)
    events: tuple[str, ...] = ()  # gate events of this step ("gate 1 engaged", "gate 1 passed (...)", ...)

    @property
    def changed(self) -> bool:
        return self.previous is not None


@dataclass
class Engagement:
    """The engagement state machine around one controller. Pure: the caller brings time and inputs."""

    params: EngagementParams
    controller: Steering
    close: CloseDetector
    limits: SafetyLimits
    phase: Phase = Phase.ACQUIRE
    passes: list[GatePass] = field(default_factory=list)
    _t0: float | None = None
    _streak: int = 0  # consecutive valid boxes
    _t_phase: float = 0.0  # when the current phase began
    _engage_start: float = 0.0
    _last_valid: float = 0.0
    _los_ned: np.ndarray | None = None  # the last filtered LOS of the engagement (NED; ENU when read: _los_enu)
    _sp: Setpoint | None = None  # the held setpoint of PASS / RECOVER
    _peak: float = 0.0  # largest box side during the pass, px
    _gone: int = 0  # frames of "gate behind" evidence
    _old_gone: bool = True  # the last engaged gate has left the view (a track now is a new gate)
    _imu: tuple[np.ndarray | None, float | None] = (None, None)  # this step's accelerometer and time now
    _last_size: float = 0.0  # larger side of the last box the controller used, px
    lock: TargetLock | None = None  # is a box still the engaged gate (companion/targetlock.py); None = no check
    _rejecting: bool = False  # the last box was rejected by the lock (one event per spell)
    verifier: TargetVerifier | None = None  # is a box the configured target (companion/verify.py); None = no check
    _unverified: bool = False  # the last box failed verification (one event per spell)
    _rejected_now: bool = False  # this frame's box was rejected (verification or lock): a box is in view
    _refused_as_target: bool = False  # this frame's box failed verification's own rules (not the lock's one-object)
    refused: int = 0  # ENGAGE frames in a row whose box was refused (verification or lock); frames without a box pass
    drop_tracker: bool = False  # this step: the tracker holds another object (drop_tracker_after refusals): drop it
    # ACQUIRE frames in a row whose candidate verification refused as not the target (its own rules, not the lock's
    # "not one object"), and, this step, that the tracker is to look past it (every drop_tracker_after of them)
    refused_candidate: int = 0
    refuse_candidate: bool = False
    used_box: BoundingBox | None = None  # the box this step's decisions used (None: none, or rejected)
    awaiting: bool = False  # a stable candidate waits for the operator's confirmation (app.engage confirm)
    _confirm: bool | None = None  # this step's confirmation (None: not needed)
    pullup: PullUpPlanner | None = None  # on_close=pull_up: when to pull up and how (companion/pullup.py)
    # Does the engaged box grow as our own acceleration towards it says the configured ring must
    # (companion/growthcheck.py); None = no check
    growth: GrowthCheck | None = None
    _growth_said: bool = False  # its refusal was logged this engagement
    # Is another candidate in view as likely the target (companion/rival.py)? None = no check. A candidate it
    # refuses is looked past at once (refuse_candidate), not after drop_tracker_after refusals.
    rivals: RivalWatch | None = None
    _rival_refused: bool = False
    # This step's attitude estimate, and its matrix once a check has needed it (``frame_attitude``): the lock, the
    # growth check, the pull-up and the core's hover estimate use one matrix a frame, not one each.
    _q: np.ndarray | None = None
    _R: np.ndarray | None = None

    @classmethod
    def from_config(cls, cfg: Config, controller: Steering, params: EngagementParams | None = None) -> Engagement:
        from companion.config import camera_model  # the camera's model built once per section (every sim run)

        lock = None
        if cfg.app.target_lock:
            lock = TargetLock.from_config(cfg, camera_model(cfg.camera))
        params = params or EngagementParams.from_config(cfg)
        eng = cls.create(params, controller, cfg.app, cfg.safety, lock)
        if cfg.app.verify.enabled:
            eng.verifier = TargetVerifier(VerifyParams.from_config(cfg))
            if cfg.app.verify.growth:
                eng.growth = GrowthCheck(GrowthParams.from_config(cfg), camera_model(cfg.camera))
            if cfg.app.verify.rival:
                eng.rivals = RivalWatch(float(cfg.app.verify.rival_margin), params.acquire_frames,
                                        int(cfg.app.verify.rival_engaged_frames))
        if params.on_close == "pull_up":
            eng.pullup = PullUpPlanner(PullUpParams.from_config(cfg, f_max=params.f_max), camera_model(cfg.camera))
        return eng

    @classmethod
    def create(cls, params: EngagementParams, controller: Steering, app: AppConfig,
               safety: SafetyConfig, lock: TargetLock | None = None) -> Engagement:
        close = CloseDetector(app, params.width, frame_rate=params.frame_rate)
        return cls(params, controller, close, SafetyLimits(safety), lock=lock)

    # -- the step ------------------------------------------------------------------------------------
    def step(self, t: float, box: BoundingBox | None, q_wxyz_ned_frd: np.ndarray, baro_rel_alt: float | None,
             events: Iterable[LinkEvent] = (), accel_frd: np.ndarray | None = None,
             t_now: float | None = None, confirm: bool | None = None) -> Decision:
        """One frame captured at ``t`` (s, any monotonic clock): its box (or None), the attitude estimate at
        ``t`` (NED/FRD wxyz), the barometric altitude above take-off (m, None if unknown), link/pilot events,
        and for the controller the accelerometer (body FRD specific force, m/s^2) and the time now (the
        frame's age), when the caller has them. ``confirm``: the operator's confirmation (companion/confirm.py;
        None: not needed, app.engage auto)."""
        self._imu = (accel_frd, t_now)
        self._confirm = confirm
        self._q, self._R = q_wxyz_ned_frd, None
        if self._t0 is None:
            self._t0 = self._t_phase = t
        p = self.params
        valid = box is not None and box.is_valid(p.width, p.height)
        if valid and p.complete_boxes:
            whole = complete_clipped_box(box, p.width, p.height, p.cut_edge_px)
            if whole is not box and whole.is_valid(p.width, p.height):  # (not cut: the same box, already valid)
                box = whole
        lock_event = ""
        self._rejected_now = False
        self._refused_as_target = False
        self._rival_refused = False
        if valid and self.verifier is not None and self.phase in (Phase.ACQUIRE, Phase.ENGAGE):
            assert box is not None
            why = self._verify(self.verifier, t, box, q_wxyz_ned_frd)
            if why:  # not the target: no box (ACQUIRE: the stable-track streak starts again)
                if not self._unverified:
                    lock_event = (f"gate {self.passes[-1].gate}: box rejected, {why}" if self.phase is Phase.ENGAGE
                                  else f"candidate rejected, {why}")
                valid, box, self._rejected_now = False, None, True
            self._unverified = bool(why)
        los = None  # the box's world LOS when the lock computed it, for the growth check (one camera model)
        if valid and self.phase is Phase.ENGAGE and self.lock is not None:
            assert box is not None
            chk = self.lock.check(t, box, self.frame_attitude(), self.controller.closing_rate)
            if chk.ok:
                los = self.lock.ref_los
            else:
                # Another object's box: for every decision below, no box at all (the controller coasts, the
                # target-lost clock runs, the close detector does not see it).
                if not self._rejecting:
                    lock_event = f"gate {self.passes[-1].gate}: box rejected, {chk.why}"
                valid, box, self._rejected_now = False, None, True
            self._rejecting = not chk.ok
        if self.phase is Phase.ENGAGE and self.growth is not None and self._imu[0] is not None:
            if los is not None and self.growth.camera is not self.lock.camera:  # type: ignore[union-attr]
                los = None
            why = self.growth.update(t, box if valid else None, self.frame_attitude(), self._imu[0],
                                     los if valid else None)
            if why and valid:
                # Not the ring its size says: no box from here on (coast, then TARGET_LOST), never a pass.
                if not self._growth_said:
                    lock_event = f"gate {self.passes[-1].gate}: box rejected, {why}"
                    self._growth_said = True
                valid, box, self._rejected_now = False, None, True
        self._streak = self._streak + 1 if valid else 0
        self.used_box = box if valid else None  # what the decisions below saw (replay judges it against labels)
        engaged = self.phase is Phase.ENGAGE
        if engaged and self._rejected_now:
            self.refused += 1
        elif valid or not engaged:
            self.refused = 0
        k = p.drop_tracker_after
        self.drop_tracker = self._rejected_now and engaged and k > 0 and self.refused % k == 0
        # A candidate refused by verification is refused again next frame while the tracker holds it: on real PX4
        # (x500, 2026-12-07, run091) a 330 px box cut by the border was held for 15 s while the gate crossed the
        # view. Told, the tracker looks past it for a while (perception's refuse_time).
        if self.phase is Phase.ACQUIRE and self._refused_as_target:
            self.refused_candidate += 1
        elif valid or self.phase is not Phase.ACQUIRE:
            self.refused_candidate = 0
        self.refuse_candidate = self._rival_refused or (self.phase is Phase.ACQUIRE and self._rejected_now and k > 0
                                                        and self.refused_candidate > 0
                                                        and self.refused_candidate % k == 0)
        d = self._step(t, box, valid, q_wxyz_ned_frd, baro_rel_alt, events)
        if lock_event:
            d = replace(d, events=(*d.events, lock_event))
        if self.drop_tracker:
            d = replace(d, events=(*d.events, f"gate {self.passes[-1].gate}: tracker told to drop its target (its box "
                                               f"refused {self.refused} frames in a row)"))
        if self.refuse_candidate:
            d = replace(d, events=(*d.events, "tracker told to look past its candidate (" + (
                "another candidate in view is as likely the target or more)" if self._rival_refused
                else f"refused {self.refused_candidate} frames in a row)")))
        return d

    def _step(self, t: float, box: BoundingBox | None, valid: bool, q_wxyz_ned_frd: np.ndarray,
              baro_rel_alt: float | None, events: Iterable[LinkEvent]) -> Decision:
        ph = self.phase
        if ph.done:
            return Decision(t, ph, None)
        ev = set(events)
        if ph.commanding and ev:
            if "link_lost" in ev:
                return self._end(t, Phase.ABORT, Reason.LINK_LOST, "telemetry lost")
            what = "vehicle left OFFBOARD" if "offboard_lost" in ev else "vehicle disarmed"
            return self._end(t, Phase.ABORT, Reason.PILOT_TAKEOVER, what)
        if ph.commanding and self._confirm is False:
            return self._end(t, Phase.ABORT, Reason.NOT_CONFIRMED, "the operator withdrew the confirmation")
        if ph is Phase.ACQUIRE:
            return self._acquire(t, box, q_wxyz_ned_frd)
        if ph is Phase.ENGAGE:
            return self._engage_step(t, box, valid, q_wxyz_ned_frd, baro_rel_alt)
        below = self.limits.floor(t, baro_rel_alt, self._arrest(t))
        if below is not None:
            return self._end(t, Phase.ABORT, below.reason, below.detail)
        if ph is Phase.PASS:
            return self._pass_step(t, box, valid, q_wxyz_ned_frd)
        return self._recover_step(t, box, valid, q_wxyz_ned_frd)

    # -- phases ----------------------------------------------------------------------------------------
    def _acquire(self, t: float, box: BoundingBox | None, q: np.ndarray) -> Decision:
        p = self.params
        if self._streak >= p.acquire_frames and self._confirm is False:
            # app.engage confirm: PX4 keeps holding; the candidate is shown until the operator confirms it.
            first, self.awaiting = not self.awaiting, True
            if t - self._t_phase > p.acquire_timeout:
                return self._end(t, Phase.LAND, Reason.NO_TARGET,
                                 f"the candidate was not confirmed within {p.acquire_timeout:.1f} s")
            return Decision(t, Phase.ACQUIRE, None, events=("candidate awaiting confirmation",) if first else ())
        self.awaiting = False
        if self._streak >= p.acquire_frames:
            return self._start_engagement(t, box, q, f"stable track for {self._streak} frames"
                                          + (", confirmed by the operator" if self._confirm else ""))
        if t - self._t_phase > p.acquire_timeout:
            return self._end(t, Phase.LAND, Reason.NO_TARGET, f"no stable track within {p.acquire_timeout:.1f} s")
        return Decision(t, Phase.ACQUIRE, None)

    def _start_engagement(self, t: float, box: BoundingBox | None, q: np.ndarray, why: str) -> Decision:
        prev = self.phase
        self.controller.reset()
        self.close.reset()
        if self.pullup is not None:
            self.pullup.reset()
        if self.growth is not None:
            self.growth.reset()
            self._growth_said = False
        if self.rivals is not None:
            self.rivals.reset()
        if self.lock is not None:
            self.lock.reset()
            if box is not None:
                self.lock.check(t, box, self.frame_attitude())  # the engaged box is the first reference
        self._rejecting = False
        self._engage_start = self._last_valid = t
        self._los_ned = None
        self.passes.append(GatePass(len(self.passes) + 1, t))
        self._go(Phase.ENGAGE, t)
        out = self.controller.step(t, box, q, *self._imu)
        self._note_los(out)
        return Decision(t, Phase.ENGAGE, out.setpoint, out, why, prev,
                        events=(f"gate {self.passes[-1].gate} engaged",))

    def _engage_step(self, t: float, box: BoundingBox | None, valid: bool, q: np.ndarray,
                     baro: float | None) -> Decision:
        out = self.controller.step(t, box, q, *self._imu)
        if getattr(out, "mode", "") == "pn":
            self._last_valid = t
            self._last_size = max(box.w, box.h) if box is not None else 0.0
        self._note_los(out)
        abort = self.limits.check(t, self._engage_start, self._last_valid, baro, self._arrest(t))
        if abort is not None:
            return self._end(t, Phase.ABORT, abort.reason, abort.detail, out)
        est = self.close.update(t, box, getattr(out, "mode", "") == "pn")
        why = f"gate close: {est.why}"
        fire = None if self.pullup is None else self.pullup.decide(
            t, box if valid else None, est.ttc, self._los_enu, baro, self.limits.climb_rate, q)
        if fire is not None:
            est, why = replace(est, close=True, why=fire.why), f"gate close: {fire.why}"
        elif not est.close and (reckoned := self._reckoned(t)):
            why = f"gate close: {reckoned}"
        elif not est.close and not valid and not self._rejected_now and (near := self._near(t, est)):
            # The gate vanished while close (a detector often loses a ring that fills the image, a slow vehicle's
            # ring leaves across a border): the pass has begun. Without this the controller would coast until
            # "target lost" aborted a good pass. Not while a box is in view that is not the gate (a wall edge
            # rejected near the gate): that is coasted, then TARGET_LOST.
            why = (f"gate lost while close (time-to-contact {est.ttc:.2f} s, box {near:.2f} of the width in the "
                   f"last {self.params.near_window:.1f} s)")
        elif not est.close:
            return Decision(t, Phase.ENGAGE, out.setpoint, out)
        gp = self.passes[-1]
        gp.t_close = t
        self._peak = max(box.w, box.h) if valid and box is not None else self._last_size
        self._gone = 0
        if self.params.on_close == "pull_up":
            gp.status, gp.t_end, gp.evidence = "pulled_up", t, est.why
            self._sp = self._recover_setpoint(q, pull_up=True)
            self._old_gone = False
            self._go(Phase.RECOVER, t)
            return Decision(t, Phase.RECOVER, self._sp, out, f"pull-up: {why.removeprefix('gate close: ')}",
                            Phase.ENGAGE,
                            events=(f"gate {gp.gate} intercept: pulled up",))
        self._sp = self._straight_setpoint(q)
        self._go(Phase.PASS, t)
        return Decision(t, Phase.PASS, self._sp, out, why, Phase.ENGAGE,
                        events=(f"gate {gp.gate} close",))

    def _pass_step(self, t: float, box: BoundingBox | None, valid: bool, q: np.ndarray) -> Decision:
        p = self.params
        gp = self.passes[-1]
        size = max(box.w, box.h) if valid and box is not None else 0.0
        behind = size <= p.pass_shrink * self._peak
        self._gone = self._gone + 1 if behind else 0
        self._peak = max(self._peak, size)
        if self._gone >= p.pass_gone_frames:
            gp.status = "confirmed"
            gp.evidence = ("the gate left the view" if size == 0.0
                           else f"the box shrank to {size:.0f} px from {self._peak:.0f} px (the next gate)")
            self._old_gone = True
            return self._to_recover(t, q, f"gate {gp.gate} passed ({gp.evidence})",
                                    f"gate {gp.gate} passed")
        if t - self._t_phase > p.pass_timeout:
            gp.status = "not_confirmed"
            gp.evidence = f"the gate was still in view after {p.pass_timeout:.1f} s"
            self._old_gone = False
            return self._to_recover(t, q, f"gate {gp.gate} pass NOT confirmed ({gp.evidence})",
                                    f"gate {gp.gate} pass not confirmed")
        return Decision(t, Phase.PASS, self._sp)

    def _to_recover(self, t: float, q: np.ndarray, why: str, event: str) -> Decision:
        self.passes[-1].t_end = t
        self._sp = self._recover_setpoint(q)
        self._streak = 0  # the next gate's track counts from here, not the passed gate's
        self._go(Phase.RECOVER, t)
        return Decision(t, Phase.RECOVER, self._sp, None, why, Phase.PASS, events=(event,))

    def _recover_step(self, t: float, box: BoundingBox | None, valid: bool, q: np.ndarray) -> Decision:
        p = self.params
        if not self._old_gone:
            # After an unconfirmed pass (or a pull-up) the track may still be that gate: only once it has
            # left the view (or shrunk) is a track a new gate. The same gate is never engaged twice.
            size = max(box.w, box.h) if valid and box is not None else 0.0
            self._gone = self._gone + 1 if size <= p.pass_shrink * self._peak else 0
            if self._gone >= p.pass_gone_frames:
                self._old_gone = True
                self._streak = 1 if valid else 0
        if self.pullup is not None and self.pullup.fired is not None and p.on_close == "pull_up":
            # The planned pull-up (full thrust, tilted back) until it is flown, then level at recover thrust.
            yaw = euler_ned_deg_from_R(self.frame_attitude())[2]
            planned = self.pullup.setpoint(t, yaw, self._thrust_model()[0])
            if planned is not None:
                return Decision(t, Phase.RECOVER, planned)
            if not self.pullup.levelled:
                self.pullup.levelled = True
                self._sp = self._recover_setpoint(q)
        if t - self._t_phase < p.recover_time:
            return Decision(t, Phase.RECOVER, self._sp)
        passed = sum(g.status == "confirmed" for g in self.passes)
        if (p.next_gate and p.on_close == "fly_through" and self._old_gone and self._streak >= p.acquire_frames
                and len(self.passes) < p.max_gates):
            return self._start_engagement(t, box, q, f"next gate tracked for {self._streak} frames")
        if p.on_close == "pull_up":
            why = "pulled up before the target"
        else:
            unconf = sum(g.status == "not_confirmed" for g in self.passes)
            why = f"{passed} gate(s) passed" + (f", {unconf} pass(es) not confirmed" if unconf else "")
            why += "; no next gate"
        return self._end(t, Phase.HANDBACK, Reason.OK, why)

    # -- helpers ---------------------------------------------------------------------------------------
    def _verify(self, verifier: TargetVerifier, t: float, box: BoundingBox, q: np.ndarray) -> str:
        """"" when ``box`` may be the configured target (companion/verify.py); at ACQUIRE also the same object
        as the streak's earlier boxes (the target lock's size and direction rules)."""
        acquiring = self.phase is Phase.ACQUIRE
        if acquiring and self._streak == 0:
            verifier.begin(box)  # a new candidate: its appearance is the reference
        why = verifier.check(box, acquiring)
        if why:
            self._refused_as_target = True
            return why
        if acquiring and self.lock is not None:
            if self._streak == 0:
                self.lock.reset()
            chk = self.lock.check(t, box, self.frame_attitude())
            if not chk.ok:
                return f"not one object: {chk.why.removeprefix('not the engaged gate: ')}"
        if acquiring and self.rivals is not None:
            if self._streak == 0:
                self.rivals.reset()
            r = box.rival  # another object in view that could be the target too
            why = self.rivals.add(box.confidence, r.confidence if r is not None and verifier.may_be_candidate(r)
                                  else 0.0, operator=self._confirm is not None)
            if why:
                self.rivals.reset()
                self._rival_refused = True
                return why
        elif self.rivals is not None and self.phase is Phase.ENGAGE:
            r = box.rival
            why = self.rivals.engaged(box, r if r is not None and verifier.may_be_candidate(r, False) else None)
            if why:
                self._rival_refused = True  # looked past: the other candidate may be tracked, the lock judges it
                # The sizes it measured were not the ring's: no time-to-contact, no "near" from them (its loss
                # is not the pass begun).
                self.close.reset()
                return why
        return ""

    def _near(self, t: float, est: object) -> float:
        """Close enough that losing the box means the pass has begun: within ``near_factor`` of a close
        trigger (time-to-contact, or the gate's largest box of the last ``near_window`` s). The box size it
        judged (fraction of the width), 0.0 when not near."""
        c, p = self.close, self.params
        ttc = getattr(est, "ttc", math.inf)
        size = max(getattr(est, "size_frac", 0.0), c.peak(t, p.near_window))
        if size < p.lost_min_size:  # a small box lost left the view (or was missed): not a pass
            return 0.0
        near = (c.trigger in ("ttc", "either") and ttc < p.near_factor * c.ttc_threshold) or (
            c.trigger in ("size", "either") and size > c.size_threshold / p.near_factor)
        return size if near else 0.0

    def _reckoned(self, t: float) -> str:
        """The time-to-contact the closing-speed filter dead-reckons with the IMU to ``reckon_range`` of the gate's
        centre, when it is at most ``reckon_ttc`` (0: that range reached) while the image gives no range (the ring
        filled the view, or no box) and the gate's box was near when the image last gave a range (at least
        ``lost_min_size`` of the width in the ``near_window`` before it): why, or ""."""
        p, c = self.params, self.close
        if not p.reckon_close or p.on_close != "fly_through" or c.trigger not in ("ttc", "either"):
            return ""
        est = self.controller.closing_estimate
        if est is None:
            return ""
        d, d_dot, t_range = est
        if t_range is None or not (0.0 < t - t_range <= p.reckon_max) or d_dot > -0.5:
            return ""
        # Near when the image last gave a range (the ring came to fill the view): a box seen since then does not
        # make an old range from a small box one to dead-reckon (on real PX4 a far gate lost 0.84 s earlier and a
        # background box near the border closed a pass 4 m beside the gate).
        if c.peak(t_range, p.near_window, until=t_range) < p.lost_min_size:
            return ""
        ttc = max(d - p.reckon_range, 0.0) / -d_dot
        if ttc > p.reckon_ttc:
            return ""
        return (f"time-to-contact {ttc:.2f} s to {p.reckon_range:.2f} m of the gate's centre, dead-reckoned with the "
                f"IMU (range {d:.2f} m; no range from the image for {t - t_range:.2f} s; closing at {-d_dot:.1f} m/s)")

    def frame_attitude(self) -> np.ndarray:
        """The attitude matrix (NED <- FRD) of the frame being stepped, built once a frame: the checks that need it
        (the target lock, the growth check, the pull-up's yaw, the flight core's hover estimate) share it and
        read it only."""
        if self._R is None:
            if self._q is None:
                raise RuntimeError("no frame stepped yet")
            self._R = R_from_quat_wxyz(self._q)
        return self._R

    def _go(self, phase: Phase, t: float) -> None:
        self.phase = phase
        self._t_phase = t

    def _end(self, t: float, phase: Phase, reason: Reason, why: str, control: object | None = None) -> Decision:
        prev = self.phase
        if self.passes and self.passes[-1].status == "engaged" and prev in (Phase.ENGAGE, Phase.PASS):
            self.passes[-1].t_end = t
            self.passes[-1].evidence = f"ended by {reason.name}"
        self._go(phase, t)
        return Decision(t, phase, None, control, why, prev, reason)

    def _note_los(self, out: object) -> None:
        los = getattr(out, "los_ned", None)
        if los is not None:
            self._los_ned = los

    @property
    def _los_enu(self) -> np.ndarray | None:
        """The last filtered LOS of the engagement (ENU), None before one: converted when read (the pass, the
        pull-up), not every frame."""
        return None if self._los_ned is None else swap_ned_enu(np.asarray(self._los_ned, dtype=float))

    def _thrust_model(self) -> tuple[float, float, float, float]:
        """(hover thrust, thrust_min, f_min, f_max): the controller's current numbers when it has them (the app
        may re-estimate the hover thrust in flight, companion/hover.py), else the parameters'."""
        cp = getattr(self.controller, "p", None)
        gp = getattr(cp, "guidance", None)
        if cp is not None and gp is not None and hasattr(cp, "hover_thrust"):
            return cp.hover_thrust, cp.thrust_min, gp.f_min, gp.f_max
        p = self.params
        return p.hover_thrust, p.thrust_min, p.f_min, p.f_max

    def _straight_setpoint(self, q: np.ndarray) -> Setpoint:
        hover, thrust_min, f_min, f_max = self._thrust_model()
        l = self._los_enu  # noqa: E741
        if l is None:  # no LOS was ever filtered (cannot happen after a close estimate): look straight ahead
            R = R_from_quat_wxyz(q)
            l = swap_ned_enu(R[:, 0])  # noqa: E741
        drag = getattr(self.controller, "drag_enu", None) if self.params.pass_keeps_velocity else None
        sol = guidance.straight_pass(l, f_min, f_max, max_tilt=self.params.max_tilt, drag=drag)
        return guidance.to_setpoint(sol.R_W_B, sol.f_th, hover, thrust_min)

    def _recover_setpoint(self, q: np.ndarray, pull_up: bool = False) -> Setpoint:
        p = self.params
        yaw = euler_ned_deg_from_R(R_from_quat_wxyz(q))[2]
        thrust = min(1.0, self._thrust_model()[0] * p.recover_thrust_scale)
        if not pull_up:
            return guidance.hover_setpoint(yaw, thrust)
        if self.pullup is not None and self.pullup.fired is not None:
            planned = self.pullup.setpoint(self.pullup.t_fire, yaw, self._thrust_model()[0])
            if planned is not None:
                return planned
        # Nose up: the thrust tilts backwards (brakes); its vertical part still carries scale x weight.
        pitch = p.pull_up_pitch
        return Setpoint(0.0, pitch, yaw, min(1.0, thrust / math.cos(math.radians(pitch))),
                        R_from_euler_ned_deg(0.0, pitch, yaw))

    def _arrest(self, t: float) -> Callable[[float], float] | None:
        """The floor's look-ahead while a pull-up is planned (or flown): the height its sink arrest would lose."""
        if self.pullup is None:
            return None
        pp, fired = self.pullup.p, self.pullup.fired is not None
        elapsed = t - self.pullup.t_fire if fired else 0.0
        return lambda rate: arrest_loss(rate, 0.0, pp, elapsed)

    # -- what the engagement claims ----------------------------------------------------------------------
    @property
    def passes_confirmed(self) -> int:
        return sum(g.status == "confirmed" for g in self.passes)

    @property
    def passes_not_confirmed(self) -> int:
        return sum(g.status == "not_confirmed" for g in self.passes)


def cut_sides(box: BoundingBox, width: int, height: int, edge_px: float = 1.0) -> tuple[bool, bool, bool, bool]:
    """(left, right, top, bottom): which image borders the box touches (is cut by)."""
    x0, y0, x1, y1 = box.xyxy
    return x0 <= edge_px, x1 >= width - edge_px, y0 <= edge_px, y1 >= height - edge_px


def complete_clipped_box(box: BoundingBox, width: int, height: int, edge_px: float = 3.0) -> BoundingBox:
    """A gate box cut by one image border, completed to the gate's round shape.

    A detector's box of a ring that reaches past one border (top, say) covers only the visible part: its
    centre is pulled towards the image centre, and the LOS with it. When exactly one side of an axis
    touches the border (within ``edge_px``: detector edges are noisy) and the other axis is whole, the ring's
    extent along the cut axis is taken as its extent along the whole one (a round gate seen near head-on),
    anchored at the side that is not cut. Boxes cut on both sides of an axis (the gate fills the image) or
    on both axes are left as they are.
    """
    x0, y0, x1, y1 = box.xyxy
    cut_l, cut_r, cut_t, cut_b = cut_sides(box, width, height, edge_px)
    cut_x, cut_y = cut_l or cut_r, cut_t or cut_b
    if cut_x == cut_y or (cut_l and cut_r) or (cut_t and cut_b):
        return box
    size = max(box.w, box.h)
    if cut_y:
        y0, y1 = (min(y0, y1 - size), y1) if cut_t else (y0, max(y1, y0 + size))
    else:
        x0, x1 = (min(x0, x1 - size), x1) if cut_l else (x0, max(x1, x0 + size))
    # The constructor with the other fields passed on: what dataclasses.replace builds, without its generic
    # field walk (a fifth of this function's time; clipped boxes come every frame near the gate).
    return type(box)((x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0, box.confidence, box.t, box.appearance,
                     box.rival)
