"""Helpers of the live-view tests: a thread feeding frames to a LiveView as the frame loop would."""

from __future__ import annotations

import threading
import time

import numpy as np

from companion.app.liveview import LiveView, ViewInfo


class Feeder:
    """Offers ``image`` with ``info`` every ``period`` s from one thread (as the frame loop does) until stopped."""

    def __init__(self, lv: LiveView, image: np.ndarray, info: ViewInfo, period: float = 0.02) -> None:
        self.lv, self.image, self.info, self.period = lv, image, info, period
        self._stop = threading.Event()
        self._th = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.lv.offer(self.image, self.info)
            time.sleep(self.period)

    def __enter__(self) -> Feeder:
        self._th.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._th.join(timeout=5)
