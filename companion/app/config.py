"""Config sections of the flight app (link, safety, app behaviour, flight log)."""

from __future__ import annotations

from pydantic import Field

from companion.configbase import Hertz, Meters, Seconds, Section


class LinkConfig(Section):
    """How the app reaches the autopilot through mavsdk."""

    url: str = Field("udpin://127.0.0.1:14540", description="mavsdk connection URL (udpin://, udpout://, serial://)")
    connect_timeout: Seconds = Field(10.0, gt=0.0, le=600.0)
    setpoint_rate: Hertz = Field(30.0, ge=5.0, le=250.0)


class SafetyConfig(Section):
    """Abort limits; every abort ends in a named safe state."""

    target_lost_timeout: Seconds = Field(1.0, gt=0.0, le=30.0)
    altitude_floor: Meters = Field(2.0, ge=0.0, le=1000.0, description="barometric altitude above take-off, m")
    max_engagement_time: Seconds = Field(20.0, gt=0.0, le=600.0)
    perception_stall_timeout: Seconds = Field(0.5, gt=0.0, le=10.0)


class AppConfig(Section):
    """State machine behaviour."""

    takeoff_altitude: Meters = Field(10.0, gt=0.5, le=500.0)
    acquire_frames: int = Field(10, ge=1, le=1000)


class LogConfig(Section):
    directory: str = Field("flights", description="one sub-folder per flight is created here")
