"""The ``px4:`` config section: where PX4 SITL lives, which instance, and the SIH vehicle it simulates.

PX4's built-in simulator (SIH) reads its vehicle from parameters (``SIH_MASS``, ``SIH_IXX``, ...),
live, so one PX4 build stands in for several airframes. ``px4.sih`` is that vehicle; the defaults
are the x500-like profile measured in ../shared/px4-sitl/README.md, ``config/vehicles/sih.yaml``
holds PX4's own default SIH quad. ``px4.params`` are further PX4 parameters set at start.
"""

from __future__ import annotations

from pydantic import Field, field_validator, model_validator

from companion.configbase import Kilograms, Meters, Number, Seconds, Section


class SihConfig(Section):
    """The SIH rigid-body quadrotor (PX4 parameters SIH_*); x500-like by default (thrust-to-weight 2)."""

    mass: Kilograms = Field(2.0, gt=0.05, le=50.0, description="kg (SIH_MASS)")
    ixx: Number = Field(0.05, gt=0.0, le=10.0, description="kg m^2 (SIH_IXX)")
    iyy: Number = Field(0.05, gt=0.0, le=10.0, description="kg m^2 (SIH_IYY)")
    izz: Number = Field(0.06, gt=0.0, le=10.0, description="kg m^2 (SIH_IZZ)")
    t_max: Number = Field(9.81, gt=0.0, le=500.0, description="N per motor (SIH_T_MAX)")
    q_max: Number = Field(0.2, gt=0.0, le=50.0, description="N m per motor (SIH_Q_MAX)")
    l_roll: Meters = Field(0.2, gt=0.0, le=5.0, description="m, roll arm (SIH_L_ROLL)")
    l_pitch: Meters = Field(0.2, gt=0.0, le=5.0, description="m, pitch arm (SIH_L_PITCH)")
    kdv: Number = Field(0.15, ge=0.0, le=20.0, description="linear drag, N per m/s (SIH_KDV)")
    kdw: Number = Field(0.05, ge=0.0, le=20.0, description="angular drag, N m per rad/s (SIH_KDW)")
    t_tau: Seconds = Field(0.05, gt=0.0, le=1.0, description="s, motor time constant (SIH_T_TAU)")

    def params(self) -> dict[str, float]:
        return {f"SIH_{k.upper()}": float(v) for k, v in self.model_dump().items()}

    @property
    def thrust_to_weight(self) -> float:
        return 4.0 * self.t_max / (self.mass * 9.81)


class PX4Config(Section):
    """Real PX4 SITL (SIH) for ``companion sim --autopilot px4``, ``companion eval --autopilot px4``, tests."""

    sitl_dir: str = Field(
        "", description="PX4 SITL build with bin/px4 and etc/ (empty: the PX4_SITL_DIR environment variable)"
    )
    instance: int | None = Field(
        None, ge=0, le=9, description="PX4 instance -i N (UDP ports shift by N); empty: the first free one"
    )
    instance_min: int = Field(0, ge=0, le=9, description="lowest instance picked automatically")
    instance_max: int = Field(9, ge=0, le=9, description="highest instance picked automatically")
    speed_factor: Number = Field(
        1.0, description="PX4_SIM_SPEED_FACTOR; only 1: the app runs on the host's clock"
    )
    work_dir: str = Field(
        "", description="parent of the fresh per-run PX4 working folders (empty: the system's temp folder)"
    )
    preflight_timeout: Seconds = Field(120.0, gt=0.0, le=1200.0, description="s; start until pre-flight OK")
    sih: SihConfig = SihConfig()
    params: dict[str, float] = Field(
        default_factory=dict,
        description="further PX4 parameters set at start (they win over EKF2_GPS_DELAY 0 and "
        "MPC_THR_HOVER = airframe.hover_thrust, which are always set)",
    )
    truth_url: str = Field(
        "", description="pymavlink URL of SIH's display link (udpin:127.0.0.1:19410+N): ground truth for the "
        "synthetic camera and the score; empty: the autopilot's LOCAL_POSITION_NED (PX4's EKF)"
    )
    truth_origin: list[float] | None = Field(
        None, min_length=3, max_length=3,
        description="SIH_LOC_LAT0, SIH_LOC_LON0 (1e-7 deg), SIH_LOC_H0 (m); empty: the first truth message",
    )
    truth_rate: Number = Field(50.0, ge=10.0, le=250.0, description="Hz of HIL_STATE_QUATERNION asked from PX4")

    @field_validator("speed_factor")
    @classmethod
    def _real_time(cls, v: float) -> float:
        if v != 1.0:
            raise ValueError("only 1 is supported: the app flies on the host's clock, a faster SIH is a "
                             "different vehicle to it")
        return v

    @field_validator("params")
    @classmethod
    def _param_names(cls, v: dict[str, float]) -> dict[str, float]:
        for name in v:
            if not name or len(name) > 16 or not all(c.isupper() or c.isdigit() or c == "_" for c in name):
                raise ValueError(f"{name!r} is not a PX4 parameter name (upper case, digits, _, at most 16)")
        return v

    @model_validator(mode="after")
    def _range(self) -> PX4Config:
        if self.instance_min > self.instance_max:
            raise ValueError(f"instance_min {self.instance_min} > instance_max {self.instance_max}")
        return self
