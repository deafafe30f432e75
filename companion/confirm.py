"""Operator-confirmed engagement (``app.engage: confirm``): the decision, pure.

The app acquires and tracks; once the engagement has a stable, verified candidate it waits in ACQUIRE (PX4 holds)
and shows it (live view, log, status). It engages only when the operator confirms: the RC switch
(``app.confirm.rc_channel``, from PX4's RC_CHANNELS) turned ON *while a candidate was awaiting confirmation*. A
switch already on when the candidate appeared does not count (a switch left on would otherwise engage whatever
is tracked next); the operator turns it off and on again. Confirmation lasts while the switch stays on; turning it
off, or the RC reading going stale (``max_age``), withdraws it: the engagement ends at once in ABORT
NOT_CONFIRMED, which the flight app carries out as Hold.

``OperatorConfirm.step(t, awaiting)`` -> True (confirmed), False (not); the engagement gets None in ``auto`` mode.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from companion.config import Config

UNUSED_US = 65535  # RC_CHANNELS: channel not in use


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
class ConfirmParams:
    channel: int  # 1-based
    threshold_us: float
    max_age: float  # s

    @classmethod
    def from_config(cls, cfg: Config) -> ConfirmParams:
        c = cfg.app.confirm
        return cls(c.rc_channel, float(c.threshold), float(c.max_age))


class OperatorConfirm:
    """The switch's state machine: confirmation latches on an OFF -> ON edge seen while a candidate awaits."""

    def __init__(self, params: ConfirmParams) -> None:
        self.p = params
        self._prev_on: bool | None = None
        self.confirmed = False
        self.why = "no RC reading yet"

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

    def step(self, t: float, rc: RcReading | None, awaiting: bool) -> bool:
        """Confirmed now? ``awaiting``: the engagement shows a candidate and waits for the operator."""
        on = self.switch_on(t, rc)
        if not on:
            self.confirmed = False
        elif awaiting and self._prev_on is False:
            self.confirmed = True  # turned on while the candidate was shown
        self._prev_on = on
        return self.confirmed
