"""Operator-confirmed engagement (``app.engage: confirm``): the decision, pure.

The app acquires and tracks; once the engagement has a stable, verified candidate it waits in ACQUIRE (PX4 holds)
and shows it (live view, log, status). It engages only when the operator confirms: the RC switch
(``app.confirm.rc_channel``, from PX4's RC_CHANNELS) turned ON *while a candidate was awaiting confirmation*. A
switch already on when the candidate appeared does not count (a switch left on would otherwise engage whatever
is tracked next); the operator turns it off and on again. Confirmation lasts while the switch stays on; turning it
off, or the RC reading going stale (``max_age``), withdraws it: the engagement ends at once in ABORT
NOT_CONFIRMED, which the flight app carries out as Hold.

The ground station is the other way (``OperatorConfirm.command``): a COMMAND_LONG addressed to the companion's own
system/component id with command ``app.confirm.command`` (MAV_CMD_USER_1 unless configured), param1 1 = confirm,
0 = withdraw; PX4 forwards it from its GCS link to the onboard link. Same rules as the switch: a confirm counts
only while a candidate awaits (else TEMPORARILY_REJECTED), a withdraw ends a confirmed engagement at once. RC and
GCS combine as "either confirms, either withdraws": the switch turned off (or its reading going stale) withdraws a
confirmation whichever way it came, and so does the GCS's withdraw; a switch left ON after a GCS withdraw confirms
nothing until it is turned off and on again. A GCS confirmation lasts while that ground station is heard: no
HEARTBEAT from it for ``app.confirm.gcs_max_age`` withdraws it (the operator could no longer withdraw).

``OperatorConfirm.step(t, rc, awaiting)`` -> True (confirmed), False (not); the engagement gets None in ``auto``
mode. ``OperatorConfirm.command(t, cmd, awaiting)`` -> (MAV_RESULT, why) for the COMMAND_ACK.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from companion.config import Config

UNUSED_US = 65535  # RC_CHANNELS: channel not in use
MAV_CMD_USER_1 = 31010  # the default confirm/withdraw command (app.confirm.command)
# MAV_RESULT values of the COMMAND_ACK
ACCEPTED, TEMPORARILY_REJECTED, DENIED = 0, 1, 2


def real_camera(cfg: Config) -> bool:
    """A camera device (V4L2 index or /dev path, a network stream, a GStreamer pipeline), not the synthetic
    camera nor a video file played back."""
    src = str(cfg.perception.source).strip()
    if cfg.app.camera == "synthetic" or src == "synthetic":
        return False
    return src.isdigit() or src.startswith(("/dev/", "rtsp://", "rtsps://", "http://", "https://", "udp://")) \
        or "!" in src


def engage_mode(cfg: Config) -> str:
    """app.engage, or when unset: confirm for a real camera, auto otherwise (synthetic, a video file)."""
    if cfg.app.engage is not None:
        return cfg.app.engage
    return "confirm" if real_camera(cfg) else "auto"


@dataclass(frozen=True, slots=True)
class RcReading:
    t: float  # when it arrived, s (the caller's monotonic clock)
    channels_us: tuple[int, ...]  # chan1_raw, chan2_raw, ... (PWM us; 65535 unused)


@dataclass(frozen=True, slots=True)
class GcsCommand:
    """The ground station's confirm/withdraw command as it arrived (COMMAND_LONG/COMMAND_INT)."""

    t: float  # when it arrived, s (the caller's monotonic clock)
    param1: float  # 1 confirm, 0 withdraw
    sysid: int  # the sender (the ground station)
    compid: int


@dataclass(frozen=True, slots=True)
class ConfirmParams:
    channel: int  # 1-based
    threshold_us: float
    max_age: float  # s
    gcs_max_age: float = 3.0  # s

    @classmethod
    def from_config(cls, cfg: Config) -> ConfirmParams:
        c = cfg.app.confirm
        return cls(c.rc_channel, float(c.threshold), float(c.max_age), float(c.gcs_max_age))


class OperatorConfirm:
    """The switch's and the ground station's state machine: confirmation latches on an OFF -> ON edge of the switch,
    or on a GCS confirm, seen while a candidate awaits; either way of withdrawing ends it."""

    def __init__(self, params: ConfirmParams) -> None:
        self.p = params
        self._prev_on: bool | None = None
        self.confirmed = False
        self.by: str | None = None  # "rc" or "gcs": who confirmed (while confirmed)
        self._gcs: tuple[int, int] | None = None  # the ground station that confirmed (sysid, compid)
        self._gcs_heard = -math.inf  # its last HEARTBEAT (or command)
        self.why = "no RC reading yet"
        self.withdrawn: str | None = None  # why the last confirmation ended (for the log), until read

    def switch_on(self, t: float, rc: RcReading | None) -> bool:
        """The switch reads ON now (a fresh reading of a used channel above the threshold)."""
        if rc is None or t - rc.t > self.p.max_age:
            self.why = "no fresh RC reading" if rc is None else f"RC reading {t - rc.t:.1f} s old"
            return False
        i = self.p.channel - 1
        if i >= len(rc.channels_us) or rc.channels_us[i] in (UNUSED_US, 0) or not math.isfinite(rc.channels_us[i]):
            self.why = f"RC channel {self.p.channel} not in use"
            return False
        on = rc.channels_us[i] > self.p.threshold_us
        self.why = f"RC channel {self.p.channel} at {rc.channels_us[i]} us ({'on' if on else 'off'})"
        return on

    def step(self, t: float, rc: RcReading | None, awaiting: bool, acquiring: bool = False) -> bool:
        """Confirmed now? ``awaiting``: the engagement shows a candidate and waits for the operator;
        ``acquiring``: it is still in ACQUIRE (not yet flying at anything)."""
        if self.confirmed and acquiring and not awaiting:
            # The confirmation was for the candidate shown; lost before the engagement began, it must not carry
            # over to whatever is tracked next (a switch left on is not a new confirmation: off and on again).
            self._withdraw("the confirmed candidate was lost before the engagement began: confirm the next one")
        on = self.switch_on(t, rc)
        if not on and (self._prev_on or self.by == "rc"):
            # the switch went off (or its reading stale): withdraws whichever way the confirmation came; a switch
            # that simply stays off (a GCS-confirmed flight without RC) withdraws nothing
            self._withdraw(f"RC switch: {self.why}")
        elif on and awaiting and self._prev_on is False and not self.confirmed:
            self._confirm("rc")  # turned on while the candidate was shown
        if self.by == "gcs" and t - self._gcs_heard > self.p.gcs_max_age:
            self._withdraw(f"ground station {self._gcs} not heard for {t - self._gcs_heard:.1f} s "
                           f"(app.confirm.gcs_max_age {self.p.gcs_max_age:g} s)")
        self._prev_on = on
        return self.confirmed

    def command(self, t: float, cmd: GcsCommand, awaiting: bool) -> tuple[int, str]:
        """The ground station's confirm (param1 1) or withdraw (0): (MAV_RESULT, why) for its COMMAND_ACK."""
        if cmd.param1 not in (0.0, 1.0):  # NaN too
            return DENIED, f"param1 must be 1 (confirm) or 0 (withdraw), not {cmd.param1}"
        if cmd.param1 == 1.0:
            if self.confirmed:
                if self.by == "gcs" and (cmd.sysid, cmd.compid) == self._gcs:
                    self._gcs_heard = max(self._gcs_heard, cmd.t)
                return ACCEPTED, f"already confirmed (by {'RC switch' if self.by == 'rc' else 'ground station'})"
            if not awaiting:
                return TEMPORARILY_REJECTED, "no candidate awaiting confirmation"
            self._gcs, self._gcs_heard = (cmd.sysid, cmd.compid), cmd.t
            self._confirm("gcs")
            return ACCEPTED, "confirmed from the ground station"
        if self.confirmed:
            self._withdraw(f"withdrawn from the ground station {(cmd.sysid, cmd.compid)}")
            return ACCEPTED, "confirmation withdrawn"
        if awaiting:
            return ACCEPTED, "nothing confirmed yet: the candidate stays unconfirmed"
        return TEMPORARILY_REJECTED, "nothing to withdraw: no candidate awaiting, no engagement confirmed"

    def heard(self, t: float, sysid: int, compid: int) -> None:
        """A HEARTBEAT from (sysid, compid): keeps a confirmation from that ground station alive."""
        if (sysid, compid) == self._gcs:
            self._gcs_heard = max(self._gcs_heard, t)

    def _confirm(self, by: str) -> None:
        self.confirmed, self.by, self.withdrawn = True, by, None

    def _withdraw(self, why: str) -> None:
        if self.confirmed:
            self.withdrawn = why
        self.confirmed, self.by = False, None
