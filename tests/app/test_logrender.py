"""``companion log rerun --rerender``: a rendered synthetic-camera flight's frames drawn again from its log and
perceived again, the core stepped on those boxes.

On a real flight (the app, real mavsdk, the simulated PX4 over UDP, the synthetic camera's rendered frames through
the shipped detector, the camera mounted 5 deg off its configured pitch):

* every frame is drawn from the pose and gate the log says the camera drew with: the renderer's own true gate box is
  companion/logclutter.py's, to a micro-pixel, on every frame with the gate in view;
* with the flown config the boxes perceived again match the flight's: on the gate on as many frames within a few,
  none off it, and the core engages on the same frame within a few frames and passes the gate; the clutter tally
  (companion log clutter's) of both: one engagement begun on the gate, no pass claimed on a wrong box;
* with a detector that finds nothing (``perception.confidence=0.99``) the core never engages: it is given the boxes
  perceived again, not the logged ones;
* a flight whose frames were not rendered: one line naming the flight, exit 2.
"""

from __future__ import annotations

import argparse
import json
import shutil
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from flighthelpers import fly_rendered

from companion.config import Config, load_config
from companion.configbase import deep_merge, parse_override
from companion.flightlog import read_flight
from companion.frames import R_enu_flu_from_ned_frd, R_from_quat_wxyz, ned_to_enu
from companion.logrender import Rerendered
from companion.logrerun import rerun

pytestmark = pytest.mark.timeout(300)


def _detector_missing() -> str | None:
    from companion.app.assemble import detector_available

    return detector_available(load_config())


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    if _detector_missing() is not None:
        pytest.skip("the shipped gate detector is not available")

    def good(folder: Path, summary: dict) -> bool:
        f = read_flight(folder)
        return "PASS" in [s["to_state"] for s in f.states] and int((f["setpoints"]["state"] == "ENGAGE").sum()) >= 30

    yield fly_rendered(tmp_path_factory.mktemp("renderlog"), 11, 5.0, good)


def _cfg(folder: Path, *overrides: str) -> Config:
    data = dict(read_flight(folder).config)
    for ov in overrides:
        data = deep_merge(data, parse_override(ov))
    return Config.model_validate(data)


def test_frames_are_drawn_where_the_log_says_the_gate_was(flight: Path) -> None:
    f = read_flight(flight)
    again = Rerendered.of(f, _cfg(flight))
    drawn = 0
    for r in again.rows:
        assert r.pose is not None
        p, q = r.pose
        gate = None if r.drawn is None else (ned_to_enu(r.drawn[0]), ned_to_enu(r.drawn[1]), r.drawn[2])
        image, truth = again.renderer.draw(r.t, ned_to_enu(p), R_enu_flu_from_ned_frd(R_from_quat_wxyz(q)), gate)
        assert image.shape == (480, 640, 3)
        assert (truth is None) == (r.truth is None), r.t
        if truth is not None and r.truth is not None:
            assert np.allclose(truth.xyxy, r.truth.xyxy, atol=1e-6), (r.t, truth, r.truth)
            drawn += 1
    assert drawn >= 30


def _engaged_at(changes: list[tuple[float, str, str]] | list[tuple[float, str]]) -> float:
    return next(c[0] for c in changes if c[1] == "ENGAGE")


def test_the_flown_config_perceives_what_the_flight_did(flight: Path) -> None:
    res = rerun(flight, _cfg(flight), rerender=True)
    s = res.perception
    assert s is not None and s["gate_in_view"] >= 30
    logged, again = s["logged"], s["again"]
    assert logged["on_gate"] >= 30 and logged["off_gate"] == 0
    # Not the flown pixels (the render's noise is drawn anew, the pose interpolated): a few frames either way.
    assert abs(again["on_gate"] - logged["on_gate"]) <= max(3, 0.1 * logged["on_gate"]), s
    assert again["off_gate"] <= 1, s
    assert again["centre_px_p50"] < 2.0 * logged["centre_px_p50"] + 2.0, s
    # The core on those boxes: engaged within a few frames of the flight, and passed the gate.
    frame = 1.0 / _cfg(flight).camera.rate
    assert abs(_engaged_at(res.changes) - _engaged_at(res.logged_changes)) <= 3.5 * frame, (res.changes,
                                                                                           res.logged_changes)
    assert "PASS" in [c[1] for c in res.changes], res.changes
    # companion log clutter's tally of both: one engagement each, begun on the gate, no pass claimed on a wrong box.
    el, ea = logged["engagements"], again["engagements"]
    assert el["engagements"] == ea["engagements"] == 1 and el["begun_on_wrong"] == ea["begun_on_wrong"] == 0, s
    assert ea["engaged_frames"] >= 20 and ea["engaged_frames_wrong"] <= 1 and ea["passes_claimed_wrong"] == 0, s


def test_a_detector_that_finds_nothing_never_engages(flight: Path) -> None:
    res = rerun(flight, _cfg(flight, "perception.confidence=0.99"), rerender=True)
    assert res.perception is not None and res.perception["again"]["on_gate"] == 0
    assert res.perception["again"]["off_gate"] == 0
    assert [c[1] for c in res.changes] == ["ACQUIRE"], res.changes
    assert res.perception["again"]["engagements"]["engagements"] == 0
    assert res.perception["logged"]["engagements"]["engagements"] == 1
    assert "ENGAGE" in [c[1] for c in res.logged_changes]


def _cli(*argv: str) -> int:
    from companion.logtools import register_log_actions

    ap = argparse.ArgumentParser()
    register_log_actions(ap.add_subparsers())
    args = ap.parse_args(list(argv))
    return int(args.func(args) or 0)


def test_cli_prints_both_perceptions(flight: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _cli("rerun", str(flight), "--rerender", "--set", "perception.confidence=0.3") == 0
    out = capsys.readouterr().out
    assert "perception on the " in out and "    logged: on the gate " in out and "    again : on the gate " in out
    assert "    again : 1 engagement(s), 0 begun on a wrong box" in out or "    again : 0 engagement(s)" in out, out


def test_a_flight_without_rendered_frames_is_one_line_and_exit_2(flight: Path, tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    geo = tmp_path / "geometric"
    shutil.copytree(flight, geo)
    cfg = json.loads((geo / "config.json").read_text())
    cfg["app"]["synthetic"]["render"] = "geometric"
    (geo / "config.json").write_text(json.dumps(cfg))
    assert _cli("rerun", str(geo), "--rerender") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(geo) in err[0] and "not a rendered synthetic-camera flight" in err[0], err
