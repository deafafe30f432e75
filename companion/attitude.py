"""Attitude over time: samples (t, q_wxyz body FRD -> NED) interpolated by slerp.

Read from a flight log or a recording (companion/replay.py, companion/app/record.py) to give each
replayed frame the attitude at its capture time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class AttitudeTrack:
    """Attitude samples (t, q_wxyz NED/FRD), interpolated by slerp; held constant outside the samples."""

    t: np.ndarray
    q_wxyz: np.ndarray
    frame_times: dict[int, float] | None = None

    def at(self, t: float) -> np.ndarray:
        from scipy.spatial.transform import Rotation, Slerp

        if len(self.t) == 1:
            return self.q_wxyz[0].copy()
        tc = float(np.clip(t, self.t[0], self.t[-1]))
        rot = Rotation.from_quat(self.q_wxyz[:, [1, 2, 3, 0]])
        x, y, z, w = Slerp(self.t, rot)([tc]).as_quat()[0]
        return np.array([w, x, y, z])
