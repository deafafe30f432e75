"""Fixtures of the flight-app tests: a real simulated PX4 on 127.0.0.1 that the real mavsdk talks to."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from flighthelpers import FAST_PX4

from companion.config import load_config
from companion.sim.px4 import SimPX4


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[SimPX4]:
    cfg = load_config([], ["sim.seed=7"])
    px4 = SimPX4(cfg, px4_params=FAST_PX4)
    px4.start()
    try:
        yield px4
    finally:
        px4.stop()


