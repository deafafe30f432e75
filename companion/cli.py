"""``companion`` command line: one sub-command per job, each registered by its own module."""

from __future__ import annotations

import argparse
import importlib
import sys

# Each module has ``register(subparsers)`` that adds its sub-command(s) and sets ``func``.
COMMAND_MODULES = (
    "companion.bench",
    "companion.sim.cli",
    "companion.evaluation.cli",
    "companion.replay",
    "companion.app.main",
    "companion.check",
    "companion.calibrate",
    "perception.evaluate",  # companion perception eval
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="companion",
        description="PN-informed PX4 companion app: fly through moving gates from a monocular camera and the IMU.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as e:
            if e.name == name:  # that job is not built yet
                continue
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    try:  # Ctrl-C while the modules still load (the first ~0.3 s) is one line too, never a traceback
        from companion.configbase import ConfigError

        args = build_parser().parse_args(argv)
        try:
            return int(args.func(args) or 0)
        except ConfigError as e:
            print(f"companion: config error: {e}", file=sys.stderr)
            return 2
    except KeyboardInterrupt:
        print("companion: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
