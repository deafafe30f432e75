"""A synthetic-camera flight's frames drawn again from its log, and perceived again (``companion log rerun
--rerender``).

Why: a flight log keeps the box perception gave on each frame, not the frame (640x480 at 30 Hz is 27 MB/s). To ask
of a PX4 SITL flight "would another detector threshold, tracker setting or model have kept the ring, and what would
the core have decided then?", its frames are drawn again: by the synthetic camera's own renderer
(companion/app/synthcam.py ``SyntheticRenderer``), from the pose and the gate the log says the camera drew with
(companion/logclutter.py ``frames_of``: the truth source's position and attitude, the gate row the capture wrote).
Each frame then goes through a fresh pipeline the way the app hands it one (``PipelinePerception`` with the attitude
at capture), and the engagement's requests (drop the track, look past a refused candidate) go back to it.

Not the flown pixels: the position is interpolated between the log's truth samples, the attitude slerped, and the
render's noise is drawn anew (the flight's stream was shared with the scene's set-up). On the test flight
(tests/app/test_logrender.py) the re-perceived box lies within a few pixels of the logged one on most frames; the
test says how many.

What it reports, for the flight as logged and as perceived again: the boxes on the gate, off it and with the gate out
of view, and companion/logclutter.py's engagement tally (engagements begun on a wrong box, passes claimed on one)
of the core's decisions on those boxes.

Open loop, as every rerun: the vehicle flew what the flight's own boxes commanded. So the first decision that differs
is the answer; what follows it answers "on these frames", not "in that flight".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from companion.app.camera import Frame, PipelinePerception
from companion.app.synthcam import SyntheticRenderer
from companion.engagetally import on_gate
from companion.flightlog import Flight
from companion.frames import R_enu_flu_from_ned_frd, R_from_quat_wxyz, ned_to_enu
from companion.logclutter import MARGIN_PX, FrameRow, apply_lock, config_of, frames_of, grown, tally_rows
from perception.types import BoundingBox

MATCH_S = 1e-6  # s: a core input and a logged frame are the same frame (times written with 9 digits)


@dataclass
class PerceivedFrame:
    row: FrameRow  # the log's frame: its time, the box the flight's perception gave, the truth, its phase and events
    again: BoundingBox | None  # the box perception gives on the frame drawn again
    # The rerun's decisions on this frame (None: the core was not stepped on it): phase, events, the box it used.
    decided: tuple[str, tuple[str, ...], BoundingBox | None] | None = None

    def box(self, which: str) -> BoundingBox | None:
        """``logged`` (the flight's) or ``again``."""
        return self.row.box if which == "logged" else self.again


@dataclass
class Rerendered:
    """Perception again, frame by frame, on a rendered synthetic-camera flight's frames drawn again from its log."""

    rows: list[FrameRow]
    renderer: SyntheticRenderer
    perception: PipelinePerception
    t0: float  # the log's clock origin on the monotonic clock (meta.json t0_monotonic)
    flown: Any  # the flight's own config (how its frames were drawn)
    frames: list[PerceivedFrame] = field(default_factory=list)
    _k: int = 0

    @classmethod
    def of(cls, flight: Flight, cfg: Any) -> Rerendered:
        """``flight`` drawn as it was flown (its own config.json: camera mount, scene seed), perceived with ``cfg``."""
        from perception.pipeline import Pipeline

        flown = config_of(flight)
        if flown.app.camera != "synthetic" or flown.app.synthetic.render != "image":
            raise ValueError(f"{flight.folder}: not a rendered synthetic-camera flight (app.camera "
                             f"{flown.app.camera!r}, app.synthetic.render {flown.app.synthetic.render!r}): its "
                             "frames cannot be drawn again")
        rows = frames_of(flight, flown)
        return cls(rows, SyntheticRenderer(flown, np.random.default_rng(flown.sim.seed)),
                   PipelinePerception(Pipeline.from_config(cfg)), float(flight.meta["t0_monotonic"]), flown)

    def box(self, tf: float, q_wxyz: np.ndarray) -> BoundingBox | None:
        """Perception's box on the frame captured at ``tf`` (flight-log clock) with attitude ``q_wxyz`` (NED/FRD, what
        the core is given); every earlier frame of the log is perceived first, as the app perceived it (also those
        the core was not stepped on, e.g. during the take-off)."""
        out = None
        while self._k < len(self.rows) and self.rows[self._k].t <= tf + MATCH_S:
            r = self.rows[self._k]
            self._k += 1
            same = abs(r.t - tf) <= MATCH_S
            b = self._perceive(r, q_wxyz if same else r.q)
            if same:
                out = b
        return out

    def _perceive(self, r: FrameRow, q_wxyz: np.ndarray) -> BoundingBox | None:
        if r.pose is None:
            self.frames.append(PerceivedFrame(r, None))
            return None
        p_ned, q_drawn = r.pose
        R_enu_flu = R_enu_flu_from_ned_frd(R_from_quat_wxyz(q_drawn))
        gate = None if r.drawn is None else (ned_to_enu(r.drawn[0]), ned_to_enu(r.drawn[1]), r.drawn[2])
        image, _ = self.renderer.draw(r.t, ned_to_enu(p_ned), R_enu_flu, gate)
        b = self.perception.process(Frame(len(self.frames), self.t0 + r.t, image), q_wxyz)
        self.frames.append(PerceivedFrame(r, b))
        return b

    def decided(self, tf: float, phase: str, events: tuple[str, ...], used: BoundingBox | None) -> None:
        """What the rerun's core decided on the frame captured at ``tf`` (after ``box`` gave it that frame's box)."""
        f = self.frames[-1] if self.frames else None
        if f is not None and abs(f.row.t - tf) <= MATCH_S:
            f.decided = (phase, events, used)

    def tallies(self, margin: float = MARGIN_PX) -> tuple[dict[str, Any], dict[str, Any]]:
        """companion/logclutter.py's engagement tally (begun on a wrong box, passes claimed on one, ...) of the flight
        as logged and of the rerun on the boxes perceived again, over the same frames."""
        logged = [f.row for f in self.frames]
        apply_lock(logged, self.flown)  # the flight's own refusals (los.csv, or its lock re-run for older logs)
        again = []
        for f in self.frames:
            phase, events, used = f.decided if f.decided is not None else ("", (), None)
            again.append(replace(f.row, box=f.again, phase=phase, events=events, used=used))
        return tally_rows(logged, margin), tally_rows(again, margin)

    def summary(self, margin: float = MARGIN_PX) -> dict[str, Any]:
        """How often each box (the logged one, the one perceived again) lies on the gate (its centre within the true
        box grown by ``margin`` px, companion/logclutter.py's rule) or off it, on the frames with the gate in view;
        how many boxes the frames without it have; the on-gate boxes' centre distance to the true box's. Frames
        within logclutter's NEAR_RADII of the gate are judged neither way (the log's pose cannot place a box there)."""
        judged = [f for f in self.frames if f.row.judged]
        seen = [f for f in judged if f.row.truth is not None]
        out: dict[str, Any] = {"frames": len(self.frames), "judged": len(judged), "gate_in_view": len(seen)}
        for key in ("logged", "again"):
            on, dist = 0, []
            for f in seen:
                b, g = f.box(key), f.row.truth
                if b is not None and g is not None and on_gate(b, grown(g, margin)):
                    on += 1
                    dist.append(math.hypot(b.cx - g.cx, b.cy - g.cy))
            boxes = sum(f.box(key) is not None for f in seen)
            out[key] = {"boxes": boxes, "on_gate": on, "off_gate": boxes - on,
                        "boxes_gate_out_of_view": sum(f.box(key) is not None for f in judged
                                                      if f.row.truth is None),
                        "centre_px_p50": float(np.percentile(dist, 50)) if dist else None,
                        "centre_px_p95": float(np.percentile(dist, 95)) if dist else None}
        keep = ("engagements", "begun_on_wrong", "engaged_frames", "engaged_frames_wrong", "passes_claimed",
                "passes_claimed_wrong")
        for key, t in zip(("logged", "again"), self.tallies(margin), strict=True):
            out[key]["engagements"] = {k: t[k] for k in keep}
        return out


def report_lines(s: dict[str, Any]) -> list[str]:
    """The perception part of ``log rerun --rerender``'s report."""

    def one(name: str, d: dict[str, Any]) -> str:
        px = ("" if d["centre_px_p50"] is None else
              f", centre to the true box p50 {d['centre_px_p50']:.1f} px, p95 {d['centre_px_p95']:.1f} px")
        return (f"    {name}: on the gate {d['on_gate']}, off it {d['off_gate']}, a box with the gate out of view "
                f"{d['boxes_gate_out_of_view']}{px}")

    def eng(name: str, e: dict[str, Any]) -> str:
        return (f"    {name}: {e['engagements']} engagement(s), {e['begun_on_wrong']} begun on a wrong box, "
                f"engaged frames on one {e['engaged_frames_wrong']}/{e['engaged_frames']}, passes claimed on one "
                f"{e['passes_claimed_wrong']}/{e['passes_claimed']}")

    return [f"  perception on the {s['frames']} frames drawn again ({s['judged']} judged, {s['gate_in_view']} of them "
            "with the gate in view):",
            one("logged", s["logged"]), one("again ", s["again"]),
            "  the engagements against the truth (companion log clutter's tally):",
            eng("logged", s["logged"]["engagements"]), eng("again ", s["again"]["engagements"])]
