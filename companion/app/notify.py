"""systemd notify protocol (sd_notify(3)) in a few lines of ``socket``: READY=1, WATCHDOG=1, STATUS=, STOPPING=1.

Without $NOTIFY_SOCKET (not started by systemd with Type=notify) every call is a no-op.
The sdnotify package is unmaintained; the protocol is one datagram per message.
"""

from __future__ import annotations

import os
import socket
import sys


class Notifier:
    def __init__(self, address: str | None = None) -> None:
        addr = address if address is not None else os.environ.get("NOTIFY_SOCKET", "")
        self.address: str | None = None
        self._sock: socket.socket | None = None
        if not addr:
            return
        if addr.startswith("@"):  # abstract namespace socket
            addr = "\0" + addr[1:]
        elif not addr.startswith("/"):
            # systemd only ever sets an absolute path or @name: anything else is a broken environment.
            # Notifications are a convenience, never a reason not to fly (or to crash): warn and go on.
            print(f"companion: NOTIFY_SOCKET={addr[:80]!r} is neither an absolute path nor @name: "
                  "systemd notifications off", file=sys.stderr)
            return
        self.address = addr
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    @staticmethod
    def watchdog_interval() -> float | None:
        """Half of systemd's WatchdogSec (from $WATCHDOG_USEC), the usual ping period; None if not set."""
        usec = os.environ.get("WATCHDOG_USEC")
        pid = os.environ.get("WATCHDOG_PID")
        if not usec or (pid and pid.isdigit() and int(pid) != os.getpid()):
            return None
        try:
            return int(usec) / 2e6
        except ValueError:
            return None

    def send(self, *fields: str) -> bool:
        if self._sock is None or self.address is None:
            return False
        try:
            self._sock.sendto("\n".join(fields).encode("utf-8"), self.address)
            return True
        except OSError:
            return False  # systemd gone or socket full: never let notification break the flight

    def ready(self, status: str = "") -> bool:
        return self.send("READY=1", *([f"STATUS={status}"] if status else []))

    def watchdog(self) -> bool:
        return self.send("WATCHDOG=1")

    def status(self, text: str) -> bool:
        return self.send(f"STATUS={text.replace(chr(10), ' ')}")

    def stopping(self, status: str = "") -> bool:
        return self.send("STOPPING=1", *([f"STATUS={status}"] if status else []))

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
