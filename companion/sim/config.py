"""Config section of the in-process simulator and the evaluation scenarios.

Everything a perturbed scenario may change lives here: the true airframe (model error against
the controller's ``airframe`` section), wind, sensor noise, the geometric camera's noise, delay
and drops, the gate motions and the initial conditions.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from companion.configbase import (
    Deg,
    DegPerSecond,
    Hertz,
    Kilograms,
    Meters,
    MetersPerSecond,
    MetersPerSecond2,
    Number,
    Pixels,
    Seconds,
    Section,
)


class SimQuadConfig(Section):
    """The simulated vehicle (paper eq:meth_quadrotor_dynamics); x500-like defaults.

    ``mass``/``hover_thrust``/``thrust_to_weight`` left empty take the ``airframe`` section's values;
    set them to model a vehicle that differs from what the controller believes. ``mass_scale`` is the one
    setting for "a heavier (or lighter) vehicle with the same motors": it scales the airframe's mass and hover
    thrust by s and divides its thrust-to-weight by s (the explicit keys, when set, win).
    """

    mass_scale: Number = Field(
        1.0, gt=0.2, le=5.0, description="true weight / the airframe's, same motors: true mass = airframe.mass x s, "
        "hover thrust = airframe.hover_thrust x s, thrust-to-weight = airframe's / s (e.g. 1.25: 25 % heavier)"
    )

    mass: Kilograms | None = Field(None, gt=0.05, le=50.0, description="kg; default airframe.mass")
    hover_thrust: Number | None = Field(
        None, gt=0.05, lt=0.95, description="true normalised hover thrust; default airframe.hover_thrust"
    )
    thrust_to_weight: Number | None = Field(None, gt=1.05, le=10.0, description="default airframe's")
    tau_omega: Seconds = Field(0.04, gt=0.0, le=1.0, description="body-rate first-order time constant, s")
    tau_att: Seconds = Field(0.15, gt=0.0, le=2.0, description="attitude loop tau (rate = 2/tau q_e), s")
    tau_thrust: Seconds = Field(0.03, gt=0.0, le=1.0, description="collective-thrust first-order lag, s")
    drag_lin: Number = Field(0.05, ge=0.0, le=10.0, description="linear drag, N per m/s of airspeed")
    drag_quad: Number = Field(0.011, ge=0.0, le=10.0, description="quadratic drag, N per (m/s)^2")
    max_rate: DegPerSecond = Field(220.0, gt=1.0, le=2000.0, description="body-rate limit, deg/s")
    cmd_delay: Seconds = Field(
        0.0, ge=0.0, le=1.0, description="pure delay of every setpoint before the vehicle's loops act on it, s"
    )
    max_touchdown_speed: MetersPerSecond = Field(
        1.0, gt=0.0, le=20.0, description="descending faster than this at z = 0 is a ground contact"
    )


class WindConfig(Section):
    mean: list[Number] = Field(default_factory=lambda: [0.0, 0.0, 0.0], min_length=3, max_length=3,
                              description="constant wind, ENU m/s")
    gust_std: MetersPerSecond = Field(0.0, ge=0.0, le=30.0, description="gust std per axis, m/s")
    gust_tau: Seconds = Field(2.0, gt=0.0, le=100.0, description="gust correlation time (Gauss-Markov), s")


class SensorsConfig(Section):
    """IMU, attitude-estimate and barometer errors (white noise std; biases drawn once per run)."""

    accel_noise: MetersPerSecond2 = Field(0.05, ge=0.0, le=10.0)
    accel_bias: MetersPerSecond2 = Field(0.02, ge=0.0, le=5.0, description="std of the per-run bias")
    gyro_noise: DegPerSecond = Field(0.3, ge=0.0, le=100.0)
    gyro_bias: DegPerSecond = Field(0.1, ge=0.0, le=100.0, description="std of the per-run bias")
    attitude_noise: Deg = Field(0.05, ge=0.0, le=30.0, description="white noise per axis of the estimate")
    attitude_bias: Deg = Field(0.2, ge=0.0, le=30.0, description="std of the per-run estimate bias per axis")
    baro_noise: Meters = Field(0.1, ge=0.0, le=10.0)
    baro_bias: Meters = Field(0.5, ge=0.0, le=100.0, description="std of the per-run offset")


class MountErrorConfig(Section):
    """How the camera truly sits on the body, relative to what ``camera.mount`` says (deg, added to its angles)."""

    roll: Deg = Field(0.0, ge=-45.0, le=45.0, description="true camera.mount.roll minus the configured one, deg")
    pitch: Deg = Field(0.0, ge=-45.0, le=45.0, description="true camera.mount.pitch minus the configured one, deg "
                       "(+: the camera looks higher than configured; a gate ahead renders lower)")
    yaw: Deg = Field(0.0, ge=-45.0, le=45.0, description="true camera.mount.yaw minus the configured one, deg")


class SimCameraConfig(Section):
    """The geometric camera: true pose + gate -> pixel box (intrinsics from the ``camera`` section)."""

    mount_error: MountErrorConfig = MountErrorConfig()

    pixel_noise: Pixels = Field(1.0, ge=0.0, le=100.0, description="std of box centre/size noise, px")
    noise_model: Literal["white", "detector"] = Field(
        "white", description="white: i.i.d. Gaussian pixel_noise; detector: the shipped detector's measured box "
        "error (size-dependent, coloured, wrong targets, misses; docs/noise.md), pixel_noise unused"
    )
    detector_profile: Literal["x500", "sih"] = Field(
        "x500", description="fitted parameter set of the detector model (companion/sim/boxnoise.py PROFILES)"
    )
    delay: Seconds = Field(0.0, ge=0.0, le=2.0, description="box of frame t arrives at t + delay")
    drop_prob: Number = Field(0.0, ge=0.0, le=1.0, description="probability a frame gives no box")
    min_box: Pixels = Field(2.0, ge=0.0, le=100.0, description="boxes smaller than this are not detected, px")
    attitude_at_capture: bool = Field(
        True, description="a delayed box reaches the controller with the attitude estimate of its capture "
        "time (True) or of its arrival time (False, a pipeline without time matching)"
    )
    clip_box: bool = Field(
        False, description="False: box centred on the projected gate centre (paper); True: ring extent clipped "
        "to the image, like a detector's box of a partly visible ring"
    )


class GateMotionConfig(Section):
    """Paper V-A gate motions. Planar/knot omega is solved so their top speeds equal these values."""

    linear_slow_speed: MetersPerSecond = Field(2.5, ge=0.0, le=50.0)
    linear_fast_speed: MetersPerSecond = Field(5.0, ge=0.0, le=50.0)
    d_plan: Meters = Field(2.0, gt=0.0, le=100.0)
    d_knot: Meters = Field(1.0, gt=0.0, le=100.0)
    planar_top_speed: MetersPerSecond = Field(3.1, gt=0.0, le=50.0)
    knot_top_speed: MetersPerSecond = Field(1.2, gt=0.0, le=50.0)
    recede_speed: MetersPerSecond = Field(
        9.0, ge=0.0, le=50.0, description="motion recede: speed away from the vehicle along the normal (the paper's "
        "truck: 8-10 m/s)")
    sinusoid_amplitude: Meters = Field(
        0.95, ge=0.0, le=100.0, description="motion sinusoid: lateral amplitude, m (0.95 m at 0.5 Hz peaks at 3 m/s)")
    sinusoid_frequency: Hertz = Field(0.5, gt=0.0, le=20.0, description="motion sinusoid: frequency, Hz")


class SimTargetConfig(Section):
    """What the camera sees: a ring, a square or a rectangle, in the air or standing on the ground."""

    shape: Literal["ring", "square", "rectangle"] = Field(
        "ring", description="ring: a circle of diameter width; square: width x width; rectangle: width x height")
    width: Meters | None = Field(
        None, gt=0.05, le=100.0, description="target width (ring: diameter), m; default 2 x scenario.visual_radius")
    height: Meters | None = Field(None, gt=0.05, le=100.0, description="rectangle height, m; default the width")
    on_ground: bool = Field(
        False, description="stand on the ground (bottom edge at z = 0) instead of floating near the start altitude")

    def size(self, visual_radius: float) -> tuple[float, float]:
        """(width, height) in metres of the target the camera sees."""
        w = self.width if self.width is not None else 2.0 * visual_radius
        if self.shape == "rectangle":
            return w, (self.height if self.height is not None else w)
        return w, w


class ScenarioConfig(Section):
    """Initial conditions (paper V-A) and run limits."""

    distance_min: Meters = Field(20.0, gt=1.0, le=1000.0)
    distance_max: Meters = Field(30.0, gt=1.0, le=1000.0)
    speed: MetersPerSecond = Field(10.0, ge=0.0, le=40.0, description="initial speed")
    angle_max: Deg = Field(10.0, ge=0.0, le=45.0, description="|angle| between initial velocity and LOS")
    altitude_min: Meters = Field(10.0, gt=0.5, le=500.0, description="start altitude AGL, m")
    altitude_max: Meters = Field(20.0, gt=0.5, le=500.0)
    gate_height_offset: Meters = Field(1.0, ge=0.0, le=50.0, description="gate centre +- this, m")
    visual_radius: Meters = Field(1.0, gt=0.05, le=20.0, description="radius of the ring the camera sees, m")
    gate_radii: list[Annotated[Number, Field(gt=0.0, le=100.0)]] = Field(
        default_factory=lambda: [0.5, 1.0, 2.0], min_length=1, max_length=100)
    timeout: Seconds = Field(20.0, gt=0.1, le=600.0, description="run ends unscored after this, s")
    fov_timeout: Seconds = Field(1.0, gt=0.0, le=60.0, description="no box for this long: fov_lost, s")


class BaselineConfig(Section):
    """The PN acceleration controller of Bhattacharya et al. (paper Table III), velocity known."""

    nav_constant: Number = Field(3.0, gt=0.0, le=20.0, description="PN navigation constant N")
    speed: MetersPerSecond = Field(5.0, gt=0.0, le=40.0, description="speed held along the LOS, m/s")
    speed_gain: Number = Field(1.0, gt=0.0, le=20.0, description="speed loop gain, 1/s")
    max_tilt: Deg = Field(45.0, gt=1.0, lt=89.0, description="tilt limit (PX4 MPC_TILTMAX_AIR), deg")


class SimConfig(Section):
    seed: int = Field(0, ge=0)
    rate: Hertz = Field(200.0, ge=200.0, le=5000.0, description="dynamics integration rate, Hz")
    imu_to_controller: bool = Field(
        True, description="give the simulated accelerometer to the controller (its closing-speed estimate); "
        "false: box and attitude only, like an app without IMU telemetry"
    )
    quad: SimQuadConfig = SimQuadConfig()
    wind: WindConfig = WindConfig()
    sensors: SensorsConfig = SensorsConfig()
    camera: SimCameraConfig = SimCameraConfig()
    gates: GateMotionConfig = GateMotionConfig()
    target: SimTargetConfig = SimTargetConfig()
    scenario: ScenarioConfig = ScenarioConfig()
    baseline: BaselineConfig = BaselineConfig()
