"""Plot of one flight log (matplotlib, Agg): states, attitude, thrust, LOS rate and box, altitude, latency."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from companion.flightlog import check_output, read_flight, write_output

_STATE_COLOURS = {
    "ACQUIRE": "#dddddd", "ENGAGE": "#ffd8a8", "PASS": "#ffa8a8", "RECOVER": "#a8d8ff",
    "HANDBACK": "#d0ffd0", "LAND": "#c8f0c8", "TAKEOFF": "#eeeeff",
}


def _spans(flight) -> list[tuple[float, float, str]]:
    st = flight.states
    out = []
    for i, r in enumerate(st):
        t1 = float(st[i + 1]["t"]) if i + 1 < len(st) else float("nan")
        out.append((float(r["t"]), t1, str(r["to_state"])))
    return out



def box_sizes(det: Any, camera: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The valid boxes' larger sides on the image's scale: (t, size) of those within the image's larger side,
    the times of those beyond it, and that side (px). A projected ring at the pass is thousands of px (a
    synthetic camera's box is not cut to the image); plotted as is, that one point flattens every other box."""
    ok = det["valid"] > 0
    t, size = det["t"][ok], np.maximum(det["w"][ok], det["h"][ok])
    top = float(max(camera.get("width") or 0, camera.get("height") or 0))
    if not top > 0.0:
        top = float(np.nanmax(size, initial=1.0))
    over = size > top
    return t[~over], size[~over], t[over], top

def plot_flight(folder: str | Path, output: str | Path | None = None) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder = Path(folder)
    f = read_flight(folder)
    # Never over a raw file of the flight (a path into the folder, a symlink or a hard link to one).
    out = check_output(Path(output) if output is not None else folder / "plot.png", folder, "plot.png")
    fig, ax = plt.subplots(5, 1, figsize=(11, 13), sharex=True)
    tmax = max((float(np.nanmax(t["t"])) for t in f.tables.values() if len(t)), default=1.0)
    for a in ax:
        for t0, t1, name in _spans(f):
            c = _STATE_COLOURS.get(name)
            if c:
                a.axvspan(t0, t1 if np.isfinite(t1) else tmax, color=c, alpha=0.5, lw=0)
        a.grid(alpha=0.3)
    for t0, _, name in _spans(f):
        ax[0].annotate(name, (t0, 1.0), xycoords=("data", "axes fraction"), rotation=90, fontsize=7,
                       va="top", ha="right")
    tel, sp, los, det = (f.tables.get(k) for k in ("telemetry", "setpoints", "los", "detections"))
    if tel is not None and len(tel):
        ax[0].plot(tel["t"], tel["roll_deg"], "C0-", lw=0.8, label="roll (PX4)")
        ax[0].plot(tel["t"], tel["pitch_deg"], "C1-", lw=0.8, label="pitch (PX4)")
    if sp is not None and len(sp):
        ax[0].plot(sp["t"], sp["roll_deg"], "C0--", lw=0.8, label="roll setpoint")
        ax[0].plot(sp["t"], sp["pitch_deg"], "C1--", lw=0.8, label="pitch setpoint")
        ax[1].plot(sp["t"], sp["thrust"], "C3-", lw=0.9, label="thrust setpoint")
    ax[0].set_ylabel("deg")
    ax[1].set_ylabel("thrust 0..1")
    if los is not None and len(los):
        ax[2].plot(los["t"], los["lambda_dot"], "C2-", lw=0.9, label="LOS rate (rad/s)")

    if det is not None and len(det):
        a2 = ax[2].twinx()
        t_in, size_in, t_over, top = box_sizes(det, f.config.get("camera", {}))
        a2.plot(t_in, size_in, "k.", ms=2, label="box size (px)")
        if len(t_over):
            a2.plot(t_over, np.full(len(t_over), top), "k^", ms=3, label="box beyond the image")
        a2.set_ylim(0.0, 1.05 * top)
        a2.set_ylabel("box px")

    ax[2].set_ylabel("rad/s")
    truth = f.tables.get("truth")
    if tel is not None and len(tel):
        b = tel["baro_alt_m"]
        b0 = b[np.isfinite(b)][0] if np.isfinite(b).any() else 0.0
        ax[3].plot(tel["t"], b - b0, "C4-", lw=0.8, label="baro altitude (rel. start)")
    if truth is not None and len(truth):
        ax[3].plot(truth["t"], -truth["d"], "k--", lw=0.8, label="true altitude (log only)")
        speed = np.sqrt(truth["vn"] ** 2 + truth["ve"] ** 2 + truth["vd"] ** 2)
        ax[3].plot(truth["t"], speed, "C5-", lw=0.8, label="true speed m/s (log only)")
    floor = f.config.get("safety", {}).get("altitude_floor")
    if floor is not None:
        ax[3].axhline(floor, color="r", lw=0.6, ls=":", label="altitude floor")
    ax[3].set_ylabel("m, m/s")

    if sp is not None and len(sp):
        ax[4].plot(sp["t"], sp["latency_ms"], "C6.", ms=2, label="frame -> setpoint latency")

    ax[4].set_ylabel("ms")
    for a in ax:
        if a.get_legend_handles_labels()[0]:
            a.legend(loc="upper left", fontsize=7, ncol=4)
    ax[4].set_xlabel("flight time, s")
    s = f.summary
    fig.suptitle(f"{folder.name}: {s.get('outcome', '?')} ({s.get('reason', '?')}) {s.get('detail', '')}"[:140],
                 fontsize=9)
    fig.tight_layout()
    import io

    png = io.BytesIO()
    fig.savefig(png, format="png", dpi=90)
    write_output(out, png.getvalue())  # a write error is an OSError (savefig to /dev/full said nothing)
    plt.close(fig)
    return out
