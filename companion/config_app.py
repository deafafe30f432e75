"""Config sections of the flight app (link, safety, app behaviour, flight log)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from companion.config_verify import ConfirmConfig, EngageMode, LiveViewConfig, VerifyConfig
from companion.configbase import Deg, Hertz, Meters, Number, Seconds, Section


def all_interfaces_reason(url: str) -> str | None:
    """Why a mavsdk URL makes mavsdk listen on every network interface, or None when it does not.

    mavsdk binds 0.0.0.0 on a random port for ``udpout://`` (to receive the answers), listens on every
    interface for ``udpin://0.0.0.0:PORT`` and for the deprecated ``udp://:PORT``, and serves ``tcpin://``
    on the address given.
    """
    u = url.strip().lower()
    if u.startswith("udpout://"):
        return "makes mavsdk bind 0.0.0.0 (every interface) on a random port"
    if u.startswith("tcpout://"):
        # An outgoing link off this machine carries the vehicle's commands over the network (MAVLink has no
        # authentication): the same rule as a link that listens on it.
        host = u[len("tcpout://"):].rsplit(":", 1)[0].strip("[]")
        if not _loopback(host):
            return f"connects to {host or '<no host>'}, off this machine (MAVLink over the network, unauthenticated)"
        return None
    for scheme in ("udpin://", "tcpin://", "udp://", "tcp://"):
        if u.startswith(scheme):
            host = u[len(scheme):].rsplit(":", 1)[0]
            if host in ("", "0.0.0.0", "[::]", "::"):
                return "listens on every network interface"
    return None


def _loopback(host: str) -> bool:
    import ipaddress

    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name: where it resolves is not known here, so not "this machine"


class LinkConfig(Section):
    """How the app reaches the autopilot through mavsdk."""

    url: str = Field("udpin://127.0.0.1:14540", description="mavsdk connection URL (udpin://, udpout://, serial://)")
    connect_timeout: Seconds = Field(10.0, gt=0.0, le=600.0)
    setpoint_rate: Hertz = Field(30.0, ge=5.0, le=250.0)
    command_timeout: Seconds = Field(5.0, gt=0.0, le=60.0, description="s; one MAVLink command incl. its ACK")
    health_timeout: Seconds = Field(30.0, gt=0.0, le=600.0, description="s; wait for PX4's preflight checks")
    link_lost_timeout: Seconds = Field(
        1.5, gt=0.0, le=30.0, description="s without any telemetry before the link counts as lost"
    )
    takeoff_timeout: Seconds = Field(30.0, gt=0.0, le=600.0, description="s; take-off to the target altitude")
    land_timeout: Seconds = Field(60.0, gt=0.0, le=600.0, description="s; landing and auto-disarm")
    mode_timeout: Seconds = Field(
        3.0, gt=0.0, le=60.0,
        description="s to see a commanded mode in PX4's heartbeat (1 Hz: a change shows 0.2-1.0 s after it happens)",
    )
    system_id: int = Field(1, ge=1, le=255, description="MAVLink system id of the autopilot (PX4 MAV_SYS_ID)")
    component_id: int = Field(1, ge=1, le=255, description="MAVLink component id of the autopilot (PX4: 1)")
    allow_all_interfaces: bool = Field(
        False, description="allow a link that listens on every network interface (udpout://, udpin://0.0.0.0, udp://:) "
        "or connects to another host (tcpout:// off loopback)"
    )
    events_metadata: str = Field(
        "", description="PX4 event metadata (all_events.json[.xz]); empty: the PX4 v1.15 file shipped with the app"
    )

    def exposure_problem(self) -> str | None:
        """The one-line reason this link may not be used (checked across sections by companion.config.Config)."""
        why = all_interfaces_reason(self.url)
        if why is not None and not self.allow_all_interfaces:
            return (f"link.url {self.url!r} {why}: anyone on the network could command the vehicle "
                    "(use udpin://127.0.0.1:PORT or a serial link, or set link.allow_all_interfaces: true)")
        return None


class SafetyConfig(Section):
    """Abort limits; every abort ends in a named safe state."""

    target_lost_timeout: Seconds = Field(1.0, gt=0.0, le=30.0)
    altitude_floor: Meters = Field(2.0, ge=0.0, le=1000.0, description="baro altitude above take-off, m")
    floor_lookahead: Seconds = Field(
        1.0, ge=0.0, le=5.0,
        description="the floor also trips when the barometric altitude, extrapolated this far at its sink rate, "
        "would be below it (a dive is caught while Hold can still brake it); 0 = the altitude alone")
    altitude_reference: float | None = Field(
        None, ge=-1000.0, le=10000.0,
        description="PX4's barometric altitude (ALTITUDE.altitude_monotonic, m) of the ground the floor is "
        "above; empty: the altitude at pre-flight (an app started on the ground). For a start in the air",
    )
    max_engagement_time: Seconds = Field(20.0, gt=0.0, le=600.0)
    perception_stall_timeout: Seconds = Field(
        0.5, gt=0.0, le=10.0,
        description="s without a fresh setpoint from the control loop before the watchdog hands over to HOLD",
    )
    loop_stall_timeout: Seconds = Field(
        2.0, ge=0.5, le=60.0,
        description="s the event loop may stop while commanding before the process kills itself (PX4 failsafe); "
        "at least 0.5 s (a detector call or a GC pause is not a stall) and later than the link's loop guard",
    )
    camera_frozen_timeout: Seconds = Field(
        0.3, ge=0.05, le=5.0,
        description="s of byte-identical camera images (fresh timestamps) before the camera counts as frozen "
        "(CAMERA_FAILED); perception/plausibility.py says why",
    )
    land_after_abort: bool = Field(
        False, description="after an abort in HOLD, land and disarm (False: stay in HOLD for the pilot)"
    )
    require_safe_offboard_loss: bool = Field(
        True, description="refuse to arm unless PX4's offboard-loss failsafe ends in a safe mode (COM_OBL_RC_ACT ...)"
    )
    max_offboard_loss_time: Seconds = Field(
        2.0, gt=0.0, le=60.0, description="s; largest COM_OF_LOSS_T accepted (PX4 flies the last setpoint that long)"
    )
    telemetry_reject_limit: int = Field(
        5, ge=1, le=1000, description="rejected attitude samples within 1 s that abort (TELEMETRY_INVALID)"
    )

    @model_validator(mode="after")
    def _layers(self) -> SafetyConfig:
        # The deadman is the last layer (companion/app/deadman.py): it must not fire before the link's
        # loop guard (2 x perception_stall_timeout + 0.2 s) has had its chance to hand over to HOLD.
        guard = 2.0 * self.perception_stall_timeout + 0.2
        if self.loop_stall_timeout <= guard:
            raise ValueError(f"safety.loop_stall_timeout {self.loop_stall_timeout:g} s must exceed the link's loop "
                             f"guard (2 x safety.perception_stall_timeout + 0.2 s = {guard:g} s)")
        return self


class SyntheticCameraConfig(Section):
    """Virtual gates seen from the vehicle pose that arrives over MAVLink (sensor simulation only).

    The scene is anchored at the first frame: gate k (k = 1..count) is placed k * distance ahead of
    the vehicle along its heading. Noise, drops and minimum box size come from ``sim.camera``.
    """

    render: Literal["geometric", "image"] = Field(
        "image", description="geometric: projected box; image: rendered frames through the detector"
    )
    motion: Literal["stationary", "linear_slow", "linear_fast", "planar", "knot", "recede", "sinusoid"] = Field(
        "linear_fast", description="the gates' motion (companion/sim/gates.py; recede and sinusoid as sim.gates sets "
        "them); the target's shape, size and ground placement come from sim.target"
    )
    distance: Meters = Field(25.0, gt=1.0, le=500.0, description="m from the vehicle to the first gate")
    lateral_offset: Meters = Field(0.0, ge=-100.0, le=100.0, description="m, to the right of the heading")
    height_offset: Meters = Field(0.0, ge=-50.0, le=50.0, description="m above the vehicle")
    radius: Meters = Field(1.0, gt=0.05, le=20.0, description="visual gate radius, m")
    count: int = Field(1, ge=1, le=20, description="gates in a row")
    fault: Literal["none", "stall", "nan_box", "los_jump", "lose_target", "exception", "block", "freeze"] = Field(
        "none", description="test switch: camera/perception fault injected after fault_after "
        "(freeze: the camera repeats its last image with fresh timestamps)"
    )
    fault_after: Seconds = Field(1.0, ge=0.0, le=600.0, description="s after the first frame")


class AppConfig(Section):
    """State machine behaviour."""

    start: Literal["takeoff", "pilot"] = Field(
        "takeoff", description="takeoff: arm and take off; pilot: wait for the pilot's hover"
    )
    takeoff_altitude: Meters = Field(10.0, gt=0.5, le=500.0)
    pilot_wait_timeout: Seconds = Field(120.0, gt=0.0, le=3600.0, description="s; start=pilot only")
    land_rest_tilt: Deg = Field(
        5.0, gt=0.0, le=45.0, description="deg; before a landing PX4's Hold must hold the vehicle this level for "
        "land_rest_time (it brakes tilted: Land commanded at speed touched down sliding, companion/app/atrest.py)"
    )
    land_rest_time: Seconds = Field(1.0, ge=0.0, le=30.0, description="s level = at rest")
    land_rest_timeout: Seconds = Field(
        15.0, ge=0.0, le=300.0, description="s; not level by then (steady wind tilts a hover): land anyway"
    )
    acquire_frames: int = Field(10, ge=1, le=1000, description="valid boxes in a row = stable track")
    acquire_timeout: Seconds = Field(15.0, gt=0.0, le=600.0, description="s; no stable track -> land")
    close_trigger: Literal["ttc", "size", "either"] = Field(
        "either", description="gate about to be passed: box time-to-contact, box size, or either"
    )
    ttc_threshold: Seconds = Field(0.25, gt=0.0, le=10.0, description="s; box time-to-contact")
    close_reckoning: bool = Field(
        True, description="also close when the range the closing-speed filter dead-reckons with the IMU, while the "
        "image gives it no range (the ring fills the view: guidance.closing_max_box), reaches half of "
        "guidance.gate_radius, once the gate's box was near; without it a slow vehicle steered at background boxes "
        "for up to 1.2 s after the crossing"
    )
    size_threshold: Number = Field(
        0.95, gt=0.0, le=2.0, description="box size (larger side) as a fraction of the image width; the default "
        "(the gate spans the image) leaves the close decision to time-to-contact, which scales with speed"
    )
    on_close: Literal["fly_through", "pull_up"] = Field(
        "fly_through",
        description="fly_through: hold attitude until the gate leaves the view; pull_up: recover at once",
    )
    pull_up_pitch: Deg = Field(
        25.0, ge=0.0, le=45.0, description="deg nose-up in a pull-up at most (brakes and climbs before impact; the "
        "planner picks the tilt up to this that clears the target's top by the most, companion/pullup.py)"
    )
    pull_up_margin: Meters = Field(
        1.5, ge=0.0, le=50.0, description="pull_up: planned clearance over the target's top, m (the pull-up fires "
        "when a later one would clear it by less)"
    )
    pull_up_response: Seconds = Field(
        0.35, ge=0.0, le=5.0, description="pull_up: s from the decision until the vehicle accelerates as planned "
        "(attitude and thrust lag, frame latency)"
    )
    target_width: Meters = Field(
        0.0, ge=0.0, le=100.0, description="pull_up: the target's width, m (0 = 2 x guidance.gate_radius)"
    )
    target_height: Meters = Field(
        0.0, ge=0.0, le=100.0, description="pull_up: the target's height, m (0 = its width)"
    )
    pass_timeout: Seconds = Field(1.0, gt=0.0, le=10.0, description="s; longest hold while passing a gate")
    recover_time: Seconds = Field(1.0, gt=0.0, le=30.0, description="s of level attitude and hover thrust")
    recover_thrust_scale: Number = Field(
        1.1, ge=0.8, le=1.5, description="recover thrust as a multiple of hover thrust (>1 climbs)"
    )
    next_gate: bool = Field(True, description="engage again if a new gate is tracked during recover")
    max_gates: int = Field(10, ge=1, le=1000, description="gates to engage in a row (camera synthetic: at most "
                           "synthetic.count, the course's length)")
    target_lock: bool = Field(
        True, description="during ENGAGE a box whose size or direction no approach explains is another object "
        "and counts as no box (companion/targetlock.py)"
    )
    camera: Literal["source", "synthetic"] = Field(
        "source", description="source: the perception camera source; synthetic: render from the vehicle pose"
    )
    synthetic: SyntheticCameraConfig = SyntheticCameraConfig()
    verify: VerifyConfig = VerifyConfig()
    engage: EngageMode | None = Field(
        None, description="auto: engage on a stable track; confirm: only while the operator confirms (RC switch or "
        "ground-station command, app.confirm); unset: confirm for a camera device or stream, auto for synthetic "
        "frames or a video file")
    confirm: ConfirmConfig = ConfirmConfig()
    live_view: LiveViewConfig = LiveViewConfig()
    status_interval: Seconds = Field(0.5, gt=0.0, le=60.0, description="s between status lines")


class LogConfig(Section):
    directory: str = Field("flights", description="one sub-folder per flight is created here")
    flush_interval: Seconds = Field(
        0.25, gt=0.0, le=1.0,
        description="s; CSV buffers reach the OS this often (a SIGKILL loses at most this + 50 ms)",
    )
    min_free_mb: Number = Field(
        20.0, ge=0.0, le=1e6, description="MB free under log.directory, or the flight is refused before it starts"
    )
    plot: bool = Field(True, description="write plot.png into the flight folder at the end")
