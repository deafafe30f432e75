"""Per-run setpoint metrics, shared by every study (in-process, simulated PX4, PX4 SITL) and log tools.

Pure numpy: a time series of commanded attitudes in, numbers out.

- ``tilt_deg``: angle of the commanded thrust axis from vertical, ``arccos(cos(roll) cos(pitch))`` for
  PX4's ZYX Euler angles (yaw does not tilt the thrust axis).
- ``oscillation``: how much the roll setpoint swings: the RMS of its rate (deg/s) and the amplitude and
  frequency of its dominant spectral line (deg, Hz), after the linear trend is removed. A steady bank
  scores zero; a limit cycle scores its amplitude.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MIN_SAMPLES = 8  # fewer setpoints than this: no oscillation figure (NaN), not a misleading zero


@dataclass(frozen=True, slots=True)
class Oscillation:
    rms_rate_dps: float  # RMS of d(roll setpoint)/dt, deg/s
    amplitude_deg: float  # amplitude of the dominant spectral line (half the peak-to-peak of a sine)
    frequency_hz: float  # its frequency

    def as_dict(self, prefix: str = "roll_osc_") -> dict[str, float]:
        return {f"{prefix}rms_rate_dps": self.rms_rate_dps, f"{prefix}amp_deg": self.amplitude_deg,
                f"{prefix}freq_hz": self.frequency_hz}


NO_OSCILLATION = Oscillation(math.nan, math.nan, math.nan)


def tilt_deg(roll_deg: np.ndarray | float, pitch_deg: np.ndarray | float) -> np.ndarray:
    """Angle between the thrust axis and vertical for ZYX Euler roll/pitch (degrees in, degrees out)."""
    c = np.cos(np.radians(roll_deg)) * np.cos(np.radians(pitch_deg))
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def max_tilt_deg(roll_deg: np.ndarray, pitch_deg: np.ndarray) -> float:
    r, p = np.asarray(roll_deg, dtype=float), np.asarray(pitch_deg, dtype=float)
    ok = np.isfinite(r) & np.isfinite(p)
    return float(np.max(tilt_deg(r[ok], p[ok]))) if ok.any() else math.nan


def oscillation(t: np.ndarray, roll_deg: np.ndarray, f_min_hz: float = 0.3) -> Oscillation:
    """RMS roll-setpoint rate and the dominant line of the roll setpoint's spectrum above ``f_min_hz``.

    Samples need not be uniform (setpoints follow camera frames): the series is resampled on a uniform
    grid at its median rate before the FFT. A Hann window keeps a trend or an odd window length from
    leaking into the peak; its coherent gain is divided out, so a pure sine of amplitude A reads A.
    """
    t = np.asarray(t, dtype=float)
    r = np.asarray(roll_deg, dtype=float)
    ok = np.isfinite(t) & np.isfinite(r)
    t, r = t[ok], r[ok]
    if t.size < MIN_SAMPLES:
        return NO_OSCILLATION
    order = np.argsort(t, kind="stable")
    t, r = t[order], r[order]
    keep = np.concatenate(([True], np.diff(t) > 0))
    t, r = t[keep], r[keep]
    if t.size < MIN_SAMPLES:
        return NO_OSCILLATION
    dt = np.diff(t)
    rms_rate = float(np.sqrt(np.mean((np.diff(r) / dt) ** 2)))
    step = float(np.median(dt))
    n = math.floor((t[-1] - t[0]) / step) + 1
    if n < MIN_SAMPLES:
        return Oscillation(rms_rate, math.nan, math.nan)
    tu = t[0] + step * np.arange(n)
    ru = np.interp(tu, t, r)
    ru = ru - np.polyval(np.polyfit(tu - tu[0], ru, 1), tu - tu[0])
    w = np.hanning(n)
    spec = np.abs(np.fft.rfft(ru * w)) * 2.0 / w.sum()
    freq = np.fft.rfftfreq(n, step)
    band = freq >= f_min_hz
    if not band.any():
        return Oscillation(rms_rate, math.nan, math.nan)
    k = int(np.argmax(np.where(band, spec, -1.0)))
    return Oscillation(rms_rate, float(spec[k]), float(freq[k]))
