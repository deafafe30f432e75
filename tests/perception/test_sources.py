"""Camera sources: a video file the test writes, the synthetic source, newest-frame semantics, errors."""

from __future__ import annotations

import itertools
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from perception.sources import SourceError, open_source


def _frame(k: int) -> np.ndarray:
    """Frame k: grey level 4k, so the index survives lossy compression (read back as round(mean / 4))."""
    return np.full((120, 160, 3), 4 * k, np.uint8)


def _index(frame: np.ndarray) -> int:
    return round(float(frame.mean()) / 4)


@pytest.fixture
def video(tmp_path: Path) -> Path:
    path = tmp_path / "clip.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (160, 120))
    assert w.isOpened()
    for k in range(40):
        w.write(_frame(k))
    w.release()
    return path


def test_video_file_offline_reads_every_frame_in_order(video: Path) -> None:
    with open_source(str(video), realtime=False) as src:
        got, times = [], []
        while (item := src.read(timeout=5.0)) is not None:
            t, frame = item
            got.append(_index(frame))
            times.append(t)
        assert got == list(range(40))
        assert all(b > a for a, b in itertools.pairwise(times))  # capture timestamps, monotonic
        assert src.stats() == {"captured": 40, "delivered": 40, "dropped": 0}
        assert src.ended and src.read(timeout=0.1) is None
    assert not src._thread.is_alive()


def test_newest_frame_wins_and_stale_frames_are_counted() -> None:
    def ramp(t: float) -> np.ndarray:
        return np.full((8, 8, 3), min(int(t * 100), 250), np.uint8)  # value = frame index (up to 250)

    with open_source("synthetic", realtime=True, frame_fn=ramp, fps=100.0) as src:
        first = src.read(timeout=5.0)
        assert first is not None
        time.sleep(0.3)  # the consumer is slow: ~30 frames are captured meanwhile
        second = src.read(timeout=5.0)
        assert second is not None
        assert second[0] > first[0]
        # the reader skipped to the newest frame: it is not the next one after `first`
        assert int(second[1][0, 0, 0]) > int(first[1][0, 0, 0]) + 1
        src.close()
        s = src.stats()
        assert s["dropped"] >= 1
        # every captured frame was either delivered, dropped, or is the one still waiting
        assert s["captured"] - s["delivered"] - s["dropped"] in (0, 1)


def test_synthetic_source_is_deterministic_offline() -> None:
    calls: list[float] = []

    def fn(t: float) -> np.ndarray | None:
        calls.append(t)
        return None if len(calls) > 5 else np.full((4, 4, 3), len(calls), np.uint8)

    with open_source("synthetic", realtime=False, frame_fn=fn, fps=30.0) as src:
        vals = []
        while (item := src.read(timeout=5.0)) is not None:
            vals.append(int(item[1][0, 0, 0]))
    assert vals == [1, 2, 3, 4, 5]
    assert calls[:5] == pytest.approx([k / 30.0 for k in range(5)])


def test_bad_sources_fail_with_one_line(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match=r"no such video file") as ei:
        open_source(str(tmp_path / "missing.mp4"))
    assert "\n" not in str(ei.value)
    with pytest.raises(SourceError, match="needs a frame function"):
        open_source("synthetic")
    with pytest.raises(SourceError, match=r"camera source 97: cannot open"):
        open_source(97)  # no such V4L2 device
    from perception.sources import _has_gstreamer

    if not _has_gstreamer():
        with pytest.raises(SourceError, match="no GStreamer support"):
            open_source("videotestsrc ! videoconvert ! appsink")
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"not a video" * 10)
    with pytest.raises(SourceError, match="cannot open"):
        open_source(str(junk))


def test_read_times_out_without_frames() -> None:
    def never(t: float) -> np.ndarray | None:
        time.sleep(0.05)
        return None

    with open_source("synthetic", realtime=True, frame_fn=never, fps=10.0) as src:
        assert src.read(timeout=2.0) is None  # ended without a frame: returns instead of blocking
