"""The simulated PX4 in its own process (``python -m companion.sim.px4``), so a test can freeze it with SIGSTOP
as a link outage (a radio fade, a stalled companion-PX4 UART): the app's commands wait in the socket buffer
and reach PX4 when it resumes, exactly as they would through a real outage."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

from flighthelpers import FAST_PX4

ROOT = Path(__file__).resolve().parents[2]


class SimProcess:
    def __init__(self) -> None:
        cmd = [sys.executable, "-m", "companion.sim.px4", "--port", "0", "--set", "sim.seed=7"]
        for k, v in FAST_PX4.items():
            cmd += ["--param", f"{k}={v}"]
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                     text=True, cwd=ROOT)
        line = self.proc.stdout.readline()  # "PORT <n> REMOTE <m>"
        parts = line.split()
        assert parts[:1] == ["PORT"] and parts[2:3] == ["REMOTE"], line
        self.url = f"udpin://127.0.0.1:{parts[3]}"
        self._lock = threading.Lock()
        self.paused_at: list[float] = []

    def ask(self, line: str) -> str:
        with self._lock:
            self.proc.stdin.write(line + "\n")
            self.proc.stdin.flush()
            return self.proc.stdout.readline().strip()

    def freeze(self, seconds: float) -> threading.Timer:
        """SIGSTOP now, SIGCONT after ``seconds`` (from a timer thread: the caller's loop runs on)."""
        os.kill(self.proc.pid, signal.SIGSTOP)
        timer = threading.Timer(seconds, os.kill, (self.proc.pid, signal.SIGCONT))
        timer.daemon = True
        timer.start()
        return timer

    def state(self) -> dict[str, str]:
        """The simulated vehicle's own state: mode, armed (what PX4 *is*, not what the app was told)."""
        reply = self.ask("state")
        assert reply.startswith("STATE "), reply
        return dict(kv.split("=", 1) for kv in reply.split()[1:])

    def events(self) -> list[str]:
        reply = self.ask("events")
        assert reply.startswith("EVENTS "), reply
        return [what for _, what in json.loads(reply[len("EVENTS "):])]

    def stop(self) -> None:
        if self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGCONT)
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)
        for f in (self.proc.stdin, self.proc.stdout):
            if f:
                f.close()
