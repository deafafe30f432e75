"""After take-off, in PX4's hover before the engagement: the hover thrust the vehicle really needs (thin).

The decision is companion/vehiclematch.py's; here only the reads (the link's ATTITUDE_TARGET samples, the core's
hover thrust), the one line on the console and in the events, the record for summary.json (``hover``), and,
when the decision says so, the core switched to PX4's measured value before it commands anything.
"""

from __future__ import annotations

import math
from typing import Any

from companion.hover import HoverThrustEstimator, use_hover_thrust
from companion.vehiclematch import MIN_SAMPLES, WINDOW, HoverCheck, hover_after_takeoff, measured_hover


class HoverAfterTakeoff:
    """``frame(core, acquiring, now)`` once per frame until it has reported: while the engagement acquires (PX4
    holds) it reports as soon as PX4's hover is measured (from the end of the take-off climb); the first frame after
    ACQUIRE reports with what there was before it."""

    def __init__(self, app: Any, mpc_thr_hover: float | None) -> None:
        self.app = app
        self.mpc_thr_hover = mpc_thr_hover
        self.until = -math.inf  # the last frame in ACQUIRE: PX4 flew the vehicle until then (clock: monotonic)
        self.done = False
        self.result: HoverCheck | None = None

    def frame(self, core: Any, acquiring: bool, now: float) -> None:
        if self.done:
            return
        if acquiring:
            self.until = now
        # Take-off and hold, up to the last frame before our first setpoint (the mode PX4 reports lags 0.2-1 s).
        # In ACQUIRE: a full window (the newest second of PX4's hover); after it, whatever there was.
        measured, n = measured_hover(list(getattr(self.app.link, "thrust_targets", ())), until=self.until,
                                     need=WINDOW if acquiring else MIN_SAMPLES,
                                     ground=getattr(self.app, "_baro0", None))  # the app's ground (raw baro)
        if acquiring and measured is None:
            return  # not yet: PX4 still holds, more samples come
        self.done = True
        self._report(core, measured, n, adopt=acquiring)

    def _report(self, core: Any, measured: float | None, n: int, adopt: bool) -> None:
        app, cfg = self.app, self.app.cfg
        in_use = float(core.hover_thrust)
        est = core.hover_estimator
        app_est = float(est.hover_thrust) if est is not None else in_use
        source = ("PX4 MPC_THR_HOVER" if getattr(app.link, "hover_thrust_source", "config") == "autopilot"
                  else "config airframe.hover_thrust")
        r = hover_after_takeoff(measured, n, app_est, cfg.airframe.hover_thrust, self.mpc_thr_hover, in_use, source,
                                start_from_px4=bool(cfg.hover.start_from_px4), estimate_on=bool(cfg.hover.estimate),
                                too_late=not adopt)
        self.result = r
        if r.flies != in_use and hasattr(core.controller, "p"):
            # Before the app's first setpoint: the controller, the pass/recovery and the estimate all start here.
            use_hover_thrust(core.controller, r.flies, cfg.airframe.thrust_to_weight, core.engagement)
            if core.hover_estimator is not None:
                core.hover_estimator = HoverThrustEstimator(r.flies, cfg.hover)
        app.vehicle_report["after_takeoff"] = r.as_dict()
        app.log.event(r.line, "warn" if r.warning else "info")
        if app.stderr is not None:
            print(f"companion: {r.line}", file=app.stderr, flush=True)
