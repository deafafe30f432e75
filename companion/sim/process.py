"""The simulated PX4 in its own process (``python -m companion.sim.px4 --port 0``), for real-time runs.

Used by ``companion sim`` (companion/sim/cli.py), the app benchmark and the tests.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time


class SimPX4Process:
    """The simulated PX4 in its own process (``python -m companion.sim.px4 --port 0``), for real-time runs."""

    def __init__(self, config_files: list[str] | None = None, overrides: list[str] | None = None,
                 extra: list[str] | None = None, timeout: float = 20.0) -> None:
        cmd = [sys.executable, "-m", "companion.sim.px4", "--port", "0"]
        for f in config_files or []:
            cmd += ["--config", f]
        for o in overrides or []:
            cmd += ["--set", o]
        cmd += extra or []
        from companion.px4sitl.launcher import die_with_parent

        # Own session: a Ctrl-C in the terminal reaches the app only, which hands over to HOLD while the
        # simulated PX4 still runs; the parent-death signal still ends the sim if the app is killed.
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                     bufsize=1, env={**os.environ, "PYTHONUNBUFFERED": "1"},
                                     start_new_session=True, preexec_fn=die_with_parent)
        self.remote_port: int | None = None
        self.port = self._read_port(timeout)

    def _read_port(self, timeout: float) -> int:
        import selectors

        sel = selectors.DefaultSelector()
        assert self.proc.stdout is not None
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if not sel.select(timeout=max(0.0, deadline - time.monotonic())):
                break
            line = self.proc.stdout.readline()
            if not line:
                break
            if line.startswith("PORT "):
                parts = line.split()  # "PORT <own> REMOTE <where mavsdk listens>"
                self.remote_port = int(parts[3]) if len(parts) >= 4 and parts[3].isdigit() else None
                return int(parts[1])
        self.stop()
        raise RuntimeError(f"simulated PX4 did not report its port within {timeout:.0f} s")

    @property
    def url(self) -> str:
        # mavsdk listens on 127.0.0.1 and the sim sends there, as with PX4 SITL: nothing binds 0.0.0.0.
        if self.remote_port is not None:
            return f"udpin://127.0.0.1:{self.remote_port}"
        return f"udpout://127.0.0.1:{self.port}"

    def command(self, line: str) -> None:
        """A switch on the sim's stdin (deny_arming 1, drop 1, takeover POSCTL, ...)."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def stop(self, timeout: float = 10.0) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=timeout)
        for f in (self.proc.stdin, self.proc.stdout):
            with contextlib.suppress(Exception):
                f.close()

    def __enter__(self) -> SimPX4Process:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
