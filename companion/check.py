"""``companion check CONFIG...``: validate a configuration without flying.

The same loading as every other command (config/default.yaml, then the files in order, then
``--set``), so the same one-line errors and exit code 2. On success a short summary of what a
flight would use; the detector is loaded too when the camera needs it (a missing or broken model
is a config error: ``perception.model``).
"""

from __future__ import annotations

import argparse
from typing import Any

from companion.config import camera_uptilt
from companion.configbase import ConfigError


def register(subparsers: Any) -> None:
    p = subparsers.add_parser("check", help="validate config file(s) without flying; print what a flight would use",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("files", nargs="*", metavar="CONFIG", help="YAML overlays on config/default.yaml, in order")
    p.add_argument("--config", "-c", action="append", default=[], metavar="FILE", help="same as a CONFIG argument")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override one value")
    p.add_argument("--no-detector", action="store_true", help="do not load the detector model")
    p.set_defaults(func=_cmd_check)


def summary_lines(cfg: Any) -> list[str]:
    """What a flight would use, one topic per line (also the static part of the pre-flight summary)."""
    K = cfg.camera.K
    dist = ", ".join(f"{d:.4g}" for d in cfg.camera.distortion) or "none"
    af, g, s, app = cfg.airframe, cfg.guidance, cfg.safety, cfg.app
    cam_src = "synthetic" if app.camera == "synthetic" else cfg.perception.source
    m, uptilt = cfg.camera.mount, camera_uptilt(cfg)
    return [
        f"airframe: {af.name}, mass {af.mass:g} kg, hover thrust {af.hover_thrust:.3f} (config), "
        f"T/W {af.thrust_to_weight:g}, thrust_min {af.thrust_min:g}; in-flight hover estimate "
        f"{'on' if cfg.hover.estimate else 'off'}",
        f"camera: {cam_src}, {cfg.camera.width}x{cfg.camera.height} @ {cfg.camera.rate:g} Hz, fx {K[0, 0]:.1f} "
        f"fy {K[1, 1]:.1f} cx {K[0, 2]:.1f} cy {K[1, 2]:.1f}, distortion {dist}, mount roll/pitch/yaw "
        f"{m.roll:g}/{m.pitch:g}/{m.yaw:g} deg",
        f"guidance: k_pn {g.k_pn:g}, gamma_bar {g.gamma_bar:g} deg, v_rel_bar {g.v_rel_bar:g} m/s, fov {g.fov}"
        + (f", FOV bound from the camera pitched up {uptilt:g} deg" if uptilt else ""),
        f"flight: start={app.start}, take-off altitude {app.takeoff_altitude:g} m, on_close={app.on_close}, "
        f"max gates {app.max_gates}",
        "safety: " + ", ".join(f"{k} {v}" for k, v in s.model_dump(mode="json").items()),
        f"link: {cfg.link.url}",
    ]


def _cmd_check(args: argparse.Namespace) -> int:
    from companion.config import load_config

    files = [*args.files, *args.config]
    cfg = load_config(files, args.overrides)  # ConfigError -> one line, exit 2 (companion/cli.py)
    need_detector = not (cfg.app.camera == "synthetic" and cfg.app.synthetic.render == "geometric")
    det = "not needed (geometric synthetic camera)"
    if need_detector and not args.no_detector:
        from companion.app.main import detector_available

        why = detector_available(cfg)
        if why is not None:
            raise ConfigError(f"perception.model: {cfg.perception.model}: detector does not load ({why})")
        det = f"loads ({cfg.perception.model or 'the shipped gate detector'})"
    elif args.no_detector:
        det = "not checked (--no-detector)"
    print(f"config OK: {', '.join(['config/default.yaml', *files])}" + (
        f" + {len(args.overrides)} --set" if args.overrides else ""))
    for line in [*summary_lines(cfg), f"detector: {det}"]:
        print("  " + line)
    return 0

