"""Hostile-probe fixtures: the flight-app helpers of tests/app (real simulated PX4, real mavsdk)."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "app"))

from flighthelpers import FAST_PX4

from companion.config import load_config
from companion.sim.px4 import SimPX4


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[SimPX4]:
    px4 = SimPX4(load_config([], ["sim.seed=7"]), px4_params=FAST_PX4)
    px4.start()
    try:
        yield px4
    finally:
        px4.stop()
