"""``python -m companion.sim.px4``: the simulated PX4 in its own process, switched over stdin.

Prints ``PORT <n> REMOTE <m>`` on stdout, reads switch commands from stdin (one reply line each),
stops on SIGTERM/SIGINT or ``quit``.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading

from companion.sim.px4.realtime import SimPX4

_SWITCH_HELP = (
    "stdin commands: deny_arming 0|1, deny_offboard 0|1, fail_preflight 0|1, drop 0|1, silence 0|1, "
    "takeover [POSCTL|HOLD|LAND], kill, nan_attitude 0|1, param NAME VALUE, state, events, "
    "wait_event PREFIX SECONDS, quit"
)


def _stdin_command(sim: SimPX4, line: str) -> str:
    parts = line.split()
    if not parts:
        return ""
    cmd, args = parts[0], parts[1:]
    try:
        if cmd == "deny_arming":
            sim.deny_arming = args[0] == "1"
        elif cmd == "deny_offboard":
            sim.deny_offboard = args[0] == "1"
        elif cmd == "fail_preflight":
            sim.fail_preflight = args[0] == "1"
        elif cmd == "drop":
            sim.drop_link(args[0] == "1")
        elif cmd == "silence":
            sim.silence_commands(args[0] == "1")
        elif cmd == "nan_attitude":
            sim.corrupt_attitude(args[0] == "1")
        elif cmd == "kill":
            sim.force_disarm()
        elif cmd == "takeover":
            sim.pilot_takeover(args[0] if args else "POSCTL")
        elif cmd == "param":
            sim.set_param(args[0], float(args[1]))
        elif cmd == "state":
            s = sim.truth()
            return (f"STATE t={sim.time:.3f} mode={sim.mode} armed={int(sim.armed)} "
                    f"p={s.p[0]:.3f},{s.p[1]:.3f},{s.p[2]:.3f} v={s.v[0]:.3f},{s.v[1]:.3f},{s.v[2]:.3f}")
        elif cmd == "events":
            return "EVENTS " + json.dumps([[round(t, 4), what] for t, what in sim.events])
        elif cmd == "wait_event":
            ev = sim.wait_event(args[0], float(args[1]))
            return "TIMEOUT" if ev is None else f"EVENT {ev[0]:.4f} {ev[1]}"
        elif cmd == "quit":
            return "BYE"
        else:
            return f"ERROR unknown command {cmd!r} ({_SWITCH_HELP})"
    except (IndexError, ValueError, KeyError) as e:
        return f"ERROR {line.strip()!r}: {e}"
    return "OK"


def main(argv: list[str] | None = None) -> int:
    from companion.config import add_config_arguments, config_from_args
    from companion.configbase import ConfigError

    ap = argparse.ArgumentParser(
        prog="python -m companion.sim.px4",
        description="Simulated PX4 on 127.0.0.1 (MAVLink 2/UDP). Prints 'PORT <n>'; " + _SWITCH_HELP,
    )
    ap.add_argument("--port", type=int, default=0, help="UDP port on 127.0.0.1 (0: a free one)")
    ap.add_argument("--remote-port", type=int, default=0, metavar="PORT",
                    help="send to 127.0.0.1:PORT, where mavsdk listens with udpin:// (PX4 SITL uses 14540; "
                         "0: a free one, printed as 'REMOTE <n>')")
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                    help="PX4 parameter, e.g. --param MPC_THR_HOVER=0.42 (repeatable)")
    ap.add_argument("--no-noise", action="store_true", help="perfect sensors")
    add_config_arguments(ap)
    args = ap.parse_args(argv)
    for opt, port in (("--port", args.port), ("--remote-port", args.remote_port)):
        if port is not None and not 0 <= port <= 65535:
            print(f"companion.sim.px4: {opt} {port}: not a UDP port (0..65535)", file=sys.stderr)
            return 2
    try:
        cfg = config_from_args(args)
        px4_params = {}
        for item in args.param:
            name, _, value = item.partition("=")
            try:
                px4_params[name.strip()] = float(value)
            except ValueError:
                raise ConfigError(f"--param {item!r}: expected NAME=NUMBER") from None
        sim = SimPX4(cfg, port=args.port, remote_port=args.remote_port, px4_params=px4_params,
                     noise=not args.no_noise)
    except (ConfigError, ValueError) as e:
        print(f"companion.sim.px4: {e}", file=sys.stderr)
        return 2
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    try:
        sim.start()
    except OSError as e:
        print(f"companion.sim.px4: cannot bind 127.0.0.1:{args.port} ({e.strerror})", file=sys.stderr)
        return 1
    print(f"PORT {sim.port} REMOTE {sim.remote_port}", flush=True)

    def read_stdin() -> None:
        for line in sys.stdin:  # EOF (e.g. stdin is /dev/null) only ends the reader, not the sim
            reply = _stdin_command(sim, line)
            if reply:
                print(reply, flush=True)
            if reply == "BYE":
                stop.set()
                return

    if sys.stdin is not None:
        threading.Thread(target=read_stdin, daemon=True).start()
    try:
        while not stop.wait(0.2):
            pass
    finally:
        sim.stop()
    return 0
