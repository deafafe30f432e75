"""``companion check CONFIG...``: validate a configuration without flying.

The same loading as every other command (config/default.yaml, then the files in order, then
``--set``), so the same one-line errors and exit code 2. On success a short summary of what a
flight would use; the detector is loaded too when the camera needs it (a missing or broken model
is a config error: ``perception.model``).
"""

from __future__ import annotations

import argparse
from typing import Any

from companion.app.preflight import summary_lines
from companion.configbase import ConfigError, printable


def register(subparsers: Any) -> None:
    p = subparsers.add_parser("check", help="validate config file(s) without flying; print what a flight would use",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("files", nargs="*", metavar="CONFIG", help="YAML overlays on config/default.yaml, in order")
    p.add_argument("--config", "-c", action="append", default=[], metavar="FILE", help="same as a CONFIG argument")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override one value")
    p.add_argument("--no-detector", action="store_true", help="do not load the detector model")
    p.set_defaults(func=_cmd_check)


def _cmd_check(args: argparse.Namespace) -> int:
    from companion.config import load_config

    files = [*args.files, *args.config]
    cfg = load_config(files, args.overrides)  # ConfigError -> one line, exit 2 (companion/cli.py)
    need_detector = not (cfg.app.camera == "synthetic" and cfg.app.synthetic.render == "geometric")
    det = "not needed (geometric synthetic camera)"
    if need_detector and not args.no_detector:
        from companion.app.assemble import detector_available

        why = detector_available(cfg)
        if why is not None:
            raise ConfigError(f"perception.model: {cfg.perception.model}: detector does not load ({why})")
        from companion.app.assemble import real_frames
        from perception.detector import model_path

        det = f"loads ({model_path(cfg.perception, real_frames(cfg)).name})"
    elif args.no_detector:
        det = "not checked (--no-detector)"
    print(printable(f"config OK: {', '.join(['config/default.yaml', *files])}" + (
        f" + {len(args.overrides)} --set" if args.overrides else "")))
    for line in [*summary_lines(cfg), f"detector: {det}"]:
        print("  " + printable(line))  # config text (a source, a path) may hold terminal escapes
    return 0

