"""The operator's confirmation (companion/confirm.py) and the engagement waiting for it (pure)."""

from __future__ import annotations

import numpy as np

from companion.config import load_config
from companion.confirm import (
    ACCEPTED,
    DENIED,
    TEMPORARILY_REJECTED,
    ConfirmParams,
    GcsCommand,
    OperatorConfirm,
    RcReading,
    engage_mode,
)
from companion.controller import PNController
from companion.engagement import Engagement, Phase
from perception.types import BoundingBox

P = ConfirmParams(channel=3, threshold_us=1700.0, max_age=0.5, gcs_max_age=2.0)
LEVEL = np.array([1.0, 0.0, 0.0, 0.0])


def rc(t: float, v: int) -> RcReading:
    return RcReading(t, (1500, 1500, v, 1500))


def test_switch_must_be_turned_on_while_a_candidate_waits() -> None:
    c = OperatorConfirm(P)
    assert c.step(0.0, rc(0.0, 2000), awaiting=False) is False  # on before any candidate
    assert c.step(0.1, rc(0.1, 2000), awaiting=True) is False  # still the old ON: no edge
    assert c.step(0.2, rc(0.2, 1000), awaiting=True) is False
    assert c.step(0.3, rc(0.3, 2000), awaiting=True) is True  # turned on while shown
    assert c.step(0.4, rc(0.4, 2000), awaiting=False) is True  # lasts while on
    assert c.step(0.5, rc(0.5, 1700), awaiting=False) is False  # at the threshold is off
    assert c.step(0.6, rc(0.6, 2000), awaiting=False) is False  # on again without a candidate: nothing


def test_stale_or_unused_channel_withdraws() -> None:
    c = OperatorConfirm(P)
    c.step(0.0, rc(0.0, 1000), True)
    assert c.step(0.1, rc(0.1, 2000), True) is True
    assert c.step(0.55, rc(0.1, 2000), False) is True  # 0.45 s old: fresh
    assert c.step(0.65, rc(0.1, 2000), False) is False and "old" in c.why  # 0.55 s old: the RC is gone
    c = OperatorConfirm(P)
    assert c.step(0.0, RcReading(0.0, (1500, 1500, 65535)), True) is False and "not in use" in c.why
    assert c.step(0.1, RcReading(0.1, (1500,)), True) is False  # channel 3 not sent
    assert c.step(0.2, None, True) is False


def test_engage_mode_defaults() -> None:
    assert engage_mode(load_config([], ["perception.source='0'"])) == "confirm"
    assert engage_mode(load_config([], ["perception.source=rtsp://cam/1"])) == "confirm"
    assert engage_mode(load_config([], ["perception.source=flight.mp4"])) == "auto"
    assert engage_mode(load_config([], ["app.camera=synthetic"])) == "auto"
    assert engage_mode(load_config([], ["perception.source='0'", "app.engage=auto"])) == "auto"
    assert engage_mode(load_config([], ["app.camera=synthetic", "app.engage=confirm"])) == "confirm"


def test_engagement_waits_for_confirmation_and_aborts_when_withdrawn() -> None:
    cfg = load_config()
    n = cfg.app.acquire_frames
    e = Engagement.from_config(cfg, PNController.from_config(cfg))
    b = BoundingBox(320, 240, 40, 40)
    t, events = 0.0, []
    for _ in range(n + 20):
        d = e.step(t, b, LEVEL, 10.0, confirm=False)
        events += d.events
        t += 1 / 30
    assert e.phase is Phase.ACQUIRE and e.awaiting and events == ["candidate awaiting confirmation"]
    d = e.step(t, b, LEVEL, 10.0, confirm=True)
    assert d.phase is Phase.ENGAGE and "confirmed by the operator" in d.why and not e.awaiting
    d = e.step(t + 1 / 30, b, LEVEL, 10.0, confirm=True)
    assert d.phase is Phase.ENGAGE
    d = e.step(t + 2 / 30, b, LEVEL, 10.0, confirm=False)
    assert d.phase is Phase.ABORT and d.reason.name == "NOT_CONFIRMED" and d.setpoint is None
    # auto (None): engages on the stable track as before
    e = Engagement.from_config(cfg, PNController.from_config(cfg))
    phases = [e.step(k / 30, b, LEVEL, 10.0).phase for k in range(n)]
    assert phases[-1] is Phase.ENGAGE


def gcs(t: float, p1: float, sysid: int = 255, compid: int = 190) -> GcsCommand:
    return GcsCommand(t, p1, sysid, compid)


def test_gcs_confirm_counts_only_while_a_candidate_waits() -> None:
    c = OperatorConfirm(P)
    assert c.command(0.0, gcs(0.0, 1), awaiting=False)[0] == TEMPORARILY_REJECTED
    assert c.step(0.1, None, awaiting=True) is False  # the refused confirm was not kept for later
    assert c.command(0.2, gcs(0.2, 1), awaiting=True) == (ACCEPTED, "confirmed from the ground station")
    assert c.step(0.3, None, awaiting=False) is True and c.by == "gcs"  # no RC at all: lasts (GCS heard)
    assert c.command(0.4, gcs(0.4, 1), awaiting=False)[0] == ACCEPTED  # a resend while confirmed
    assert c.command(0.5, gcs(0.5, 0), awaiting=False) == (ACCEPTED, "confirmation withdrawn")
    assert c.step(0.6, None, awaiting=False) is False and "ground station" in str(c.withdrawn)
    assert c.command(0.7, gcs(0.7, 0), awaiting=False)[0] == TEMPORARILY_REJECTED  # nothing to withdraw
    assert c.command(0.8, gcs(0.8, 0), awaiting=True)[0] == ACCEPTED  # the candidate stays unconfirmed
    assert c.step(0.9, None, awaiting=True) is False
    for bad in (0.5, 2.0, float("nan")):
        assert c.command(1.0, gcs(1.0, bad), awaiting=True)[0] == DENIED
    assert c.step(1.1, None, awaiting=True) is False


def test_gcs_confirmation_lapses_when_that_ground_station_goes_silent() -> None:
    c = OperatorConfirm(P)
    c.command(0.0, gcs(0.0, 1), awaiting=True)
    c.heard(1.5, 200, 190)  # another system's heartbeat keeps nothing alive
    assert c.step(1.9, None, False) is True  # 1.9 s since the command (gcs_max_age 2.0)
    assert c.step(2.1, None, False) is False and "not heard for 2.1 s" in str(c.withdrawn)
    c = OperatorConfirm(P)
    c.command(0.0, gcs(0.0, 1), awaiting=True)
    for k in range(1, 10):  # its 1 Hz heartbeat
        c.heard(float(k), 255, 190)
        assert c.step(k + 0.9, None, False) is True
    assert c.step(11.1, None, False) is False


def test_rc_and_gcs_either_confirms_either_withdraws() -> None:
    # GCS confirms with the switch off: the switch staying off withdraws nothing; turning it on/off does
    c = OperatorConfirm(P)
    c.step(0.0, rc(0.0, 1000), True)
    c.command(0.1, gcs(0.1, 1), awaiting=True)
    assert c.step(0.2, rc(0.2, 1000), False) is True
    assert c.step(0.3, rc(0.3, 2000), False) is True and c.by == "gcs"
    assert c.step(0.4, rc(0.4, 1000), False) is False and "RC switch" in str(c.withdrawn)
    # the switch confirms, the GCS withdraws; the switch left ON then confirms nothing until cycled
    c = OperatorConfirm(P)
    c.step(0.0, rc(0.0, 1000), True)
    assert c.step(0.1, rc(0.1, 2000), True) is True and c.by == "rc"
    assert c.command(0.2, gcs(0.2, 0), awaiting=False)[0] == ACCEPTED
    assert c.step(0.3, rc(0.3, 2000), True) is False
    c.step(0.4, rc(0.4, 1000), True)
    assert c.step(0.5, rc(0.5, 2000), True) is True
    # an RC confirmation does not lapse with GCS silence (only with a stale RC reading)
    assert c.step(9.0, rc(9.0, 2000), False) is True


def test_a_confirmation_does_not_outlive_the_candidate_it_was_given_for() -> None:
    """Confirmed on the frame the candidate was lost: the next candidate must be confirmed again, not engaged."""
    cfg = load_config()
    n = cfg.app.acquire_frames
    e = Engagement.from_config(cfg, PNController.from_config(cfg))
    c = OperatorConfirm(P)
    b = BoundingBox(320, 240, 40, 40)
    t, k = 0.0, 0

    def step(box: BoundingBox | None, switch: int):  # the flight loop's order: confirm, then the engagement
        nonlocal t, k
        conf = c.step(t, rc(t, switch), e.awaiting, acquiring=e.phase is Phase.ACQUIRE)
        d = e.step(t, box, LEVEL, 10.0, confirm=conf)
        t, k = t + 1 / 30, k + 1
        return conf, d

    for _ in range(n + 5):
        step(b, 1000)
    assert e.awaiting
    conf, d = step(None, 2000)  # switched on while shown; the box is gone in that very frame
    assert conf is True and d.phase is Phase.ACQUIRE and not e.awaiting
    phases = [step(b, 2000)[1].phase for _ in range(n + 10)]  # a new candidate, the switch still on
    assert Phase.ENGAGE not in phases and e.awaiting and c.confirmed is False
    assert "lost before the engagement began" in (c.withdrawn or "")
    step(b, 1000)
    conf, d = step(b, 2000)  # turned on again while this candidate is shown
    assert conf is True and d.phase is Phase.ENGAGE
