"""Last resort when the app's event loop itself stops (a blocking call on the flight loop's thread).

The asyncio watchdog and the link's watchdog cannot run then, and MAVSDK's C++ thread keeps
resending the last attitude setpoint to PX4 forever. This thread, outside the event loop, kills
the process with SIGKILL when the loop has not beaten for ``timeout`` while we command the vehicle:
MAVSDK dies with it, the setpoints stop, and PX4's offboard-loss failsafe takes over (the same
outcome as systemd's WatchdogSec, which covers the service; this covers the CLI too).

Layers, fastest first: the app's and the link's asyncio watchdogs (perception_stall_timeout), the
link's loop-guard thread (stops offboard -> HOLD at 2x that + 0.2 s), then this kill at
safety.loop_stall_timeout: a process whose loop is stuck can do nothing useful any more, and the
kill also covers a loop guard whose stop command failed.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from collections.abc import Callable


class LoopDeadman:
    def __init__(self, timeout: float, engaged: Callable[[], bool],
                 last_words: Callable[[str], None] | None = None) -> None:
        self.timeout = float(timeout)
        self.engaged = engaged
        self.last_words = last_words
        self._beat = time.monotonic()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="loop-deadman", daemon=True)

    def start(self) -> LoopDeadman:
        self._thread.start()
        return self

    def beat(self) -> None:
        self._beat = time.monotonic()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)

    def _run(self) -> None:
        last = time.monotonic()
        while not self._stop.wait(self.timeout / 4):
            now = time.monotonic()
            if now - last > self.timeout / 2:
                # This thread did not run either: the whole process was stopped (SIGSTOP, a paused VM), not only
                # the loop. Its loop gets the full timeout from now to notice what PX4 did meanwhile.
                self._beat = now
            last = now
            age = now - self._beat
            if age > self.timeout and self.engaged():
                msg = (f"companion: event loop stalled for {age:.1f} s while commanding the vehicle: killing the "
                       "process (MAVSDK's setpoint resends end with it: PX4's offboard-loss failsafe acts if it is "
                       "still in OFFBOARD)\n")
                os.write(2, msg.encode())
                if self.last_words is not None:
                    with contextlib.suppress(Exception):  # nothing may stop the kill
                        self.last_words(msg.strip())
                os.kill(os.getpid(), signal.SIGKILL)
