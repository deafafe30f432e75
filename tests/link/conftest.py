"""Fixtures for the vehicle-link tests: a fresh simulated PX4 per test and a raw MAVLink client.

Everything talks over real UDP sockets on 127.0.0.1; the simulated PX4 binds a free port of its
own, so tests can run in parallel (pytest -n).
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from linkkit import FAST_PX4, TRUE_HOVER, RawGcs

from companion.config import Config
from companion.sim.dynamics import QuadParams
from companion.sim.px4 import SimPX4


@pytest.fixture
def cfg() -> Config:
    return Config()


@pytest.fixture
def sim(cfg: Config) -> Iterator[SimPX4]:
    params = QuadParams.from_config(cfg)
    params = QuadParams(**{**params.__dict__, "hover_thrust": TRUE_HOVER})
    with SimPX4(cfg, params=params, px4_params=FAST_PX4) as s:
        yield s


@pytest.fixture
def gcs(sim: SimPX4) -> Iterator[RawGcs]:
    g = RawGcs(sim.port)
    g.heartbeat()  # the sim answers whoever it heard from
    yield g
    g.close()
