"""What our own commands did since a frame was captured: the velocity and displacement they added.

A late frame shows the gate where it was; since then the vehicle has flown on under the accelerations we
commanded. The delay prediction (companion/controller.py ``_predict_state``) takes that motion off the predicted
relative state. Model (no position or velocity measured): each commanded acceleration (world ENU, normal to the
LOS) is held until the next one and reached with a first-order lag ``lag``; drag takes the added velocity back at
``drag_rate`` (1/s): ``dv' = a_eff - k dv``, integrated exactly for the piecewise first-order ``a_eff``. The
callers shift the times by the airframe's response time (a command acts that much after it is given).
"""

from __future__ import annotations

import bisect
import math

import numpy as np

HISTORY_S = 2.0  # older commands never fall in a frame's window


class OwnMotion:
    """History of commanded accelerations; ``dv`` / ``motion`` over a window of command times."""

    def __init__(self, lag: float, drag_rate: float = 0.0) -> None:
        self.lag = float(lag)
        self.drag_rate = float(drag_rate)
        self.reset()

    def reset(self) -> None:
        # (t issued, commanded accel, modelled accel), vectors as float triples: this runs every frame and the
        # element-wise math below is the same in floats as in arrays, bit for bit.
        self._hist: list[tuple[float, tuple[float, float, float], tuple[float, float, float]]] = []
        self._t: list[float] = []  # the times of _hist, for bisection

    def __bool__(self) -> bool:
        return bool(self._hist)

    def note(self, t: float, a: np.ndarray | tuple[float, float, float]) -> None:
        """The acceleration commanded at ``t``."""
        prev = self._hist[-1] if self._hist else None
        tau = self.lag
        if prev is None:
            eff = (0.0, 0.0, 0.0)
        else:
            t0, a0, e0 = prev
            if tau > 0.0:
                # a0 + (e0 - a0) exp(-(t - t0) / tau)
                c = math.exp(-(t - t0) / tau)
                (ax, ay, az), (ex, ey, ez) = a0, e0
                eff = (ax + (ex - ax) * c, ay + (ey - ay) * c, az + (ez - az) * c)
            else:
                eff = a0
        ax, ay, az = a.tolist() if isinstance(a, np.ndarray) else (float(a[0]), float(a[1]), float(a[2]))
        hist, times = self._hist, self._t
        hist.append((t, (ax, ay, az), eff))
        times.append(t)
        horizon = t - HISTORY_S
        while len(times) > 2 and times[1] < horizon:  # times[i] is hist[i][0]
            del hist[0], times[0]

    def dv(self, t0: float, t1: float) -> np.ndarray:
        """The velocity the (modelled) acceleration added between t0 and t1, without drag."""
        vx = vy = vz = 0.0
        tau = self.lag
        hist = self._hist
        for i, (ti, (ax, ay, az), (ex, ey, ez)) in enumerate(hist):
            tn = hist[i + 1][0] if i + 1 < len(hist) else t1
            s0, s1 = (ti if ti > t0 else t0), (tn if tn < t1 else t1)  # max(t0, ti), min(t1, tn): see motion_xyz
            if s1 <= s0:
                continue
            h = s1 - s0
            if tau > 0.0:
                # ai h + (ei - ai) tau e, in the order of the array expression it replaced
                e = math.exp(-(s0 - ti) / tau) - math.exp(-(s1 - ti) / tau)
                vx += ax * h + (ex - ax) * tau * e
                vy += ay * h + (ey - ay) * tau * e
                vz += az * h + (ez - az) * tau * e
            else:
                vx += ax * h
                vy += ay * h
                vz += az * h
        return np.array([vx, vy, vz])

    def motion(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
        """The velocity and displacement added between t0 and t1, with drag taking the velocity back."""
        v, p = self.motion_xyz(t0, t1)
        return np.array(v), np.array(p)

    def motion_xyz(self, t0: float, t1: float) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """:meth:`motion` as float triples (the controller's per-frame prediction: no arrays)."""
        k, tau = self.drag_rate, self.lag
        vx = vy = vz = px = py = pz = 0.0
        hist = self._hist
        first = bisect.bisect_right(self._t, t0) - 1  # the command in effect at t0
        first = first if first > 0 else 0
        # max(t0, ti) and min(t1, tn) below as ``b if b > a else a``: the builtins' value (ties and NaN keep the
        # first argument) without their cost (~0.1 us a call, every frame).
        for i in range(first, len(hist)):
            ti, ai, ei = hist[i]
            if ti >= t1:
                break
            tn = hist[i + 1][0] if i + 1 < len(hist) else t1
            s0, s1 = (ti if ti > t0 else t0), (tn if tn < t1 else t1)
            if s1 <= s0:
                continue
            dt = s1 - s0
            e_k = math.exp(-k * dt)
            f1 = -math.expm1(-k * dt) / k if k * dt > 1e-12 else dt  # int_0^dt e^{-k u} du
            f2 = (dt - f1) / k if k * dt > 1e-4 else dt * dt * (0.5 - k * dt / 6.0)  # int_0^dt f1(u) du
            g = h = 0.0  # the lag's transient: int of e^{-u/tau} through the drag, for velocity and displacement
            if tau > 0.0:
                e_t = math.exp(-dt / tau)
                m = k - 1.0 / tau
                if abs(m) > 1e-6:
                    g = (e_t - e_k) / m
                    h = (tau * (1.0 - e_t) - f1) / m
                else:
                    g = dt * e_k
                    h = (1.0 - e_k * (1.0 + k * dt)) / (k * k)
                c = math.exp(-(s0 - ti) / tau)
            else:
                c = 0.0
            (ax, ay, az), (ex, ey, ez) = ai, ei
            cx, cy, cz = (ex - ax) * c, (ey - ay) * c, (ez - az) * c
            px += vx * f1 + ax * f2 + cx * h
            py += vy * f1 + ay * f2 + cy * h
            pz += vz * f1 + az * f2 + cz * h
            vx, vy, vz = vx * e_k + ax * f1 + cx * g, vy * e_k + ay * f1 + cy * g, vz * e_k + az * f1 + cz * g
        return (vx, vy, vz), (px, py, pz)
