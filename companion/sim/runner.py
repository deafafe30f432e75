"""One in-process simulated run: dynamics + sensors + geometric camera + controller + scorer.

The closed loop, every camera frame (1 / camera.rate, 30 Hz by default):

1. the scorer looks for the gate-plane crossing (ground truth; scoring only);
2. the geometric camera captures a box from the vehicle's *true* pose; it arrives at the
   controller ``sim.camera.delay`` later (latency), or never (drops, out of view);
3. the controller gets the arrived box (or None) and the *noisy* attitude estimate in PX4's
   NED/FRD wxyz, and returns a setpoint (NED/FRD Euler + normalised thrust);
4. the setpoint, converted to ENU/FLU xyzw, drives the dynamics for one frame (integrated at
   ``sim.rate`` >= 200 Hz inside :meth:`Quadrotor.step`), with wind.

``PNController.step`` takes no position or velocity; only the ablations that the paper runs
with ground truth (the "perfect v_rel knowledge" row, the velocity-based baseline) get it, via
their own explicit arguments.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import asdict, dataclass, field, replace
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from scipy.spatial.transform import Rotation

from companion.configbase import deep_merge
from companion.core import FlightCore, FrameInput, ImuReading
from companion.engagement import Phase
from companion.frames import P_NED_ENU, R_from_quat_wxyz
from companion.metrics import NO_OSCILLATION, Oscillation, max_tilt_deg, oscillation
from companion.reasons import Reason
from companion.sim.camera import GeometricCamera, detector_noise, true_camera_config
from companion.sim.dynamics import QuadParams, Quadrotor, quat_enu_flu_from_R_ned_frd, quat_to_matrix
from companion.sim.gates import ALL_MOTIONS, MOTIONS, MotionKind
from companion.sim.scenario import Scenario, make_scenario
from companion.sim.scoring import PlaneCrossingScorer, PullUpScorer, RunOutcome
from companion.sim.sensors import Sensors, Wind

if TYPE_CHECKING:
    from companion.config import Config

ControllerKind = Literal["pn", "pn_true_vrel", "baseline"]
CONTROLLERS: tuple[ControllerKind, ...] = ("pn", "pn_true_vrel", "baseline")
CameraKind = Literal["geometric", "rendered"]
CAMERAS: tuple[CameraKind, ...] = ("geometric", "rendered")
ProtocolKind = Literal["engagement", "controller"]
PROTOCOLS: tuple[ProtocolKind, ...] = ("engagement", "controller")


@dataclass(frozen=True)
class RunSpec:
    motion: MotionKind
    seed: int
    controller: ControllerKind = "pn"
    label: str = ""  # free text for grouping in suites
    # geometric: projected box (fast, the paper's V-A setup); rendered: drawn frames through the real
    # detector/tracker (perception/simcamera.py), ~100x slower.
    camera: CameraKind = "geometric"
    # engagement: the engagement core in the loop (acquire, close, pass, recover, aborts) on detector-like
    # boxes; controller: the paper's protocol (controller until the gate plane, box centred on the gate).
    protocol: ProtocolKind = "engagement"


@dataclass
class Trajectory:
    """Per-frame record of a run (for plots and debugging)."""

    t: list[float] = field(default_factory=list)
    p: list[np.ndarray] = field(default_factory=list)
    v: list[np.ndarray] = field(default_factory=list)
    gate: list[np.ndarray] = field(default_factory=list)
    mode: list[str] = field(default_factory=list)
    thrust: list[float] = field(default_factory=list)
    roll_sp: list[float] = field(default_factory=list)  # the held attitude setpoint, NED/FRD Euler deg
    pitch_sp: list[float] = field(default_factory=list)
    box: list[tuple[float, float, float, float] | None] = field(default_factory=list)
    demand_scale: list[float] = field(default_factory=list)
    lambda_dot: list[float] = field(default_factory=list)
    accel: list[np.ndarray] = field(default_factory=list)  # simulated IMU specific force, FLU (logged only)
    baro: list[float] = field(default_factory=list)  # simulated barometric altitude, m (logged only)

    def arrays(self) -> dict[str, np.ndarray]:
        return {"t": np.array(self.t), "p": np.array(self.p), "v": np.array(self.v), "gate": np.array(self.gate)}


@dataclass
class RunResult:
    spec: RunSpec
    outcome: RunOutcome
    distance: float
    angle: float
    altitude: float
    sim_time: float
    frames: int
    frames_with_box: int
    trajectory: Trajectory | None = None
    max_tilt_deg: float = math.nan  # largest commanded tilt over the engagement (companion.metrics)
    roll_osc: Oscillation = NO_OSCILLATION  # roll-setpoint oscillation over the engagement
    engagement: dict[str, Any] | None = None  # engagement protocol: how it ended, the pass's status
    pullup: dict[str, Any] | None = None  # on_close=pull_up: predicted miss, clearance (PullUpScorer)

    def as_dict(self, radii: list[float]) -> dict[str, Any]:
        d = {**asdict(self.spec), "distance_m": self.distance, "angle_deg": self.angle,
             "altitude_m": self.altitude, "sim_time_s": self.sim_time, "frames": self.frames,
             "frames_with_box": self.frames_with_box}
        d.update(self.outcome.as_dict(radii))
        # None, not NaN, for "too few setpoints": valid JSON, and equal results compare equal.
        metrics = {"max_tilt_deg": self.max_tilt_deg, **self.roll_osc.as_dict()}
        d.update({k: (v if math.isfinite(v) else None) for k, v in metrics.items()})
        if self.engagement is not None:
            d.update({f"engagement_{k}": v for k, v in self.engagement.items()})
        if self.pullup is not None:
            d.update({f"pullup_{k}": v for k, v in self.pullup.items()})
        return d


def with_overrides(cfg: Config, overrides: dict[str, Any]) -> Config:
    """A copy of cfg with a nested dict of values (canonical units) merged in, validated again."""
    from companion.config import Config

    return Config.model_validate(deep_merge(cfg.model_dump(), overrides))


class _Steering:
    """The controller as the engagement steps it: ``step(t, box, q)``, ``reset()``.

    The paper's ablations that know ground truth (the "perfect v_rel knowledge" row, the velocity-based
    baseline) get it here, set by the runner before each step; the engagement itself never sees it.
    """

    def __init__(self, cfg: Config, kind: ControllerKind) -> None:
        self.kind = kind
        if kind == "baseline":
            from companion.baseline import BaselinePN

            self.ctrl: Any = BaselinePN.from_config(cfg)
        else:
            from companion.controller import PNController

            if kind == "pn_true_vrel":  # the ablation sets v_rel_bar itself: no estimate on top of it
                cfg = with_overrides(cfg, {"guidance": {"closing_speed": "fixed"}})
            self.ctrl = PNController.from_config(cfg)
        self._cfg = cfg
        self.truth: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None  # p, v, gate, gate v
        self.imu: tuple[np.ndarray | None, float] | None = None  # (accelerometer FRD at capture, now), set per frame

    @property
    def closing_rate(self) -> tuple[float, float] | None:
        return None if self.kind == "baseline" else self.ctrl.closing_rate

    @property
    def closing_estimate(self) -> tuple[float, float, float | None] | None:
        return None if self.kind == "baseline" else self.ctrl.closing_estimate

    @property
    def p(self) -> Any:
        """The PN controller's parameters (the core's hover estimate updates them); none for the baseline."""
        if self.kind == "baseline":
            raise AttributeError("the velocity-based baseline has no PN parameters")
        return self.ctrl.p

    @p.setter
    def p(self, value: Any) -> None:
        self.ctrl.p = value

    @property
    def drag_enu(self) -> np.ndarray | None:
        return getattr(self.ctrl, "drag_enu", None)

    def reset(self) -> None:
        if self.kind == "baseline":
            from companion.baseline import BaselinePN

            self.ctrl = BaselinePN.from_config(self._cfg)
        else:
            self.ctrl.reset()

    def step(self, t: float, box: Any, q: np.ndarray, accel_frd: np.ndarray | None = None,
             t_now: float | None = None) -> Any:
        if self.kind == "pn":
            if accel_frd is None and t_now is None and self.imu is not None:
                accel_frd, t_now = self.imu
            return self.ctrl.step(t, box, q, accel_frd, t_now)
        assert self.truth is not None
        p, v, g, gv = self.truth
        if self.kind == "pn_true_vrel":
            # Ablation only: the paper's "perfect knowledge" of the closing speed.
            r = g - p
            closing = -float(r @ (gv - v)) / float(np.linalg.norm(r))
            gp = replace(self.ctrl.p.guidance, v_rel_bar=max(closing, 0.1))
            self.ctrl.p = replace(self.ctrl.p, guidance=gp)
            return self.ctrl.step(t, box, q)
        # baseline: velocities known (GPS), as Bhattacharya et al. assume
        out = self.ctrl.step(t, box, q, v.copy(), gv - v)
        los = out.los_enu
        return _BaselineOut(out.t, out.setpoint, out.mode, None if los is None else P_NED_ENU @ los)


@dataclass(frozen=True)
class _BaselineOut:
    t: float
    setpoint: Any
    mode: str
    los_ned: np.ndarray | None
    demand_scale: float = math.nan
    lambda_dot: float = math.nan


def _camera_model(cfg: Config) -> Any:
    """The true camera's model (``true_camera_config``), built once per (frozen) camera section."""
    from companion.config import camera_model

    return camera_model(true_camera_config(cfg))


# Engagement ends -> the run's end reason (when the gate plane was not crossed).
_END_REASONS = {Reason.OK: "handback", Reason.NO_TARGET: "no_target", Reason.TARGET_LOST: "target_lost",
                Reason.MAX_ENGAGEMENT: "max_engagement", Reason.ALTITUDE_FLOOR: "altitude_floor"}
POST_CROSSING_S = 1.5  # s flown after the crossing at most while the engagement is still before RECOVER
# After a pull-up's handback the run goes on this long with PX4's Hold approximated by a level hover setpoint (it
# keeps the forward speed where Hold would brake: the pessimistic side for the clearance over the target).
POST_PULLUP_S = 2.0


def run_once(cfg: Config, spec: RunSpec, record: bool = False) -> RunResult:
    """Fly one run to its end; deterministic for spec.seed.

    ``engagement`` protocol: the engagement core decides (acquire, engage, close, pass, recover, aborts) on
    detector-like boxes (clipped to the image); the run ends when the engagement ends, when it is in RECOVER
    after the gate-plane crossing, or on the simulator's own limits (ground, timeout). ``controller``
    protocol (the paper's V-A): the controller alone, boxes centred on the gate, until the crossing,
    fov_lost, ground or timeout. Either way the gate-plane crossing from ground truth scores the run.
    """
    if spec.motion not in ALL_MOTIONS:
        raise ValueError(f"run: unknown gate motion {spec.motion!r} (use one of: {', '.join(ALL_MOTIONS)})")
    if spec.controller not in CONTROLLERS:
        raise ValueError(f"run: unknown controller {spec.controller!r} (use one of: {', '.join(CONTROLLERS)})")
    if spec.camera not in CAMERAS:
        raise ValueError(f"run: unknown camera {spec.camera!r} (use one of: {', '.join(CAMERAS)})")
    if spec.protocol not in PROTOCOLS:
        raise ValueError(f"run: unknown protocol {spec.protocol!r} (use one of: {', '.join(PROTOCOLS)})")
    sim = cfg.sim
    engaged = spec.protocol == "engagement"
    # Independent streams, so e.g. turning pixel noise on does not change the initial condition.
    ss = np.random.SeedSequence([sim.seed, spec.seed])
    rng_scn, rng_cam, rng_sens, rng_wind = (np.random.default_rng(s) for s in ss.spawn(4))
    params = QuadParams.from_config(cfg)
    tw, th = sim.target.size(sim.scenario.visual_radius)
    scn: Scenario = make_scenario(spec.motion, rng_scn, sim.scenario, sim.gates, params,
                                  ground_centre=0.5 * th if sim.target.on_ground else None)
    gate = scn.gate
    quad = Quadrotor(params, scn.state0)
    make_camera = GeometricCamera
    rendered = spec.camera == "rendered"
    if rendered:
        from perception.simcamera import geometric_camera_substitute

        make_camera = geometric_camera_substitute(cfg)
    # The engagement protocol sees a detector-like box: the ring's extent clipped to the image.
    # The camera sees through the true mount (sim.camera.mount_error); the controller keeps the configured one.
    camera = make_camera(_camera_model(cfg), sim.camera.pixel_noise,
                         sim.camera.drop_prob, sim.camera.min_box, rng_cam, sim.camera.clip_box or engaged)
    if sim.camera.noise_model == "detector" and isinstance(camera, GeometricCamera):
        camera.use_detector_noise(detector_noise(cfg, rng_cam))
    if sim.target.shape != "ring":
        if not isinstance(camera, GeometricCamera):
            raise ValueError(f"run: the rendered camera draws rings only (sim.target.shape {sim.target.shape!r})")
        camera.use_rectangle(tw, th)
    if type(camera) is GeometricCamera and sim.camera.drop_prob <= 0.0 and camera.detector_noise is None:
        camera.read_ahead()  # the pixel noise is the camera stream's one reader: its normals a block at a time
    sensors = Sensors(sim.sensors, rng_sens)
    sensors.read_ahead()  # rng_sens is the sensors' alone (the logged barometer has rng_rec)
    wind = Wind(sim.wind, rng_wind)
    steer = _Steering(cfg, spec.controller)
    # The engagement steps the PN controller with the frame's accelerometer and time itself, and every other use of
    # the wrapper passes straight through for "pn": it gets the controller, without a layer of calls a frame.
    core = FlightCore.from_config(cfg, controller=steer.ctrl if spec.controller == "pn" else steer) if engaged else None
    eng = core.engagement if core is not None else None
    scorer = PlaneCrossingScorer(gate.normal)
    pulling = eng is not None and cfg.app.on_close == "pull_up"
    pull_scorer = PullUpScorer(gate.normal, 0.5 * tw, 0.5 * th) if pulling else None
    hold_end: float | None = None  # pull-up handed back: PX4 Hold (approximated) until then

    dt = 1.0 / cfg.camera.rate
    delay = sim.camera.delay
    radius = 0.5 * tw  # a ring's; a rectangle's size is the camera's own (use_rectangle)
    timeout, fov_timeout = sim.scenario.timeout, sim.scenario.fov_timeout
    # Until the first setpoint, PX4 would hold the last one: the cruise trim.
    q_cmd = scn.state0.q.copy()
    thrust_cmd = min(1.0, scn.state0.f_th * params.hover_thrust / 9.81)
    pending: deque = deque()  # (arrival time, capture time, box)
    traj = Trajectory() if record else None
    # The logged barometer's noise has a stream of its own: recording a run must not change the flight (it drew
    # from the sensors' stream, which shifted the attitude noise: recorded plots showed another flight).
    rng_rec = np.random.default_rng(np.random.SeedSequence([sim.seed, spec.seed, 0x0BA20])) if record else None
    last_seen = 0.0
    frames = frames_with_box = 0
    top_speed = 0.0
    outcome: RunOutcome | None = None
    crossing: RunOutcome | None = None
    mode: str | Phase = "init"  # the controller's mode, or the engagement's phase (its name only for the record)
    imu_to_controller, attitude_at_capture = sim.imu_to_controller, sim.camera.attitude_at_capture
    last_out = None
    end: str | None = None  # the engagement's end (phase and reason), if it ended
    roll_cmd = pitch_cmd = math.nan
    sp_t: list[float] = []  # commanded attitude per control step, for the per-run metrics
    sp_roll: list[float] = []
    sp_pitch: list[float] = []
    k = 0
    while True:
        t = k * dt
        # The state from the integrator's floats (Quadrotor.advance builds no QuadState): the position as an array
        # (the camera's and the scorer's numpy arithmetic), the same values as QuadState.p.
        p_xyz = quad.p_xyz
        p_enu = np.array(p_xyz)
        g = gate.position(t)
        vx, vy, vz = quad.v_xyz
        speed = math.sqrt(vx * vx + vy * vy + vz * vz)  # np.linalg.norm's value (sqrt of the dot), without its overhead
        top_speed = max(top_speed, speed)
        if crossing is None:
            crossing = scorer.update(t, p_enu, g)
            t_cross = t
        if pull_scorer is not None:
            pulled = bool(eng is not None and eng.passes and eng.passes[0].status == "pulled_up")
            pull_scorer.update(t, p_enu, np.array(quad.v_xyz), g, gate.velocity(t), pulled)
        if crossing is not None and not pulling and (
                eng is None or eng.phase in (Phase.RECOVER,) or eng.phase.done or t - t_cross > POST_CROSSING_S):
            break
        if hold_end is not None:
            if t > hold_end or quad.ground_contact or quad.on_ground:
                if quad.ground_contact or quad.on_ground:
                    outcome = RunOutcome(False, None, None, "ground")
                break
            x = quat_to_matrix(quad.q_xyzw)[:, 0]
            q_cmd = Rotation.from_euler("z", math.atan2(x[1], x[0])).as_quat()
            thrust_cmd = params.hover_thrust
            quad.advance(dt, q_cmd, thrust_cmd, wind.step(dt))
            k += 1
            continue
        if quad.ground_contact or (quad.on_ground and k > 0):
            outcome = RunOutcome(False, None, None, "ground")
            break
        if t > timeout:
            outcome = RunOutcome(False, None, None, "timeout")
            break
        q_true = quad.q_xyzw
        R_true = quat_to_matrix(q_true)
        # The attitude estimate and the accelerometer (one draw per frame, recorded or not), from the sensors' own
        # stream: drawn before the camera or after, the same.
        q_est, (ax, ay, az) = sensors.frame(q_true, quad.specific_force_body_xyz())
        if rendered:  # the pipeline moves its track by the attitude the controller is given (perception/derotate.py)
            box = camera.capture(t, p_enu, R_true, g, gate.normal, radius, R_world_body=R_from_quat_wxyz(q_est))
        else:
            box = camera.capture(t, p_enu, R_true, g, gate.normal, radius)
        frames += 1
        if box is not None:
            frames_with_box += 1
            last_seen = t
        elif eng is None and t - last_seen > fov_timeout:
            outcome = RunOutcome(False, None, None, "fov_lost")
            break
        # The controller's contract: the box of the frame captured at t_cap with the attitude at t_cap
        # (the app matches telemetry to the frame time). attitude_at_capture=False instead pairs the
        # late box with the attitude at arrival, which is what a naive pipeline does.
        # The accelerometer as PX4 reports it (body FRD): the FLU reading times (1, -1, -1), element by element.
        acc_frd = np.array((ax, -ay, -az))
        pending.append((t + delay, t, box, q_est, acc_frd))
        if steer.kind != "pn":  # only the ablations that know ground truth read it (gate.velocity: ~1.5 % of a frame)
            steer.truth = (p_enu, np.array(quad.v_xyz), g, gate.velocity(t))
        while pending and pending[0][0] <= t + 1e-9:
            _, t_cap, b, q_cap, acc_cap = pending.popleft()
            # The controller may use the accelerometer at the frame's capture time and the frame's age.
            steer.imu = (acc_cap if imu_to_controller else None, t)
            if attitude_at_capture:
                q_est = q_cap
            if core is None:
                out = steer.step(t_cap, b, q_est)
                sp, mode, last_out = out.setpoint, out.mode, out
            else:
                # Barometric altitude above the ground with the run's baro offset (its white noise, 0.1 m,
                # is irrelevant to the floor and would shift the attitude-noise stream).
                acc, t_now = steer.imu
                step = core.step(FrameInput(t_cap, b, q_est, p_xyz[2] + sensors.baro_bias, accel_frd=acc,
                                            t_now=t_now, imu=ImuReading(t, acc_frd)))
                d = step.decision
                step.tell_tracker(camera)  # the rendered camera's tracker, as the app's
                sp, mode = d.setpoint, d.phase  # (an Enum's .value is a Python-level property: read when recorded)
                last_out = d.control if d.control is not None else last_out
                if d.phase.done:
                    end = f"{d.phase.value} {d.reason.name if d.reason else ''}".strip()
                    if pulling and d.reason is Reason.OK:
                        hold_end = t + POST_PULLUP_S
                        break
                    if crossing is None:
                        outcome = RunOutcome(False, None, None, _END_REASONS.get(d.reason, "handback"))
                    break
            if sp is None:
                continue  # ACQUIRE: PX4 holds (here: the cruise trim)
            q_cmd = quat_enu_flu_from_R_ned_frd(sp.R_ned_frd)
            thrust_cmd = sp.thrust
            sp_t.append(t)
            sp_roll.append(sp.roll_deg)
            sp_pitch.append(sp.pitch_deg)
            roll_cmd, pitch_cmd = sp.roll_deg, sp.pitch_deg
        if outcome is not None:
            break
        if traj is not None:
            traj.t.append(t)
            traj.p.append(p_enu.copy())
            traj.v.append(np.array(quad.v_xyz))
            traj.gate.append(g)
            traj.mode.append(mode.value if isinstance(mode, Phase) else mode)
            traj.thrust.append(thrust_cmd)
            traj.roll_sp.append(roll_cmd)
            traj.pitch_sp.append(pitch_cmd)
            traj.box.append(None if box is None else (box.cx, box.cy, box.w, box.h))
            traj.demand_scale.append(float(getattr(last_out, "demand_scale", float("nan"))))
            traj.lambda_dot.append(float(getattr(last_out, "lambda_dot", float("nan"))))
            # IMU and baro are simulated for the log (and the app's safety layer); the PN law needs neither.
            traj.accel.append(np.array((ax, ay, az)))
            traj.baro.append(sensors.baro_altitude(p_xyz[2], rng_rec))
        quad.advance(dt, q_cmd, thrust_cmd, wind.step(dt))
        k += 1
    if crossing is not None and (outcome is None or not pulling):
        outcome = crossing  # ground truth scores the run, whatever the engagement did after
    if outcome is None:  # a pull-up handed back and held without crossing the target's plane
        outcome = RunOutcome(False, None, None, None)
    assert outcome is not None
    outcome.top_speed = top_speed
    info = None
    if eng is not None:
        first = eng.passes[0] if eng.passes else None
        info = {"end": end or eng.phase.value, "pass_status": first.status if first else None,
                "t_close_s": first.t_close if first else None}
    return RunResult(spec, outcome, scn.distance, scn.angle, scn.altitude, k * dt, frames, frames_with_box, traj,
                     max_tilt_deg(np.array(sp_roll), np.array(sp_pitch)),
                     oscillation(np.array(sp_t), np.array(sp_roll)), info,
                     pull_scorer.as_dict() if pull_scorer is not None else None)


def bench_sim(seconds: float = 60.0, cfg: Config | None = None) -> dict[str, float]:
    """Simulator speed on one core: fly runs (all motions, geometric camera, PN controller)
    until ``seconds`` of simulated time have passed.

    ``sim_speed_x_realtime`` is simulated time / this process's CPU time (what one core delivers,
    independent of other load on a shared machine); ``sim_speed_x_realtime_wall`` uses wall time.
    """
    if cfg is None:
        from companion.config import load_config

        cfg = load_config()
    # Warm-up: imports and the per-process caches (each motion's shape extremes, ~0.1 s once per process on a
    # 200k-point grid), which are not per-frame costs.
    for m in MOTIONS:
        run_once(cfg, RunSpec(m, seed=10_000))
    sim_t = 0.0
    frames = 0
    runs = 0
    t0 = time.perf_counter()
    c0 = time.process_time()
    while sim_t < seconds:
        r = run_once(cfg, RunSpec(MOTIONS[runs % len(MOTIONS)], seed=runs))
        sim_t += r.sim_time
        frames += r.frames
        runs += 1
    wall = time.perf_counter() - t0
    cpu = max(time.process_time() - c0, 1e-9)
    return {
        "sim_speed_x_realtime": sim_t / cpu,
        "sim_speed_x_realtime_wall": sim_t / wall,
        "sim_seconds": sim_t,
        "cpu_seconds": cpu,
        "wall_seconds": wall,
        "runs": float(runs),
        "frame_us": 1e6 * cpu / max(frames, 1),
        "integration_hz": float(cfg.sim.rate),
    }
