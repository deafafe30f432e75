"""The configuration schema: one typed, validated object built from YAML files.

``load_config()`` reads ``config/default.yaml`` (which includes the per-topic files:
airframe, camera, guidance, ...), then any further files the user names (later
files win, key by key), then ``--set section.key=value`` overrides.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, ValidationError, model_validator
from scipy.spatial.transform import Rotation

from companion.cameramodel import distortion_problem
from companion.config_app import AppConfig, LinkConfig, LogConfig, SafetyConfig
from companion.config_perception import PerceptionConfig
from companion.configbase import (
    ConfigError,
    Deg,
    Hertz,
    Kilograms,
    Meters,
    MetersPerSecond,
    Number,
    Seconds,
    Section,
    deep_merge,
    format_validation_error,
    parse_override,
    read_yaml,
)
from companion.hover import HoverConfig
from companion.px4sitl.config import PX4Config
from companion.sim.config import SimConfig

G = 9.81  # m/s^2, the paper's |g|


class AirframeConfig(Section):
    """What the controller needs to know about the vehicle (x500-like by default)."""

    name: str = "x500"
    mass: Kilograms = Field(2.0, gt=0.05, le=50.0, description="kg")
    hover_thrust: Number = Field(
        0.5, gt=0.05, lt=0.95, description="normalised thrust that hovers (PX4 MPC_THR_HOVER)"
    )
    thrust_to_weight: Number = Field(2.0, gt=1.05, le=10.0, description="max collective thrust / weight")
    thrust_min: Number = Field(
        0.1, ge=0.01, lt=0.5, description="lowest normalised thrust ever sent (never 0: a quad at 0 falls; >= 0.01: "
        "below, the command is zero in all but name)"
    )
    max_tilt: Deg = Field(
        50.0, ge=10.0, le=80.0, description="flight envelope: largest commanded tilt of the thrust axis from vertical"
    )
    response_time: Seconds = Field(
        0.14, ge=0.0, le=2.0, description="how long the attitude takes to follow a setpoint (PX4 SIH quad ~0.22 s)"
    )
    drag_rate: Number = Field(
        0.1, ge=0.0, le=10.0, description="how fast drag takes back a velocity change, 1/s (linear drag / mass; "
        "quadratic drag c v^2: c v / mass at cruise; PX4's SIH quad: SIH_KDV 1 N/(m/s) on 1 kg = 1/s)"
    )

    @property
    def f_max(self) -> float:
        """Largest mass-normalised thrust [m/s^2] the setpoint can ask for (thrust <= 1 and <= T/W)."""
        return G * min(self.thrust_to_weight, 1.0 / self.hover_thrust)

    @property
    def f_min(self) -> float:
        """Smallest mass-normalised thrust [m/s^2]: the one thrust_min maps to."""
        return G * self.thrust_min / self.hover_thrust


class MountConfig(Section):
    """Camera-to-body rotation as intrinsic roll/pitch/yaw of the camera relative to body FRD (deg).

    All zero: the camera looks along body x (forward), image x to the right, image y down.
    Positive pitch tilts the camera up.
    """

    roll: Deg = Field(0.0, ge=-180.0, le=180.0)
    pitch: Deg = Field(0.0, ge=-90.0, le=90.0)
    yaw: Deg = Field(0.0, ge=-180.0, le=180.0)


class CameraConfig(Section):
    width: int = Field(640, ge=16, le=8192, description="px")
    height: int = Field(480, ge=16, le=8192, description="px")
    half_fov: Deg = Field(33.5, gt=1.0, lt=89.0, description="horizontal half angle of view, deg")
    fx: Number | None = Field(None, gt=0.0, le=1e6, description="px; default from half_fov")
    fy: Number | None = Field(None, gt=0.0, le=1e6, description="px; default = fx")
    cx: Number | None = Field(None, description="px; default = width/2 (must lie in the image)")
    cy: Number | None = Field(None, description="px; default = height/2 (must lie in the image)")
    distortion: list[Number] = Field(default_factory=list, max_length=14, description="OpenCV k1,k2,p1,p2[,k3..]")
    rate: Hertz = Field(30.0, gt=0.5, le=1000.0, description="frame rate, Hz")
    mount: MountConfig = MountConfig()

    @model_validator(mode="after")
    def _check(self) -> CameraConfig:
        if len(self.distortion) not in (0, 4, 5, 8, 12, 14):
            raise ValueError(f"distortion must have 0, 4, 5, 8, 12 or 14 coefficients, got {len(self.distortion)}")
        if any(not math.isfinite(d) for d in self.distortion):
            raise ValueError("distortion coefficients must be finite")
        for name, c, size in (("cx", self.cx, self.width), ("cy", self.cy, self.height)):
            if c is not None and not 0.0 <= c <= size:
                raise ValueError(f"{name} {c} lies outside the image (0..{size} px)")
        problem = distortion_problem(self.K, self.dist, self.width, self.height)
        if problem:
            raise ValueError(f"distortion {list(self.distortion)}: {problem}")
        return self

    @property
    def K(self) -> np.ndarray:
        fx = self.fx if self.fx is not None else (self.width / 2.0) / math.tan(math.radians(self.half_fov))
        fy = self.fy if self.fy is not None else fx
        cx = self.cx if self.cx is not None else self.width / 2.0
        cy = self.cy if self.cy is not None else self.height / 2.0
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        return np.asarray(self.distortion, dtype=float)

    @property
    def R_body_cam(self) -> np.ndarray:
        """Rotation camera (OpenCV: x right, y down, z forward) -> body FRD."""
        # Zero mount: cam z (forward) -> body x, cam x (right) -> body y, cam y (down) -> body z.
        base = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
        mount = Rotation.from_euler("ZYX", [self.mount.yaw, self.mount.pitch, self.mount.roll], degrees=True)
        return mount.as_matrix() @ base


_CAMERA_MODELS: dict[int, tuple[CameraConfig, Any]] = {}  # id(camera section) -> (the section, its CameraModel)


def camera_model(camera: CameraConfig) -> Any:
    """``perception.los.CameraModel.from_config(camera)``, built once per camera section (sections are frozen):
    building one (the mount's rotation through scipy, the intrinsics' inverse) cost ~2 % of the simulator's
    frames, three times a run (controller, target lock, simulated camera). The section is kept with its model, so
    its id is not reused while cached. The model is shared: nobody changes one."""
    from perception.los import CameraModel

    hit = _CAMERA_MODELS.get(id(camera))
    if hit is not None and hit[0] is camera:
        return hit[1]
    model = CameraModel.from_config(camera)
    if not isinstance(camera, CameraConfig):
        return model  # only a frozen section can be cached
    if len(_CAMERA_MODELS) >= 16:  # a mount error builds a new section per run: keep the cache small
        _CAMERA_MODELS.clear()
    _CAMERA_MODELS[id(camera)] = (camera, model)
    return model


class GuidanceConfig(Section):
    """PN law and closed-form solver (paper eq:meth_pn_guidance_law and the optimum below it)."""

    k_pn: Number = Field(2.10, gt=0.0, le=20.0, description="navigation constant k_PN")
    gamma_bar: Deg = Field(21.05, gt=0.5, lt=89.0, description="bound on LOS-to-optical-axis angle, deg")
    v_rel_bar: MetersPerSecond = Field(15.0, gt=0.0, le=200.0, description="over-estimate of the relative speed, m/s")
    fov: Literal["exact", "paper"] = Field(
        "exact",
        description="exact: bound the real angle between LOS and optical axis; paper: the paper's "
        "conservative cos(phi) cos(theta) >= cos(gamma_bar), which caps sideways acceleration at g tan(gamma_bar)",
    )
    closing_speed: Literal["estimate", "fixed"] = Field(
        "estimate", description="estimate: v_rel_bar lowered on evidence from the gate's image expansion (and the "
        "IMU when given), companion/closing.py; fixed: the paper's constant v_rel_bar"
    )
    gate_radius: Meters = Field(
        1.0, ge=0.0, le=50.0, description="radius of the ring the camera sees, m (0 = unknown: fixed v_rel_bar)"
    )
    closing_margin: Number = Field(
        5.0, ge=1.0, le=10.0, description="relative-speed estimate x this in the PN law, before the caps v_rel_bar and "
        "the lag cap (1.5 cut jitter most but lost moving gates on the SIH profile: docs/guidance.md)"
    )
    closing_max_box: Number = Field(
        0.8, ge=0.0, le=1.0, description="a box whose larger side reaches this fraction of the image's smaller side "
        "gives the closing-speed filter no range (the ring fills the view; from there the range is dead-reckoned "
        "with the IMU); 0 = off"
    )
    lag_margin: Number = Field(
        1.0, ge=0.0, le=20.0, description="near the gate the PN gain is capped so its loop gain N / t_go stays below "
        "1 / (this x the loop lag: airframe.response_time + the LOS filters); 0 = off"
    )
    drag_compensation: Number = Field(
        1.0, ge=0.0, le=1.5, description="fraction of the drag normal to the LOS (from the accelerometer, when the "
        "caller gives it) cancelled in the PN demand; 0 = the paper (drag assumed along the LOS)"
    )
    delay_compensation: bool = Field(
        True, description="bring a late frame's LOS rate forward by the velocity our own acceleration added since "
        "its capture (a Smith predictor; needs the caller's time now and gate_radius > 0; no effect on a frame with "
        "no age); with delay_prediction the own-velocity part of the prediction (docs/guidance.md, Latency session)"
    )
    delay_compensation_lag: Seconds = Field(
        0.2, gt=0.0, le=5.0, description="time constant of the modelled response of our acceleration to its command, "
        "s, after the pure delay airframe.response_time (docs/guidance.md \"Latency session\")"
    )
    delay_prediction: bool = Field(
        True, description="bring a late frame's LOS and LOS rate forward through its age with the relative motion "
        "the image shows (range from gate_radius, range rate, LOS rate): the LOS rate of an unaccelerated gate grows "
        "as 1/range^2 while the frame was on its way; with delay_compensation also our own velocity change"
    )
    keep_ring_in_view: bool = Field(
        False, description="shrink the FOV bound as the ring grows so its rim stays in the image (a detector's box "
        "of a ring cut by the border pulls the LOS towards the image centre); off by default: it costs forward "
        "thrust, and loses the SIH profile's linear_fast chases (docs/guidance.md, Evening session)"
    )
    view_margin: Deg = Field(
        -3.0, ge=-30.0, le=30.0, description="keep_ring_in_view: the rim kept this far inside the view, deg "
        "(negative: it may reach this far past the border)"
    )
    gamma_min: Deg = Field(3.0, gt=0.0, lt=89.0, description="keep_ring_in_view: the FOV bound never below this, deg")


class LosFilterConfig(Section):
    """First-order low-pass on the world-frame unit LOS before the LOS rate is differenced."""

    cutoff: Hertz = Field(6.0, gt=0.0, le=1000.0, description="cut-off frequency, Hz (high = no filtering)")
    max_rate: Number = Field(
        3.0, gt=0.0, le=100.0, description="LOS rates above this (rad/s) are a jump: frame rejected"
    )
    max_dt: Seconds = Field(0.5, gt=0.0, le=10.0, description="s; a gap longer than this restarts the filter")
    rate_cutoff: Hertz = Field(
        0.0, ge=0.0, le=1000.0, description="low-pass on the LOS rate vector (lambda_dot n), Hz; 0 = off"
    )
    rate_cutoff_min: Hertz = Field(
        0.0, ge=0.0, le=1000.0, description="> 0: the rate low-pass's cut-off scheduled on the time to go, "
        "max(this, min(rate_cutoff, rate_cutoff_tgo / t_go)), Hz (needs guidance.gate_radius); 0 = rate_cutoff"
    )
    rate_cutoff_tgo: Number = Field(
        2.0, gt=0.0, le=100.0, description="the scheduled cut-off is at least this / time to go (Hz): its lag "
        "1 / (2 pi f_c) stays below t_go / (2 pi this)"
    )
    kind: Literal["lowpass", "kalman"] = Field(
        "lowpass", description="lowpass: the low-pass above, rate by differencing; kalman: constant-velocity "
        "Kalman filter on the LOS (perception/los.py LosKalman; docs/noise.md), rate_cutoff still applies"
    )
    kalman_accel: Number = Field(0.5, gt=0.0, le=1000.0, description="Kalman: white LOS acceleration, rad/s^2/rtHz")
    kalman_accel_width: Number = Field(0.0, ge=0.0, le=10000.0, description="Kalman: > 0: the LOS acceleration "
                                       "grows with the box, kalman_accel * (1 + size / this px); 0 = constant")
    kalman_px: Number = Field(1.5, gt=0.0, le=1000.0, description="Kalman: box-centre noise std at zero size, px")
    kalman_px_rel: Number = Field(0.03, ge=0.0, le=10.0, description="Kalman: + this times the box size, px/px")
    kalman_gate: Number = Field(4.0, gt=0.0, le=1000.0, description="Kalman: innovations beyond this many sigmas "
                                "are rejected (wrong target)")


class Config(Section):
    airframe: AirframeConfig = AirframeConfig()
    camera: CameraConfig = CameraConfig()
    guidance: GuidanceConfig = GuidanceConfig()
    los_filter: LosFilterConfig = LosFilterConfig()
    perception: PerceptionConfig = PerceptionConfig()
    link: LinkConfig = LinkConfig()
    safety: SafetyConfig = SafetyConfig()
    app: AppConfig = AppConfig()
    log: LogConfig = LogConfig()
    sim: SimConfig = SimConfig()
    hover: HoverConfig = HoverConfig()  # in-flight hover-thrust estimate (companion/hover.py)
    px4: PX4Config = PX4Config()

    @model_validator(mode="after")
    def _cross_checks(self) -> Config:
        uptilt = camera_uptilt(self)
        if uptilt is not None:  # the exact FOV bound measures from the pitched optical axis (companion/guidance.py)
            limit = min(self.guidance.gamma_bar + self.airframe.max_tilt, 89.0)
            if abs(uptilt) >= limit:
                raise ValueError(
                    f"camera.mount.pitch {uptilt:g} deg: |pitch| must stay below min(89, guidance.gamma_bar + "
                    f"airframe.max_tilt) = {limit:g} deg, or no attitude within the tilt envelope sees a gate ahead"
                )
            return self._other_checks()
        # Otherwise the controller keeps the LOS within gamma_bar of body x; a tilted camera eats into that margin.
        misalign = math.degrees(math.acos(np.clip(self.camera.R_body_cam[:, 2] @ np.array([1.0, 0, 0]), -1, 1)))
        if misalign >= self.guidance.gamma_bar:
            raise ValueError(
                f"camera.mount tilts the optical axis {misalign:.1f} deg off body x, "
                f">= guidance.gamma_bar {self.guidance.gamma_bar} deg: the FOV bound cannot be kept"
            )
        return self._other_checks()

    def _other_checks(self) -> Config:
        if self.airframe.f_min >= G:
            raise ValueError("airframe.thrust_min is at or above hover thrust")
        exposed = self.link.exposure_problem()  # here, not in LinkConfig: url and allow_all_interfaces together
        if exposed is not None:
            raise ValueError(exposed)
        return self


def camera_uptilt(cfg: Config) -> float | None:
    """The camera's uptilt (camera.mount.pitch, deg) when the solver handles it exactly, else None.

    Exactly handled: a mount pitched about body y only (roll = yaw = 0) with ``guidance.fov: exact``. Any other
    mount (or the paper's FOV bound) is taken conservatively: gamma_bar minus the optical axis's angle off body x.
    """
    m = cfg.camera.mount
    return m.pitch if cfg.guidance.fov == "exact" and m.roll == 0.0 and m.yaw == 0.0 else None


def default_config_dir() -> Path:
    env = os.environ.get("COMPANION_CONFIG_DIR")
    if env:
        return Path(env)
    return Path(__file__).resolve().parent.parent / "config"


def _load_with_includes(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    path = path.resolve()
    if path in seen:
        raise ConfigError(f"{path}: include loop ({' -> '.join(str(p) for p in (*seen, path))})")
    data = read_yaml(path)
    includes = data.pop("include", [])
    if isinstance(includes, str):
        includes = [includes]
    if not isinstance(includes, list) or not all(isinstance(i, str) for i in includes):
        raise ConfigError(f"{path}: include: expected a list of file names (got {includes!r})")
    merged: dict[str, Any] = {}
    for inc in includes:
        merged = deep_merge(merged, _load_with_includes(path.parent / inc, (*seen, path)))
    return deep_merge(merged, data)


def _validate_one(path: Path, data: dict[str, Any]) -> None:
    """Validate one file's content alone, so an error names the file that holds the bad value."""
    try:
        Config.model_validate(data)
    except ValidationError as e:
        # Cross-section checks may fail only once files are merged; blame the file only for field errors.
        if e.errors()[0]["loc"]:
            raise ConfigError(format_validation_error(e, str(path))) from None


def load_config(
    files: Sequence[str | Path] = (),
    overrides: Iterable[str] = (),
    *,
    base: str | Path | None = None,
) -> Config:
    """Build the Config: base file (default config/default.yaml) + files + ``section.key=value`` overrides."""
    base_path = Path(base) if base is not None else default_config_dir() / "default.yaml"
    steps: list[tuple[str, dict[str, Any]]] = []  # (source named in errors, its data), in order
    for p in (base_path, *map(Path, files)):
        data = _load_with_includes(p)
        _validate_one(p, data)
        steps.append((str(p), data))
    for ov in overrides:
        one = parse_override(ov)
        try:
            Config.model_validate(deep_merge({}, one))
        except ValidationError as e:
            if e.errors()[0]["loc"]:
                raise ConfigError(format_validation_error(e, f"--set {ov}")) from None
        steps.append((f"--set {ov}", one))
    merged: dict[str, Any] = {}
    for _, data in steps:
        merged = deep_merge(merged, data)
    try:
        return Config.model_validate(merged)
    except ValidationError as e:
        raise ConfigError(format_validation_error(e, _culprit(steps))) from None


def _culprit(steps: Sequence[tuple[str, dict[str, Any]]]) -> str:
    """The source whose addition first makes the merged config invalid (a cross-section error's cause).

    Each source alone was valid, so the first invalid prefix names the file or --set that broke it.
    Runs on the error path only.
    """
    merged: dict[str, Any] = {}
    for name, data in steps:
        merged = deep_merge(merged, data)
        try:
            Config.model_validate(merged)
        except ValidationError:
            return name
    return ", ".join(name for name, _ in steps)


def config_as_dict(cfg: Config) -> dict[str, Any]:
    """Plain data (canonical units) for logs and result files."""
    return cfg.model_dump(mode="json")


def add_config_arguments(parser: Any) -> None:
    """The config options every command shares."""
    parser.add_argument(
        "--config", "-c", action="append", default=[], metavar="FILE",
        help="YAML overlay on top of config/default.yaml (repeatable; later files win)",
    )
    parser.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
        help="override one value, e.g. --set guidance.k_pn=2.5 or --set sim.camera.delay='100 ms'",
    )


def config_from_args(args: Any) -> Config:
    return load_config(getattr(args, "config", []), getattr(args, "overrides", []))
