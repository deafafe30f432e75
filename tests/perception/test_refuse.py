"""A candidate the app refuses is looked past, not held (real PX4, x500, 2026-12-07 table, run091).

Logged: from take-off a 330x345 px box 5 px from the image's left border (confidence ~0.84, every frame) was tracked
by the pipeline; verification refused it at every frame as cut by the border (an edge within 13 px), and the 39 px
gate crossed the view from the centre to the right border in 7 s without the search ever running: NO_TARGET after
15 s. Scripted detections reproduce it; the first test shows the pipeline holding the box without a refusal.
"""

from __future__ import annotations

import numpy as np

from companion.config import load_config
from companion.config_perception import PerceptionConfig
from companion.core import FlightCore, FrameInput
from companion.engagement import Phase
from perception.pipeline import Pipeline
from perception.types import BoundingBox
from tests.perception.test_tracker_pipeline import ScriptedDetector

FRAME = np.zeros((480, 640, 3), np.uint8)
DT = 1 / 30
LEVEL = np.array([1.0, 0.0, 0.0, 0.0])


def big(c: float = 0.84) -> BoundingBox:
    """The logged border box: x0 = 5 px (the pipeline's own border rule, 2 px, lets it start a track)."""
    return BoundingBox(170.0, 175.0, 330.0, 345.0, c)


def gate(k: int) -> BoundingBox:
    """The logged gate: 39 px at 25 m, moving right ~1.6 px a frame from (320, 237)."""
    return BoundingBox(320.0 + 1.6 * k, 237.0, 39.0, 39.0, 0.6)


def _pipe(script: list[list[BoundingBox]], **kw) -> Pipeline:
    return Pipeline(ScriptedDetector(script), PerceptionConfig(**kw), 640, 480)  # type: ignore[arg-type]


def _on_gate(o: BoundingBox | None, k: int) -> bool:
    return o is not None and abs(o.cx - gate(k).cx) < 10 and o.w < 60


def test_without_a_refusal_the_pipeline_holds_the_border_box_and_never_shows_the_gate() -> None:
    script = [[big(), gate(k)] for k in range(90)]
    p = _pipe(script)
    outs = [p.process(FRAME, k * DT) for k in range(90)]
    assert all(o is not None and o.w > 300 for o in outs[1:])
    assert not any(_on_gate(o, k) for k, o in enumerate(outs))


def test_a_refused_candidate_is_looked_past_and_the_gate_is_tracked() -> None:
    script = [[big(), gate(k)] for k in range(90)]
    p = _pipe(script)
    outs = [p.process(FRAME, k * DT) for k in range(4)]
    assert outs[-1] is not None and outs[-1].w > 300
    p.refuse()  # the app: refused 3 frames in a row
    outs = [p.process(FRAME, k * DT) for k in range(4, 90)]
    # the gate is acquired (acquire_confidence 0.5: on its own frame) and kept past the refuse time (1 s = 30
    # frames): the big box, size-inconsistent with the gate's track, never takes it
    assert all(_on_gate(o, k) for k, o in enumerate(outs, start=4))
    assert p.stats.refusals == 1 and p.stats.switches == 0 and p.stats.acquisitions == 2


def test_a_refused_object_alone_is_taken_back_once_the_refuse_time_is_up() -> None:
    # A gate refused while the border cut it is found again when in view: the refusal is for refuse_time only.
    script = [[big()] for _ in range(90)]
    p = _pipe(script, refuse_time=1.0)
    for k in range(4):
        p.process(FRAME, k * DT)
    p.refuse()
    outs = {k: p.process(FRAME, k * DT) for k in range(4, 90)}
    t_refused = 3 * DT
    assert all(o is None for k, o in outs.items() if k * DT <= t_refused + 1.0)
    assert all(o is not None and o.w > 300 for k, o in outs.items() if k * DT > t_refused + 1.0 + DT)


def test_the_refusal_follows_the_object_as_it_moves() -> None:
    # The refused object moves 4 px a frame; the gate comes into view 10 frames after the refusal. The object's
    # continuation stays excluded (it is followed, not a fixed region), so the gate is what acquires.
    def moving(k: int) -> BoundingBox:
        return BoundingBox(170.0 + 4.0 * k, 175.0, 330.0, 345.0, 0.84)

    script = [[moving(k)] for k in range(14)] + [[moving(k), gate(k)] for k in range(14, 40)]
    p = _pipe(script)
    for k in range(4):
        p.process(FRAME, k * DT)
    p.refuse()
    outs = [p.process(FRAME, k * DT) for k in range(4, 40)]
    assert all(o is None for o in outs[:10])
    assert all(_on_gate(o, k) for k, o in enumerate(outs[10:], start=14))


def test_the_core_asks_to_look_past_a_candidate_verification_refuses_and_then_engages_the_gate() -> None:
    """End to end through the pipeline and the flight core, as every loop wires them (``CoreStep.tell_tracker``):
    verification refuses the border box as cut; at the third refusal in a row the core asks the tracker to look
    past it; the gate is then tracked, acquired and engaged."""
    cfg = load_config([], [])
    assert cfg.app.verify.enabled and not cfg.app.verify.acquire_cut
    core = FlightCore.from_config(cfg)
    script = [[big(), gate(k)] for k in range(60)]
    p = Pipeline(ScriptedDetector(script), cfg.perception, 640, 480)  # type: ignore[arg-type]
    asked, engaged_on = [], None
    for k in range(60):
        b = p.process(FRAME, k * DT)
        step = core.step(FrameInput(k * DT, b, LEVEL, 10.0))
        if step.refuse_candidate:
            asked.append(k)
            assert "tracker told to look past its candidate (refused 3 frames in a row)" in step.decision.events
        step.tell_tracker(p)
        if core.phase is Phase.ENGAGE and engaged_on is None:
            engaged_on = (k, core.engagement.used_box)
    assert asked == [2]  # the confident box acquires on its own frame: frames 0-2 refused
    assert p.stats.refusals == 1
    assert engaged_on is not None
    k, used = engaged_on
    assert used is not None and abs(used.cx - gate(k).cx) < 10 and used.w < 60
