"""Helpers for the tests against real PX4 SITL (SIH): one PX4 per xdist worker, the app as a real process.

PX4 needs 30-40 s after start before it would arm, so each pytest worker starts one instance (a fresh
working folder, the first free instance) and the tests share it: ``Px4Bench.ready()`` lands, disarms,
sets Hold and waits for pre-flight OK between tests, and starts a fresh PX4 when that does not work.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from companion.app.atrest import tilt_of
from companion.config import load_config
from companion.flightlog import read_table
from companion.frames import R_from_quat_wxyz
from companion.px4sitl.launcher import PX4Sitl, PX4SitlError, find_sitl_dir, px4_params
from companion.px4sitl.truth import SihTruth

REPO = Path(__file__).resolve().parents[2]
SKIP_REASON = ("no PX4 SITL build: set PX4_SITL_DIR to a folder with bin/px4 and etc/ "
               "(../shared/px4-sitl here; docs/px4.md says how to build one)")


def sitl_dir() -> Path | None:
    try:
        return find_sitl_dir(None, "")
    except PX4SitlError:
        return None


def instance_range() -> range:
    """COMPANION_PX4_INSTANCES=A-B limits the instances tests may use (default 0-9)."""
    spec = os.environ.get("COMPANION_PX4_INSTANCES", "0-9")
    a, _, b = spec.partition("-")
    return range(int(a), int(b or a) + 1)


MAX_RESTING_TILT_DEG = 2.0  # fresh: 0.0; landings at rest 0.1-3.0 deg (2026-12-07), linear gates ~2.8: a restart


def resting_tilt(px4: PX4Sitl) -> float:
    """deg, the vehicle's true tilt (SIH's truth link)."""
    truth = SihTruth(px4.truth_url, px4.origin)
    try:
        q = truth.wait(10.0).q_wxyz
    finally:
        truth.close()
    return math.degrees(tilt_of(R_from_quat_wxyz(q)))


class Px4Bench:
    """One PX4 SITL instance shared by the tests of one worker."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.px4: PX4Sitl | None = None
        self.cfg = load_config([], [])

    def _start(self) -> PX4Sitl:
        if self.px4 is not None:
            self.px4.stop()
        self.px4 = PX4Sitl(find_sitl_dir(None, ""), candidates=instance_range(), work_parent=self.root,
                           params=px4_params(self.cfg))
        self.px4.start()
        self.px4.wait_preflight(120.0)
        return self.px4

    def fresh(self) -> PX4Sitl:
        """A freshly started PX4 (new working folder), on the ground, pre-flight checks passing."""
        return self._start()

    def ready(self) -> PX4Sitl:
        """PX4 on the ground, disarmed, in Hold, pre-flight checks passing, resting level."""
        if self.px4 is None or not self.px4.running:
            return self._start()
        try:
            self.px4.land_and_reset(90.0)
        except PX4SitlError:
            return self._start()
        # SIH freezes the vehicle's rotation on its ground: one that came down tilted stays so, and its next
        # take-off spends the motors on a roll it never makes (2026-12-07: 46 deg after a landing at speed, then
        # every take-off of that instance stayed at 0 m). Only a fresh PX4 stands level again.
        tilt = resting_tilt(self.px4)
        if tilt > MAX_RESTING_TILT_DEG:
            print(f"PX4 instance {self.px4.instance}: resting {tilt:.1f} deg tilted on SIH's ground; a fresh one")
            return self._start()
        return self.px4

    def retire(self) -> None:
        """Stop this PX4 so that the next test gets a fresh one. After a test froze PX4 (SIGSTOP, then thawed) its
        SIH sensors time out: CI 2026-12-08 saw the next test's take-off end in PX4's failsafe Land ("Magnetometer
        sensor #0 failure: Timeout", "No valid data from barometer"), and the test after it stay on SIH's ground."""
        if self.px4 is not None:
            self.px4.stop()

    def close(self) -> None:
        if self.px4 is not None:
            self.px4.stop()


def app_command(px4: PX4Sitl, log_dir: Path, *overrides: str) -> list[str]:
    """``companion fly`` with the synthetic camera (geometric box) against this PX4, SIH truth for the score."""
    cmd = [sys.executable, "-m", "companion.cli", "fly", "--yes", "--synthetic", "--geometric", "--no-plot",
           "--log-dir", str(log_dir)]
    for o in [*px4.config_overrides(), *overrides]:
        cmd += ["--set", o]
    return cmd


def start_app(px4: PX4Sitl, log_dir: Path, *overrides: str) -> subprocess.Popen[str]:
    return subprocess.Popen(app_command(px4, log_dir, *overrides), cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})


def flight_folder(log_dir: Path, timeout: float = 30.0) -> Path:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = [p for p in log_dir.glob("*") if (p / "states.csv").exists()]
        if found:
            return found[0]
        time.sleep(0.1)
    raise AssertionError(f"no flight folder under {log_dir} within {timeout:.0f} s")


def states(folder: Path) -> list[str]:
    t = read_table(folder / "states.csv")
    return [str(s) for s in t["to_state"]] if len(t) else []


def wait_state(folder: Path, state: str, proc: subprocess.Popen[str], timeout: float) -> float:
    """Block until the flight log shows ``state`` (returns time.monotonic() then); fail if the app exits."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if state in states(folder):
            return time.monotonic()
        if proc.poll() is not None:
            raise AssertionError(f"app exited ({proc.returncode}) before {state}: {states(folder)}\n"
                                 f"{proc.stdout.read() if proc.stdout else ''}")
        time.sleep(0.05)
    raise AssertionError(f"no {state} within {timeout:.0f} s: {states(folder)}")


def finish(proc: subprocess.Popen[str], timeout: float) -> tuple[int, str]:
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGINT)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.communicate(timeout=30)
        proc.kill()
        out, _ = proc.communicate()
        raise AssertionError(f"app did not end within {timeout:.0f} s:\n{out}") from None
    return proc.returncode, out
