"""A UDP port on 127.0.0.1 for a listener that binds it later (mavsdk's ``udpin://``, a truth reader).

``bind(0)`` hands out a port of the OS's ephemeral range, the range every unbound client socket also draws
from at its first send. Between closing such a probe and mavsdk's bind (seconds later) another process's
client socket took the port once in CI (``BIND_ERROR``). Ports below the ephemeral range are only ever taken
by an explicit bind, so a random one found free there stays free unless someone picks the same number.
"""

from __future__ import annotations

import random
import socket
from pathlib import Path

_LOW = 20000  # above PX4 SITL's fixed ports (14540+N, 14550, 14580+N, 18570+N, 19410+N)


def _ephemeral_low() -> int:
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768  # Linux's default; the IANA range starts at 49152


def _bindable(host: str, port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


def free_udp_port(host: str = "127.0.0.1") -> int:
    """A UDP port free now, outside the ephemeral range where it can be (else one the OS picks)."""
    high = _ephemeral_low() - 1
    if high - _LOW >= 1000:
        rng = random.SystemRandom()
        for _ in range(200):
            port = rng.randint(_LOW, high)
            if _bindable(host, port):
                return port
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind((host, 0))
        return int(probe.getsockname()[1])
