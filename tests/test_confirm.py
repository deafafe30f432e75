"""The operator's confirmation (companion/confirm.py) and the engagement waiting for it (pure)."""

from __future__ import annotations

import numpy as np

from companion.config import load_config
from companion.confirm import ConfirmParams, OperatorConfirm, RcReading, engage_mode
from companion.controller import PNController
from companion.engagement import Engagement, Phase
from perception.types import BoundingBox

P = ConfirmParams(channel=3, threshold_us=1700.0, max_age=0.5)
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
