"""Fixtures of the tests against real PX4 SITL: skipped with a reason when no build is found (PX4_SITL_DIR)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from px4kit import SKIP_REASON, Px4Bench, sitl_dir

from companion.px4sitl.launcher import PX4Sitl


@pytest.fixture(scope="session")
def px4_bench(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Px4Bench]:
    """One PX4 per pytest worker (session scope is per xdist worker), stopped at the end."""
    if sitl_dir() is None:
        pytest.skip(SKIP_REASON)
    bench = Px4Bench(tmp_path_factory.mktemp("px4"))
    try:
        yield bench
    finally:
        bench.close()


@pytest.fixture
def px4(px4_bench: Px4Bench) -> PX4Sitl:
    """PX4 ready for a flight: on the ground, disarmed, in Hold, pre-flight checks passing."""
    return px4_bench.ready()


@pytest.fixture
def log_dir(tmp_path: Path) -> Path:
    d = tmp_path / "flights"
    d.mkdir()
    return d
