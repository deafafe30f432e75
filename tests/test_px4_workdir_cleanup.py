"""PX4 SITL working folders (issue 22): an interrupted start removes its own; the next start removes those of
processes that are gone when they hold no ULog; a ULog's folder, a live owner's and a folder that is not ours
stay. No PX4 needed: the start is interrupted before PX4 runs."""

from __future__ import annotations

import io
import subprocess
import sys
from pathlib import Path

import pytest

from companion.px4sitl import launcher
from companion.px4sitl.launcher import OWNER_FILE, PX4Sitl, clean_stale_work


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid  # reaped: no such process now (reuse within the test is practically impossible)


def _folder(parent: Path, name: str, owner: int | None, ulog: bool = False) -> Path:
    d = parent / name
    (d / "log" / "2026-01-01").mkdir(parents=True)
    (d / "px4.out").write_text("INFO  [px4] startup\n")
    if owner is not None:
        (d / OWNER_FILE).write_text(f"{owner}\n")
    if ulog:
        (d / "log" / "2026-01-01" / "10_00_00.ulg").write_bytes(b"ULog")
    return d


def test_stale_folders_of_gone_processes_are_removed(tmp_path):
    import os

    dead = _dead_pid()
    stale = _folder(tmp_path, "px4-0-abc", dead)
    flown = _folder(tmp_path, "px4-1-def", dead, ulog=True)
    live = _folder(tmp_path, "px4-2-ghi", os.getpid())
    foreign = _folder(tmp_path, "px4-3-jkl", None)
    assert clean_stale_work(tmp_path) == [stale]
    assert not stale.exists() and flown.exists() and live.exists() and foreign.exists()


def test_an_interrupted_start_removes_its_folder(tmp_path, monkeypatch):
    px4 = PX4Sitl.__new__(PX4Sitl)
    px4.__dict__.update(requested=None, candidates=[0], work_parent=tmp_path, params={}, truth_rate=50.0,
                        log=lambda _m: None, instance=-1, work=None, proc=None, _lock=None, _out=None,
                        origin=None, t_start=0.0, sitl=tmp_path, bin=tmp_path)
    monkeypatch.setattr(launcher, "claim_instance", lambda c: (0, io.StringIO()))

    def interrupted(*a, **k):
        raise KeyboardInterrupt  # Ctrl-C while PX4 starts

    monkeypatch.setattr(launcher.subprocess, "Popen", interrupted)
    with pytest.raises(KeyboardInterrupt):
        px4.start()
    assert px4.work is not None and not px4.work.exists()
    assert list(tmp_path.glob("px4-*")) == []
