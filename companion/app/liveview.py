"""The live view: the annotated camera stream over HTTP as MJPEG (``app.live_view``), for a browser or VLC.

    http://ADDRESS:PORT/            a page showing the stream
    http://ADDRESS:PORT/stream      multipart/x-mixed-replace JPEG stream (VLC: open the network stream)
    http://ADDRESS:PORT/frame.jpg   the newest annotated frame

What it shows: the tracked box with its detector confidence (green while engaged, yellow for a candidate awaiting
the operator's confirmation, grey otherwise); the frame's most confident other candidate (``BoundingBox.rival``:
dashed magenta, "other 0.42"), so an operator asked to confirm sees what competes with the candidate; the
engagement's phase, the track state and the last event.

Why its cost to the flight is bounded: drawing, JPEG encoding and every client run in a separate process
(companion/app/liveview_proc.py) at a lower CPU priority (``os.nice``), so they never take the flight process's
GIL. The two share one frame slot in shared memory with a one-byte state (IDLE -> WANT, written by the view when a
client is connected and ``max_fps`` allows; WANT -> READY, written here after copying the frame in). The frame
loop's ``offer()`` reads that byte and, only when the view wants a frame, copies it in (one memcpy) and writes
one byte to a non-blocking pipe: it never waits; without a client it copies nothing. Frames arriving while the
view is busy are dropped. The listening socket is bound here (a taken port is known at once) and handed over.
Any failure of the view (port taken, the process dies) logs one line and the flight goes on without it.
"""

from __future__ import annotations

import contextlib
import math
import mmap
import os
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

BOUNDARY = "companionframe"
PAGE = (b"<!doctype html><html><head><title>companion live view</title></head>"
        b"<body style='margin:0;background:#111'><img src='/stream' style='display:block;width:100%'></body></html>")

# The shared frame slot: byte 0 the state, then the header, then the pixels at DATA.
IDLE, WANT, READY = 0, 1, 2
# version, seq, h, w, channels, has box, awaiting, has rival, box x0 y0 x1 y1 confidence, rival x0 y0 x1 y1
# confidence, phase, text. The version leads so that a view reading a header it does not know stops with one line
# (the flight flies on) rather than drawing garbage; bump it with any change of this layout.
HEADER_VERSION = 2
HEADER = struct.Struct("<BQIIIBBB5d5d32s256s")
DATA = 512
assert 1 + HEADER.size <= DATA, "the header overlaps the pixels"

RIVAL_BGR = (255, 0, 255)  # magenta: unlike the held box's green / yellow / grey, and rare in sky and ground


@dataclass(frozen=True, slots=True)
class ViewInfo:
    """What to draw on one frame."""

    box: Any = None  # anything with .xyxy (perception.types.BoundingBox) or None
    phase: str = ""
    awaiting: bool = False  # a candidate waits for the operator's confirmation
    text: str = ""  # one more line (track state, the last event)
    # The frame's most confident other candidate (the box's ``.rival``; .xyxy and .confidence) or None: what the
    # operator weighs against the candidate before confirming it.
    rival: Any = None


def _finite_xyxy(b: Any) -> tuple[int, int, int, int] | None:
    """Pixel corners, None for a box that cannot be drawn (a detector's NaN must not end the view process)."""
    x0, y0, x1, y1 = b.xyxy
    if not all(math.isfinite(v) for v in (x0, y0, x1, y1)):
        return None
    return round(x0), round(y0), round(x1), round(y1)


def _confidence(b: Any) -> str:
    """"0.42", or "" when the box carries no finite confidence (nothing made up)."""
    c = getattr(b, "confidence", None)
    return f"{c:.2f}" if isinstance(c, (int, float)) and math.isfinite(c) else ""


def _dashed_rectangle(img: np.ndarray, p0: tuple[int, int], p1: tuple[int, int], colour: tuple[int, int, int],
                      thickness: int = 2, dash: int = 8, gap: int = 5) -> None:
    """OpenCV has no dashed line: dashes along each edge (dashed: not the box the app holds)."""
    import cv2

    (x0, y0), (x1, y1) = p0, p1
    for a, b, fixed, horizontal in ((x0, x1, y0, True), (x0, x1, y1, True), (y0, y1, x0, False),
                                    (y0, y1, x1, False)):
        for s in range(a, b + 1, dash + gap):
            e = min(s + dash - 1, b)
            cv2.line(img, (s, fixed) if horizontal else (fixed, s), (e, fixed) if horizontal else (fixed, e),
                     colour, thickness)


def annotate(image: np.ndarray, info: ViewInfo) -> np.ndarray:
    import cv2

    img = image.copy() if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    r = info.rival
    if r is not None and (xy := _finite_xyxy(r)) is not None:  # first: the held box is drawn over it
        x0, y0, x1, y1 = xy
        _dashed_rectangle(img, (x0, y0), (x1, y1), RIVAL_BGR)
        cv2.putText(img, f"other {_confidence(r)}".rstrip(), (x0, max(14, y0 - 6)), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    RIVAL_BGR, 1, cv2.LINE_AA)
    b = info.box
    if b is not None and (xy := _finite_xyxy(b)) is not None:
        engaged = info.phase in ("ENGAGE", "PASS")
        colour = (0, 220, 255) if info.awaiting else (0, 255, 0) if engaged else (180, 180, 180)
        x0, y0, x1, y1 = xy
        cv2.rectangle(img, (x0, y0), (x1, y1), colour, 2)
        # its own confidence beside the rival's: the operator compares the two numbers
        label = " ".join(x for x in ("CONFIRM?" if info.awaiting else "", _confidence(b)) if x)
        if label:
            cv2.putText(img, label, (x0, max(14, y0 - 6)), cv2.FONT_HERSHEY_SIMPLEX, 0.55, colour, 2, cv2.LINE_AA)
    lines = [f"{info.phase}" + ("  candidate awaiting confirmation" if info.awaiting else ""), info.text]
    for i, s in enumerate(x for x in lines if x):
        cv2.putText(img, s, (8, 20 + 20 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 2, cv2.LINE_AA)
    return img


def _box_fields(b: Any) -> tuple[float, ...]:
    if b is None:
        return (0.0,) * 5
    return (*(float(v) for v in b.xyxy), float(getattr(b, "confidence", math.nan)))


def pack_header(seq: int, shape: tuple[int, ...], info: ViewInfo) -> bytes:
    h, w = shape[:2]
    c = shape[2] if len(shape) == 3 else 1
    return HEADER.pack(HEADER_VERSION, seq, h, w, c, info.box is not None, bool(info.awaiting),
                       info.rival is not None, *_box_fields(info.box), *_box_fields(info.rival),
                       info.phase.encode()[:32], info.text.encode()[:256])


@dataclass(frozen=True, slots=True)
class _Box:
    xyxy: tuple[float, float, float, float]
    confidence: float = math.nan  # NaN: the box had none (no number drawn)


def unpack_header(raw: bytes) -> tuple[int, tuple[int, ...], ViewInfo]:
    """ValueError for a header of another layout (HEADER_VERSION)."""
    if len(raw) < HEADER.size or raw[0] != HEADER_VERSION:
        raise ValueError(f"live-view header version {raw[0] if raw else None}, expected {HEADER_VERSION}")
    (_, seq, h, w, c, has_box, awaiting, has_rival, *nums, phase, text) = HEADER.unpack(raw[:HEADER.size])
    shape = (h, w) if c == 1 else (h, w, c)
    box = _Box(tuple(nums[0:4]), nums[4]) if has_box else None
    rival = _Box(tuple(nums[5:9]), nums[9]) if has_rival else None
    dec = lambda b: b.rstrip(b"\0").decode(errors="replace")  # noqa: E731
    return seq, shape, ViewInfo(box, dec(phase), bool(awaiting), dec(text), rival)


class LiveView:
    """``start()``, then ``offer(image, info)`` per frame (never blocks), ``close()`` at the end."""

    def __init__(self, address: str = "127.0.0.1", port: int = 0, max_fps: float = 15.0, quality: int = 70,
                 capacity: int = 3840 * 2160 * 3,  # bytes of the largest frame (4K BGR; pages used on touch)
                 on_error: Callable[[str], None] | None = None, nice: int = 10) -> None:
        self.address, self.port, self.max_fps, self.quality = address, int(port), float(max_fps), int(quality)
        self.capacity, self.nice = int(capacity), int(nice)
        self._on_error = on_error or (lambda msg: print(msg, file=sys.stderr))
        self.offered = self.sent = self.skipped = 0  # offered == sent + skipped (a frame the view did not want)
        self.failed: str | None = None  # why the view stopped (the flight goes on)
        self.proc: subprocess.Popen[bytes] | None = None
        self._mem: mmap.mmap | None = None
        self._wake_w: int | None = None
        self.sockname: tuple[Any, ...] = ()

    @property
    def url(self) -> str:
        return f"http://{self.address}:{self.port}/"

    def start(self) -> LiveView:
        """Bind the port (OSError when taken) and start the view process."""
        sock = socket.create_server((self.address, self.port), backlog=16)
        child_fds: list[int] = []  # the view's ends: closed here once it holds them (or on failure)
        try:
            self.sockname = sock.getsockname()
            self.port = self.sockname[1]
            size = DATA + self.capacity
            if hasattr(os, "memfd_create"):  # Linux: anonymous memory, freed when both processes let go
                child_fds.append(os.memfd_create("companion-liveview"))
            else:
                with tempfile.TemporaryFile() as f:
                    child_fds.append(os.dup(f.fileno()))
            os.ftruncate(child_fds[0], size)
            self._mem = mmap.mmap(child_fds[0], size)
            wake_r, self._wake_w = os.pipe()
            child_fds.append(wake_r)
            os.set_blocking(self._wake_w, False)
            fds = (sock.fileno(), *child_fds)
            # Own session: a Ctrl-C at the terminal goes to the flight, which then closes the view in order.
            # Niced from its first instruction (coreutils nice) where there is one: even its start-up yields.
            nice = ["nice", "-n", str(self.nice)] if self.nice > 0 and shutil.which("nice") else []
            self.proc = subprocess.Popen(
                [*nice, sys.executable, "-m", "companion.app.liveview_proc", *(str(f) for f in fds), str(size),
                 str(self.max_fps), str(self.quality), str(self.nice)],
                pass_fds=fds, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, start_new_session=True)
        except BaseException:
            self.close()
            raise
        finally:
            sock.close()  # the view process holds it now: if it dies, the port is free again
            for fd in child_fds:
                os.close(fd)
        return self

    def offer(self, image: np.ndarray | None, info: ViewInfo) -> None:
        """The frame loop's only call: a byte read, and a copy only when the view wants a frame; never waits."""
        mem = self._mem
        if image is None or mem is None or self.failed is not None:
            return
        self.offered += 1
        if mem[0] != WANT:
            self.skipped += 1
            if self.proc is not None and self.proc.poll() is not None:  # waitpid(WNOHANG): no wait
                self._fail(f"the process exited with code {self.proc.returncode}")
            return
        if image.dtype != np.uint8 or image.nbytes > self.capacity or image.ndim not in (2, 3):
            self._fail(f"cannot show a {image.dtype} frame of shape {image.shape}")
            return
        mem[1:1 + HEADER.size] = pack_header(self.sent + 1, image.shape, info)
        np.ndarray(image.shape, np.uint8, buffer=mem, offset=DATA)[...] = image
        mem[0] = READY
        self.sent += 1
        try:
            os.write(self._wake_w, b"\1")  # type: ignore[arg-type]
        except BlockingIOError:
            pass  # the pipe is full of wake-ups already: the view will see READY
        except OSError as e:  # the view's end is gone
            self._fail(str(e))

    def _fail(self, why: str) -> None:
        self.failed = why
        self._on_error(f"live view stopped ({why}); flying on without it")
        self.close()

    def close(self) -> None:
        """Stop the view at once (it holds nothing worth saving): no wait worth speaking of in the flight."""
        if self._wake_w is not None:
            with contextlib.suppress(OSError):
                os.close(self._wake_w)  # also its signal to exit, should the terminate below not arrive
            self._wake_w = None
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=1.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=1.0)
        if self._mem is not None:
            self._mem.close()
            self._mem = None


def from_config(cfg: Any, on_error: Callable[[str], None] | None = None) -> LiveView | None:
    """The live view of ``app.live_view``, started; None when it is off or cannot start (``on_error`` says why,
    in one line: the flight never depends on it)."""
    lv = cfg.app.live_view
    if not lv.enabled:
        return None
    view = LiveView(lv.address, lv.port, lv.max_fps, lv.quality, on_error=on_error)
    try:
        return view.start()
    except OSError as e:
        view._on_error(f"live view off: cannot serve on {lv.address}:{lv.port} ({e}); flying on without it")
        return None
