"""``--record`` checked before anything is made or flown (issue 22): a target that is not a folder, a disk
without room for a recording, a byte budget that is not a finite number."""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest

from companion.app.record import RecordError, check_record_target

pytestmark = pytest.mark.timeout(120)


def _fly(tmp_path, *args: str) -> subprocess.CompletedProcess:
    # A link URL nothing answers on: only a check before connecting can end this within the timeout.
    return subprocess.run([sys.executable, "-m", "companion.cli", "fly", "--yes", "--set",
                           f"log.directory={tmp_path / 'logs'}", *args],
                          capture_output=True, text=True, timeout=90)


@pytest.mark.parametrize(("args", "fragment"), [
    (["--record", "/dev/null"], "--record /dev/null: not a folder"),
    (["--record", "REC", "--record-max-mb", "inf"], "--record-max-mb inf: must be a number > 0"),
    (["--record", "REC", "--record-max-mb", "nan"], "--record-max-mb nan: must be a number > 0"),
])
def test_fly_refuses_a_bad_record_target_before_starting(tmp_path, args, fragment):
    args = [str(tmp_path / "rec") if a == "REC" else a for a in args]
    res = _fly(tmp_path, *args)
    assert res.returncode == 2, (res.returncode, res.stderr[-500:])
    assert len(res.stderr.strip().splitlines()) == 1 and fragment in res.stderr, res.stderr
    assert not (tmp_path / "logs").exists()  # no flight folder made
    assert not (tmp_path / "rec").exists()


def test_too_little_free_space_is_refused_at_start(tmp_path):
    free = shutil.disk_usage(tmp_path).free
    # The recorder leaves free_margin bytes on the disk: with a margin of all but 5 MB of what is free, it
    # would stop at once (the "< 210 MB free: 0 frames recorded, exit 0").
    with pytest.raises(RecordError, match=r"MB free on its disk; recording needs more than"):
        check_record_target(tmp_path / "rec", free_margin=free - 5 * 1024 * 1024)
    check_record_target(tmp_path / "rec", free_margin=0)  # the same folder with room: accepted
    assert not (tmp_path / "rec").exists()  # checking makes nothing
    (tmp_path / "file").write_text("x")
    with pytest.raises(RecordError, match="not a folder"):
        check_record_target(tmp_path / "file")
    with pytest.raises(RecordError, match="not a writable folder"):
        check_record_target(tmp_path / "file" / "sub")
