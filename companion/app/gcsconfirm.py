"""The ground station's confirm/withdraw command (``app.engage: confirm``): thin I/O around companion/confirm.py.

The ground station sends COMMAND_LONG (or COMMAND_INT) with command ``app.confirm.command`` (MAV_CMD_USER_1 by
default), param1 1 = confirm / 0 = withdraw, addressed to the companion's own (system id, component id)
(``link.own_ids``: mavsdk's companion-computer ids, 1/195). PX4 forwards it from its GCS link to the onboard link:
both are started with forwarding on (``-f`` in PX4's etc/init.d-posix/px4-rc.mavlink) and PX4 passes a targeted
message on to a link where it has seen that component, which mavsdk's own traffic provides. mavsdk's server
component (``mavlink_direct_server``) hands it to us; ``OperatorConfirm.command`` decides; the COMMAND_ACK goes
back to the sender (PX4 forwards it to the GCS link). The ground station's HEARTBEATs, also forwarded, keep its
confirmation alive (``OperatorConfirm.heard``, ``app.confirm.gcs_max_age``).

Messages, not ``subscribe_command``: with mavsdk 4.1 ``subscribe_command`` delivered nothing for the command PX4
forwarded (PX4 1.15 SITL), while the message subscription sees it; mavsdk sent no ack of its own either.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
from collections.abc import Callable
from typing import Any

from companion.confirm import ACCEPTED, GcsCommand, OperatorConfirm

_RESULT = {0: "ACCEPTED", 1: "TEMPORARILY_REJECTED", 2: "DENIED"}


def parse_command(msg: Any, own_ids: tuple[int, int], command_id: int, t: float) -> GcsCommand | None:
    """A mavlink_direct COMMAND_LONG/COMMAND_INT, if it is our confirm/withdraw command addressed to us."""
    try:
        f = json.loads(msg.fields_json)
        if int(f["command"]) != command_id:
            return None
        if (int(f["target_system"]), int(f["target_component"])) != own_ids:
            return None  # another component's (PX4 forwards what it has seen addressed anywhere)
        p1 = f["param1"]
        p1 = math.nan if p1 is None else float(p1)
    except (ValueError, KeyError, TypeError):
        return None
    return GcsCommand(t, p1, int(msg.system_id), int(msg.component_id))


def ack_message(cmd: GcsCommand, command_id: int, result: int) -> dict[str, int]:
    """COMMAND_ACK's fields, to the sender."""
    return {"command": command_id, "result": result, "progress": 0, "result_param2": 0,
            "target_system": cmd.sysid, "target_component": cmd.compid}


class GcsConfirm:
    """Listens for the command while the flight's frame loop runs; each command is decided and acknowledged at once
    (the ground station resends an unacknowledged command after ~1 s), not at the next frame."""

    def __init__(self, link: Any, confirm: OperatorConfirm, awaiting: Callable[[], bool],
                 log: Callable[..., None], clock: Callable[[], float], command_id: int) -> None:
        self.link, self.confirm, self.awaiting, self.log, self.clock = link, confirm, awaiting, log, clock
        self.command_id = int(command_id)
        self._plugin: Any = None
        self._tasks: list[asyncio.Task[None]] = []

    async def start(self) -> bool:
        """Subscribe; False (and a log line) when the link cannot receive commands (no mavsdk server component)."""
        mav, own = getattr(self.link, "mavsdk", None), getattr(self.link, "own_ids", None)
        if mav is None or own is None:
            return False
        try:
            from mavsdk.asyncio.plugins.mavlink_direct_server import MavlinkDirectServerAsync

            server = await mav.server_component()
            if server is None:
                raise RuntimeError("mavsdk has no server component")
            self._plugin = MavlinkDirectServerAsync(server)
        except Exception as e:  # no GCS command: the switch still confirms; nothing confirmed -> acquire_timeout
            self.log(f"ground-station confirm unavailable ({type(e).__name__}: {e}); RC switch only", "warn")
            return False
        for name in ("COMMAND_LONG", "COMMAND_INT", "HEARTBEAT"):
            self._tasks.append(asyncio.create_task(self._follow(name), name=f"gcsconfirm:{name}"))
        self.log(f"ground-station confirm: command {self.command_id} to {own[0]}/{own[1]} "
                 "(param1 1 confirm, 0 withdraw)")
        return True

    async def close(self) -> None:
        for t in self._tasks:
            t.cancel()
        if self._tasks:
            await asyncio.wait(self._tasks, timeout=2.0)
        self._tasks = []
        if self._plugin is not None:  # before the link destroys mavsdk, not whenever Python collects it
            with contextlib.suppress(Exception):
                self._plugin.destroy()
            self._plugin = None

    async def _follow(self, name: str) -> None:
        try:
            async with contextlib.aclosing(self._plugin.subscribe_message(name)) as gen:
                async for msg in gen:
                    if name == "HEARTBEAT":
                        self.confirm.heard(self.clock(), int(msg.system_id), int(msg.component_id))
                    else:
                        await self.on_command(msg)
        except asyncio.CancelledError:
            raise
        except Exception as e:  # the RC switch still works; a GCS confirmation lapses (gcs_max_age)
            self.log(f"ground-station confirm: {name} stream failed: {type(e).__name__}: {e}", "warn")

    async def on_command(self, msg: Any) -> None:
        cmd = parse_command(msg, self.link.own_ids, self.command_id, self.clock())
        if cmd is None:
            return
        result, why = self.confirm.command(cmd.t, cmd, self.awaiting())
        what = {1.0: "confirm", 0.0: "withdraw"}.get(cmd.param1, f"param1 {cmd.param1}")
        self.log(f"ground-station {what} from {cmd.sysid}/{cmd.compid}: {_RESULT.get(result, result)} ({why})",
                 "info" if result == ACCEPTED else "warn")
        from mavsdk.plugins.mavlink_direct_server import MavlinkMessage

        ack = MavlinkMessage("COMMAND_ACK", 0, 0, cmd.sysid, cmd.compid,
                             json.dumps(ack_message(cmd, self.command_id, result)))
        try:
            await self._plugin.send_message(ack)
        except Exception as e:  # the GCS resends; the decision stands
            self.log(f"ground-station confirm: COMMAND_ACK not sent: {type(e).__name__}: {e}", "warn")
