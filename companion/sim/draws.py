"""Standard normals of a random stream drawn a block at a time (the simulator's per-frame noise)."""

from __future__ import annotations

import numpy as np


class NormalReadAhead:
    """``take(n)``: the next n standard normals of ``rng``, drawn ``block`` at a time.

    A Generator's normals come one after another whatever the size of the call (``standard_normal(288)`` is the
    same 288 values as 32 calls of 9), so for a stream nothing else draws from this hands out exactly the values a
    call a frame would give, for one numpy call per block instead of one per frame (~0.5 us a call, a few calls
    a simulated frame). Whoever reads ahead must be the stream's only reader from then on: what is left of the
    block when the run ends is never used, and another reader would get values already handed out.
    """

    def __init__(self, rng: np.random.Generator, block: int = 256) -> None:
        self.rng = rng
        self.block = int(block)
        self._buf: list[float] = []
        self._i = 0

    def take(self, n: int) -> list[float]:
        i, j = self._i, self._i + n
        if j > len(self._buf):
            self._buf = self._buf[i:] + self.rng.standard_normal(max(self.block, n)).tolist()
            i, j = 0, n
        self._i = j
        return self._buf[i:j]
