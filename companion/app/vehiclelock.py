"""One flight app per vehicle: an exclusive ``flock`` on a lock file named after the link.

Two apps on one vehicle fight over it (the second arms and "takes off" a vehicle already in the air
and knocks the first one out). The lock lives in ``$XDG_RUNTIME_DIR`` (else the system temp folder),
is named after the link URL with what does not name the vehicle left out (a serial port's baud
rate, a listening UDP link's address: its port is what two apps would share); a serial port is named
by the device itself (its device number, else its real path), so /dev/ttyACM0, a /dev/serial/by-id/
link to it and a path through ``..`` are one lock. The file holds the
owner's pid. ``flock`` belongs to the open file: the kernel drops it when the process ends however
it ends (SIGKILL included), so a stale file never blocks the next flight.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import re
import stat
import tempfile
from pathlib import Path


class VehicleBusy(RuntimeError):
    """Another app holds this vehicle's lock (one line: link, holder pid, lock file)."""


def lock_name(url: str) -> str:
    """``companion-<link>.lock``: the vehicle's address from the URL, in file-name characters."""
    u = url.strip()
    if u.lower().startswith("serial://"):
        dev = re.sub(r":\d+$", "", u[len("serial://"):])  # serial:///dev/ttyACM0:57600 and :921600: one vehicle
        u = "serial://" + _device_key(dev)
    u = u.lower()
    m = re.match(r"^(udpin|udp)://[^/]*:(\d+)$", u)
    if m:  # a listening link is its local port: udpin://127.0.0.1:14540 and udpin://0.0.0.0:14540 collide
        u = f"udpin://{m.group(2)}"
    return "companion-" + re.sub(r"[^a-z0-9._-]+", "_", u).strip("_")[:120] + ".lock"


def _device_key(dev: str) -> str:
    """One name per device however the path reaches it: the character device's number (st_rdev) when it
    exists, else the resolved path (symlinks, ``..``; a device that is not there yet keeps its text)."""
    try:
        st = os.stat(dev)
    except OSError:
        return os.path.realpath(dev) if dev else dev
    if stat.S_ISCHR(st.st_mode):
        return f"dev-{os.major(st.st_rdev)}-{os.minor(st.st_rdev)}"
    return os.path.realpath(dev)


def lock_dir() -> Path:
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime and Path(runtime).is_dir() and os.access(runtime, os.W_OK):
        return Path(runtime)
    return Path(tempfile.gettempdir())


class VehicleLock:
    def __init__(self, url: str, directory: Path | None = None) -> None:
        self.url = url
        self.path = (directory or lock_dir()) / lock_name(url)
        self._fd: int | None = None

    def acquire(self) -> VehicleLock:
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as e:
            raise VehicleBusy(f"{self.path}: cannot open the vehicle lock ({e.strerror or e})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = _read_pid(fd)
            os.close(fd)
            who = f"pid {holder}" if holder else "another process"
            raise VehicleBusy(f"{self.url}: another companion app ({who}) is flying this vehicle "
                              f"(lock {self.path})") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.ftruncate(self._fd, 0)
            os.close(self._fd)  # drops the flock
            self._fd = None

    def __enter__(self) -> VehicleLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def _read_pid(fd: int) -> int | None:
    try:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
        return int(text) if text.isdigit() else None
    except OSError:
        return None
