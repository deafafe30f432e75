"""free_udp_port: a port a later listener can bind, outside the range client sockets draw from."""

from __future__ import annotations

import socket

from companion import netports


def test_the_port_is_bindable_and_below_the_ephemeral_range() -> None:
    low = netports._ephemeral_low()
    for _ in range(20):
        port = netports.free_udp_port()
        if low - 1 - netports._LOW >= 1000:
            assert netports._LOW <= port < low
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", port))  # free for the listener


def test_a_taken_port_is_never_handed_out(monkeypatch) -> None:
    held = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    held.bind(("127.0.0.1", 0))
    taken = held.getsockname()[1]
    try:
        # Force the random pick to the taken port first: the next candidates must be used instead.
        free = netports.free_udp_port()
        picks = iter([taken, taken, free])
        monkeypatch.setattr(netports.random.SystemRandom, "randint", lambda self, a, b: next(picks))
        monkeypatch.setattr(netports, "_ephemeral_low", lambda: 65000)
        assert netports.free_udp_port() == free
    finally:
        held.close()


def test_without_room_below_the_range_the_os_picks(monkeypatch) -> None:
    monkeypatch.setattr(netports, "_ephemeral_low", lambda: 1024)
    port = netports.free_udp_port()
    assert 1024 <= port <= 65535
