"""The detector's box error in closed loop: rendered frames through the shipped pipeline against the exact box.

Flies in-process runs with the rendered camera (``companion eval --camera rendered``'s camera) and, for every
frame, also projects the gate exactly (the geometric camera, clipped to the image, no noise). Prints, by the
exact box's width: how often the pipeline gave no box, how often its box is off by more than 15 / 50 px (a
wrong target, not noise), the inliers' centre noise, the size error, and the frame-to-frame correlation of the
centre error. What it is for: the geometric camera of the in-process studies models a detector with 1 px
white noise (``sim.camera.pixel_noise``); this says what the real pipeline does on our own renders.
``--camera geometric`` measures the geometric camera's own box error the same way (with
``--set sim.camera.noise_model=detector``: the fit of the detector model, docs/noise.md).

    .venv/bin/python tools/measure_box_error.py --config config/vehicles/sih.yaml --runs 2 [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import perception.simcamera as simcamera  # noqa: E402
from companion.config import load_config  # noqa: E402
from companion.sim import runner  # noqa: E402
from companion.sim.camera import GeometricCamera  # noqa: E402

Row = tuple[int, float, tuple[float, ...] | None, tuple[float, ...] | None]  # run, t, pipeline box, exact box
WIDTH_BINS = ((0, 40), (40, 80), (80, 160), (160, 400), (400, 10_000))


def _paired_cameras(rows: list[Row], run: list[int]) -> Callable[..., Callable[..., Any]]:
    """geometric_camera_substitute, with every capture also projected exactly and both boxes recorded."""
    original = simcamera.geometric_camera_substitute

    def substitute(cfg: Any, **kw: Any) -> Callable[..., Any]:
        make = original(cfg, **kw)

        def build(model: Any, pixel_noise: float = 0.0, drop_prob: float = 0.0, min_box: float = 2.0,
                  rng: Any = None, clip: bool = True) -> Any:
            cam = make(model, pixel_noise, drop_prob, min_box, rng, clip)
            exact = GeometricCamera(model, 0.0, 0.0, min_box, None, True)
            capture = cam.capture

            def paired(t: float, p: Any, R: Any, c: Any, n: Any, r: float) -> Any:
                b = capture(t, p, R, c, n, r)
                e = exact.capture(t, p, R, c, n, r)
                rows.append((run[0], t, None if b is None else (b.cx, b.cy, b.w, b.h),
                             None if e is None else (e.cx, e.cy, e.w, e.h)))
                return b

            cam.capture = paired
            return cam

        return build

    return substitute


def _paired_geometric(rows: list[Row], run: list[int]) -> type[GeometricCamera]:
    """GeometricCamera with every capture also projected exactly (clipped, no noise) and both boxes recorded."""

    class Paired(GeometricCamera):
        def capture(self, t: float, p: Any, R: Any, c: Any, n: Any, r: float) -> Any:  # type: ignore[override]
            b = super().capture(t, p, R, c, n, r)
            e = GeometricCamera.box_exact(self, p, R, c, n, r, t) if self.clip else None
            rows.append((run[0], t, None if b is None else (b.cx, b.cy, b.w, b.h),
                         None if e is None else (e.cx, e.cy, e.w, e.h)))
            return b

    return Paired


def summarise(rows: list[Row]) -> dict[str, Any]:
    with_exact = [r for r in rows if r[3] is not None]
    hits = np.array([(r[3][2], r[2][0] - r[3][0], r[2][1] - r[3][1], (r[2][2] - r[3][2]) / r[3][2], r[0])
                     for r in with_exact if r[2] is not None]).reshape(-1, 5)
    out: dict[str, Any] = {
        "frames_with_gate": len(with_exact),
        "no_box_share": 1.0 - len(hits) / max(len(with_exact), 1),
        "box_without_gate": sum(1 for r in rows if r[3] is None and r[2] is not None),
        "by_width": [],
    }
    dc = np.hypot(hits[:, 1], hits[:, 2])
    widths_all = np.array([r[3][2] for r in with_exact])
    missed = np.array([r[2] is None for r in with_exact])
    for lo, hi in WIDTH_BINS:
        m = (hits[:, 0] >= lo) & (hits[:, 0] < hi)
        if m.sum() < 5:
            continue
        inl = m & (dc < 15.0)
        out["by_width"].append({
            "width_px": [lo, hi], "n": int(m.sum()),
            "no_box": float(missed[(widths_all >= lo) & (widths_all < hi)].mean()),
            "off_15px": float(np.mean(dc[m] > 15.0)), "off_50px": float(np.mean(dc[m] > 50.0)),
            "inlier_std_px": [float(hits[inl, 1].std()), float(hits[inl, 2].std())],
            "median_centre_error_px": float(np.median(dc[m])),
            "width_error_rel_median": float(np.median(hits[m, 3])),
        })
    ac = []
    for run in np.unique(hits[:, 4]):
        e = hits[(hits[:, 4] == run) & (dc < 15.0)]
        if len(e) > 20:
            x = e[:, 1] - e[:, 1].mean()
            ac.append([float(np.corrcoef(x[:-k], x[k:])[0, 1]) for k in (1, 2, 5)])
    out["inlier_cx_autocorr_lag_1_2_5"] = np.nanmean(ac, axis=0).tolist() if ac else None
    # Misses come in spells: the mean length of a run of frames without a box while the gate is in view.
    spells, cur, last_run = [], 0, None
    for r in with_exact:
        if r[0] != last_run and cur:
            spells.append(cur)
            cur = 0
        last_run = r[0]
        if r[2] is None:
            cur += 1
        elif cur:
            spells.append(cur)
            cur = 0
    if cur:
        spells.append(cur)
    out["no_box_spell_mean_frames"] = float(np.mean(spells)) if spells else 0.0
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", action="append", default=[], help="config overlay(s), e.g. config/vehicles/sih.yaml")
    ap.add_argument("--set", action="append", default=[], dest="sets", metavar="SECTION.KEY=VALUE")
    ap.add_argument("--runs", type=int, default=2, help="runs per gate motion")
    ap.add_argument("--seed", type=int, default=5000)
    ap.add_argument("--json", type=Path, help="write the summary here")
    ap.add_argument("--camera", choices=("rendered", "geometric"), default="rendered",
                    help="geometric: the in-process camera's own error (its sim.camera.noise_model)")
    a = ap.parse_args(argv)
    cfg = load_config(a.config, a.sets)
    rows: list[Row] = []
    run = [0]
    if a.camera == "rendered":
        simcamera.geometric_camera_substitute = _paired_cameras(rows, run)
    else:
        runner.GeometricCamera = _paired_geometric(rows, run)  # type: ignore[misc]
    for motion in runner.MOTIONS:
        for _ in range(a.runs):
            run[0] += 1
            r = runner.run_once(cfg, runner.RunSpec(motion, seed=a.seed + run[0], camera=a.camera))
            print(f"run {run[0]:3d} {motion:12s} success 1 m: {r.outcome.success(1.0)!s:5s} "
                  f"{r.outcome.failure(1.0) or ''}", flush=True)
    s = summarise(rows)
    print(f"frames with the gate in view {s['frames_with_gate']}, no box {s['no_box_share']:.2f}, "
          f"boxes with no gate in view {s['box_without_gate']}")
    for b in s["by_width"]:
        lo, hi = b["width_px"]
        print(f"width {lo:4d}-{hi:5d} px: n {b['n']:5d}  no box {b['no_box']:.2f}  "
              f"off >15 px {b['off_15px']:.2f}  >50 px {b['off_50px']:.2f}  "
              f"inlier std {b['inlier_std_px'][0]:.1f}/{b['inlier_std_px'][1]:.1f} px  "
              f"median centre error {b['median_centre_error_px']:.1f} px  "
              f"width error {b['width_error_rel_median']:+.2f}")
    print(f"inlier centre-error autocorrelation at lag 1/2/5 frames: {s['inlier_cx_autocorr_lag_1_2_5']}")
    print(f"mean spell of frames without a box (gate in view): {s['no_box_spell_mean_frames']:.1f}")
    if a.json:
        a.json.write_text(json.dumps(s, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
