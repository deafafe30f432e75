"""The systemd unit: notify type, watchdog, no automatic restart; checked by systemd's own parser."""

from __future__ import annotations

import configparser
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.timeout(60)
UNIT = Path(__file__).resolve().parents[2] / "config" / "companion.service"


def _unit() -> configparser.ConfigParser:
    cp = configparser.ConfigParser(strict=False, interpolation=None)
    cp.optionxform = str  # systemd keys are case-sensitive
    cp.read_string(UNIT.read_text())
    return cp


def test_unit_policy():
    svc = _unit()["Service"]
    assert svc["Type"] == "notify" and svc["NotifyAccess"] == "main"
    assert svc["WatchdogSec"] == "2s"
    assert svc["Restart"] == "no"  # never a new flight on its own
    assert svc["KillSignal"] == "SIGTERM" and int(svc["TimeoutStopSec"]) >= 10
    assert "companion fly" in svc["ExecStart"] and "app.start=pilot" in svc["ExecStart"]


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_accepts_the_unit(tmp_path):
    # systemd-analyze checks that the program exists: point ExecStart at this interpreter's companion.
    exe = Path(sys.executable).parent / "companion"
    text = UNIT.read_text().replace("/opt/pn-companion/.venv/bin/companion", str(exe))
    unit = tmp_path / "companion.service"
    unit.write_text(text)
    r = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=30)
    problems = [line for line in (r.stdout + r.stderr).splitlines() if "companion.service" in line]
    assert r.returncode == 0 and not problems, problems
    # The check can fail: a broken value is reported.
    unit.write_text(text.replace("WatchdogSec=2s", "WatchdogSec=soon"))
    r = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=30)
    assert "WatchdogSec" in r.stderr or "sec value" in r.stderr
