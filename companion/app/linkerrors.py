"""The vehicle link's failures (companion/app/link.py): one class per thing that can go wrong.

Every one derives ``LinkError`` and carries a one-line message saying what failed and where. The flight
app maps them to its outcome reasons by name (companion/app/flight.py ``_classify``).
"""

from __future__ import annotations


class LinkError(RuntimeError):
    """Base of every link failure; ``str(e)`` is one line: what failed and why."""


class ConnectFailed(LinkError):
    pass


class NotHealthy(LinkError):
    pass


class ArmDenied(LinkError):
    pass


class TakeoffFailed(LinkError):
    pass


class OffboardDenied(LinkError):
    pass


class OffboardLost(LinkError):
    """Offboard ended without the app asking: pilot takeover, PX4 failsafe or the link's watchdog."""


class CommandDenied(LinkError):
    pass


class CommandTimeout(LinkError):
    pass


class LinkLost(LinkError):
    pass


class SetpointRejected(LinkError, ValueError):
    """Upstream produced a setpoint that must never leave the app (non-finite): nothing was sent."""


class WrongAutopilot(ConnectFailed):
    """Heard an autopilot, but not the configured system (link.system_id)."""
