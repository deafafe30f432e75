"""Render a mount-calibration recording through a camera that sits off its configured mount, for studies.

    PYTHONPATH=. python tools/render_mount_recording.py REC --set sim.camera.mount_error.pitch=5 [--views 20]
    companion calibrate REC --mount --cols 10 --rows 7 --square 0.04 -o cam.yaml

The board, hand attitudes and renderer are companion/sim/boardrec.py's (what tests/test_mountcal.py checks
against known mounts); the true mount is ``camera.mount`` + ``sim.camera.mount_error`` of the config given. A
study then flies ``--config cam.yaml`` with ``sim.camera.mount_error`` = the true mount minus the calibration.
"""

from __future__ import annotations

import argparse

import numpy as np

from companion.config import load_config
from companion.sim.boardrec import hand_attitudes, render_board_recording
from companion.sim.camera import true_camera_config


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder")
    ap.add_argument("--config", action="append", default=[])
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--views", type=int, default=20)
    ap.add_argument("--seed", type=int, default=3)
    a = ap.parse_args()
    cfg = load_config(a.config, a.overrides)
    R_true = true_camera_config(cfg).R_body_cam
    render_board_recording(a.folder, cfg.camera, R_true, hand_attitudes(a.views, np.random.default_rng(a.seed)),
                           rng=np.random.default_rng(a.seed + 100))
    print(f"wrote {a.views} views to {a.folder} (camera.mount {cfg.camera.mount}, error {cfg.sim.camera.mount_error})")


if __name__ == "__main__":
    main()
