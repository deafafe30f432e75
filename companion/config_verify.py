"""Config sections of target verification, operator-confirmed engagement and the live view (issue 18)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from companion.configbase import Deg, Meters, Number, Seconds, Section


class VerifyConfig(Section):
    """Is a box the configured target (companion/verify.py): checked at ACQUIRE and during ENGAGE."""

    enabled: bool = Field(True, description="check candidates and engaged boxes against the configured target")
    max_view_angle: Deg = Field(
        75.0, ge=0.0, lt=90.0, description="deg; a ring seen at most this far off its axis: an uncut box's "
        "min/max side ratio >= cos(this) (0 = no shape rule)")
    max_range: Meters = Field(
        0.0, ge=0.0, le=10000.0, description="m; a box smaller than the gate (guidance.gate_radius) at this range "
        "is not the gate (0 = no far limit)")
    min_acquire_range: Meters = Field(
        0.0, ge=0.0, le=1000.0, description="m; at ACQUIRE a box larger than the gate at this range is not the "
        "gate to engage (0 = no near limit)")
    growth: bool = Field(
        True, description="during ENGAGE, a box whose size does not follow our own acceleration towards it as the "
        "configured ring's must (companion/growthcheck.py) is another object: no box (coast, then TARGET_LOST)")
    growth_min_push: Meters = Field(
        4.0, gt=0.0, le=1000.0, description="m; growth: judged once our own acceleration has moved us this far "
        "along the line of sight")
    growth_max_push: Meters = Field(
        10.0, gt=0.0, le=1000.0, description="m; growth: no more judged once our own acceleration has moved us this "
        "far (later a gate's own motion weighs more than the accelerometer's integral can tell apart)")
    growth_min_scale: Number = Field(
        0.3, gt=0.0, lt=1.0, description="growth: the box's range follows our motion by at least this fraction (a "
        "ring of the configured size: 1; a gate up to 1/this x the configured size passes)")
    size_tolerance: Number = Field(
        0.7, gt=0.0, le=1.0, description="a detector's box may be this factor tighter (or 1/this looser) than "
        "the ring's projection")
    acquire_cut: bool = Field(
        False, description="accept a candidate cut by the image border at ACQUIRE (its shape and size cannot be "
        "checked; during ENGAGE a cut box is always accepted)")
    acquire_margin: Number = Field(
        0.02, ge=0.0, le=0.2, description="fraction of the image width: at ACQUIRE a candidate with an edge this near "
        "the border counts as cut (a detector's edges wander by several px between frames; 0: within 3 px only)")
    rival: bool = Field(
        True, description="at ACQUIRE, a candidate is not engaged while another object in view (one that passes the "
        "cut, shape and range rules) is as likely the target: their mean detector confidences over the stable-track "
        "streak within rival_margin (companion/rival.py); it is looked past. With app.engage confirm only another "
        "leading by rival_margin replaces the candidate shown (the operator judges two alike)")
    rival_margin: Number = Field(
        0.05, ge=0.0, le=1.0, description="rival: the candidate's mean confidence must exceed the best other "
        "candidate's by more than this")
    rival_engaged_frames: int = Field(
        2, ge=0, le=100, description="rival while engaged: the engaged box counts as no box (and is looked past) "
        "once another candidate at most half its size, passing the cut, shape and range rules, has had a confidence "
        "more than rival_margin above it in this many frames in a row (a detector seeing the frame at half size rates "
        "a smaller object lower, not higher: the box has merged with background; companion/rival.py). 0 = off")
    min_similarity: Number = Field(
        0.0, ge=0.0, le=1.0, description="appearance (hue-saturation histogram of the box, Bhattacharyya "
        "coefficient) against the box the track began with; below it is another object (0 = off)")


class ConfirmConfig(Section):
    """The operator's confirmation (app.engage: confirm): an RC switch read from PX4 (RC_CHANNELS), or a command
    from the ground station (COMMAND_LONG to the companion's own ids, forwarded by PX4). Either confirms, either
    withdraws."""

    rc_channel: int = Field(7, ge=1, le=18, description="RC channel of the engage switch (1-based, RC_CHANNELS)")
    threshold: Number = Field(
        1700.0, ge=800.0, le=2200.0, description="us; the switch is on when its channel reads above this "
        "(RC_CHANNELS chanN_raw, PWM microseconds)")
    max_age: Seconds = Field(
        0.5, gt=0.0, le=10.0, description="s; an RC reading older than this counts as the switch off")
    command: int = Field(
        31010, ge=0, le=65535, description="MAVLink command id the ground station sends to the companion's own "
        "system/component id to confirm (param1 1) or withdraw (param1 0); default MAV_CMD_USER_1 (31010); 0: no "
        "ground-station command, the RC switch only")
    gcs_max_age: Seconds = Field(
        3.0, gt=0.0, le=60.0, description="s; a confirmation from the ground station is withdrawn when no HEARTBEAT "
        "from that ground station arrived for this long (PX4 forwards them; ground stations send 1 Hz)")


class LiveViewConfig(Section):
    """The annotated camera stream over HTTP (MJPEG): box, track state, phase, the candidate awaiting confirmation."""

    enabled: bool = Field(False, description="serve the annotated stream at http://ADDRESS:PORT/")
    port: int = Field(8090, ge=0, le=65535, description="TCP port (0 = any free port, printed at start)")
    address: str = Field(
        "127.0.0.1", description="listen address; 127.0.0.1 unless set (another address exposes the camera)")
    max_fps: Number = Field(15.0, gt=0.0, le=120.0, description="frames per second served at most")
    quality: int = Field(70, ge=10, le=100, description="JPEG quality")


EngageMode = Literal["auto", "confirm"]
