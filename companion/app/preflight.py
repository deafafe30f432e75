"""The pre-flight summary and the operator's confirmation, between the pre-flight checks and arming.

What the operator confirms (printed, logged as events and written to ``preflight.json`` in the flight
folder): the link, the autopilot's version, mode, armed / armable state, PX4's failsafe settings (what
happens if this app dies), the hover thrust in use and where it came from, the camera's measured frame
rate, the detector's status on those frames, the PN parameters, the flight envelope and the safety
limits. Its config part (``summary_lines``) is also what ``companion check`` prints.

Confirmation: ``companion fly`` asks on stdin ("yes" to arm) unless ``--yes``. Anything else, an
end of input, or no answer within ``CONFIRM_TIMEOUT`` is a named ground abort (``ABORT_NOT_ARMED``,
reason ``NOT_CONFIRMED``): nothing was armed. Non-interactive callers never ask: ``companion sim``
and the tests call ``fly()`` without a confirmation function (an explicit yes: they own the simulated
vehicle), and the service runs with ``app.start=pilot`` where the app never arms (the pilot does), so
the summary is printed and logged and the flight goes on.
"""

from __future__ import annotations

import asyncio
import json
import math
import sys
import time
from collections.abc import Awaitable, Callable
from typing import Any

import numpy as np

from companion.config import Config, camera_uptilt

Confirm = Callable[[str], Awaitable[bool]]
CONFIRM_TIMEOUT = 120.0  # s the operator has to answer
FRAME_SAMPLE_S = 1.0  # s of camera frames measured before arming


async def gather(app: Any) -> dict[str, Any]:
    """Everything the summary shows, read now (best effort: a value that cannot be read says so)."""
    cfg, link = app.cfg, app.link
    out: dict[str, Any] = {
        "link": {"url": cfg.link.url, "ok": bool(link.link_ok), "telemetry_age_s": round(link.telemetry_age, 3)},
        "autopilot_version": await _version(link),
        "mode": link.flight_mode, "armed": link.armed, "landed_state": link.landed_state,
        "armable": _armable(link),
        "failsafe": await _failsafe(app),
        "hover_thrust": _hover(app),
        "px4_params": await _px4_params(app),
        "camera": await _camera(app),
        "pn": {"k_pn": cfg.guidance.k_pn, "gamma_bar_deg": cfg.guidance.gamma_bar,
               "v_rel_bar_mps": cfg.guidance.v_rel_bar, "fov": cfg.guidance.fov,
               "los_cutoff_hz": cfg.los_filter.cutoff, "rate_cutoff_hz": cfg.los_filter.rate_cutoff},
        "envelope": _envelope(app),
        "safety": cfg.safety.model_dump(mode="json"),
        "static": summary_lines(cfg),
    }
    return out


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


def _hover(app: Any) -> dict[str, Any]:
    """The hover thrust in use, the configured and the autopilot's, and a mismatch line when they differ."""
    from companion.hover import hover_mismatch

    cfg, value = app.cfg, app.ctrl.p.hover_thrust
    # The app flies PX4's MPC_THR_HOVER when it read a plausible one (flight.py), so that is the value in use.
    px4 = value if getattr(app.link, "hover_thrust_source", "config") == "autopilot" else None
    return {"value": value, "source": _hover_source(app), "in_flight_estimate": bool(cfg.hover.estimate),
            "configured": cfg.airframe.hover_thrust, "autopilot": px4,
            "mismatch": hover_mismatch(cfg.airframe.hover_thrust, px4, value, bool(cfg.hover.estimate))}


async def _px4_params(app: Any) -> dict[str, Any]:
    """PX4's parameters that decide the flight beside the hover thrust (companion/vehiclematch.py PARAM_PAIRS),
    and one line for each that disagrees with the airframe."""
    from companion.vehiclematch import PARAM_PAIRS, param_mismatches

    values: dict[str, float | None] = {}
    reader = getattr(app.link, "read_param", None)
    for name in PARAM_PAIRS:
        try:
            values[name] = None if reader is None else float(await reader(name, 2.0))
        except Exception:  # (not answered, or not a PX4 parameter here): not compared
            values[name] = None
    return {"values": values, "mismatches": param_mismatches(values, app.cfg.airframe)}


def _hover_source(app: Any) -> str:
    src = getattr(app.link, "hover_thrust_source", "config")
    return "PX4 MPC_THR_HOVER" if src == "autopilot" else "config airframe.hover_thrust"


def _armable(link: Any) -> dict[str, Any]:
    h = link.health
    if h is None:
        return {"armable": None, "problems": ["no health report"]}
    checks = {"gyro calibration": "is_gyrometer_calibration_ok", "accelerometer calibration":
              "is_accelerometer_calibration_ok", "magnetometer calibration": "is_magnetometer_calibration_ok",
              "local position": "is_local_position_ok", "global position": "is_global_position_ok",
              "home position": "is_home_position_ok", "armable": "is_armable"}
    problems = [k for k, attr in checks.items() if getattr(h, attr, True) is False]
    return {"armable": bool(getattr(h, "is_armable", False)), "problems": problems}


async def _version(link: Any) -> str:
    system = getattr(link, "_system", None)  # the link keeps the mavsdk System; the Info plugin reads it
    if system is None:
        return "unknown (not connected)"
    try:
        from mavsdk.asyncio.plugins.info import InfoAsync

        v = await asyncio.wait_for(InfoAsync(system).get_version(), 3.0)
        sw = f"{v.flight_sw_major}.{v.flight_sw_minor}.{v.flight_sw_patch}"
        git = str(getattr(v, "flight_sw_git_hash", "") or "")[:8]
        return f"flight software {sw}" + (f" ({git})" if git else "")
    except Exception as e:  # (an autopilot that does not answer AUTOPILOT_VERSION)
        return f"unknown ({type(e).__name__}: {e})"[:120]


async def _failsafe(app: Any) -> dict[str, Any]:
    """PX4's failsafe parameters: the link's reader and judge when they exist, else the two that matter."""
    link, cfg = app.link, app.cfg
    reader = getattr(link, "failsafe_params", None)
    if reader is not None:
        values = await reader(2.0)
        try:
            from companion.app.failsafe import judge

            line, problems = judge(values, getattr(cfg.safety, "max_offboard_loss_time", 2.0))
            return {"values": values, "report": line, "problems": problems}
        except ImportError:
            return {"values": values}
    values: dict[str, float | None] = {}
    read_int = getattr(link, "read_param_int", None)
    for name, reader in (("COM_OF_LOSS_T", link.read_param), ("COM_OBL_RC_ACT", read_int)):
        try:
            values[name] = None if reader is None else float(await reader(name, 2.0))
        except Exception:
            values[name] = None
    return {"values": values}


async def _camera(app: Any) -> dict[str, Any]:
    """Measured frame rate and the detector on those frames (a real camera); the synthetic camera is
    not sampled: its first frame anchors the virtual gates, which must happen in the air."""
    cfg = app.cfg
    if cfg.app.camera == "synthetic":
        render = cfg.app.synthetic.render
        return {"source": f"synthetic ({render})", "rate_hz": None, "configured_rate_hz": cfg.camera.rate,
                "detector": ("geometric box, no detector" if render == "geometric"
                             else "detector pipeline on rendered frames"),
                "note": "not sampled before take-off (the first frame anchors the virtual gates)"}
    times: list[float] = []
    ms: list[float] = []
    boxes = 0
    t_end = time.monotonic() + FRAME_SAMPLE_S
    try:
        while time.monotonic() < t_end or len(times) < 3:
            frame = await asyncio.wait_for(app.camera.read(), 2.0)
            times.append(frame.t)
            t0 = time.perf_counter()
            box = await asyncio.get_running_loop().run_in_executor(None, app.perception.process, frame)
            ms.append((time.perf_counter() - t0) * 1e3)
            boxes += box is not None
            if len(times) > 200:
                break
    except Exception as e:
        return {"source": cfg.perception.source, "rate_hz": None, "error": f"{type(e).__name__}: {e}"}
    reset = getattr(app.perception, "reset", None)
    if reset is not None:
        reset()  # the tracker starts fresh in the air
    span = times[-1] - times[0] if len(times) > 1 else 0.0
    rate = (len(times) - 1) / span if span > 0 else None
    return {"source": cfg.perception.source, "rate_hz": rate, "configured_rate_hz": cfg.camera.rate,
            "frames": len(times), "detector_ms_p50": float(np.median(ms)) if ms else None,
            "detector": f"{_model_name(cfg)} ran on {len(times)} frames, gate boxes in {boxes}"}


def _model_name(cfg: Config) -> str:
    from companion.app.assemble import real_frames
    from perception.detector import model_path

    return model_path(cfg.perception, real_frames(cfg)).name


def _envelope(app: Any) -> dict[str, Any]:
    cfg, p = app.cfg, app.ctrl.p
    g = 9.81
    f_max, f_min = p.guidance.f_max, p.guidance.f_min
    return {"thrust_normalised": [p.thrust_min, min(1.0, p.hover_thrust * f_max / g)],
            "accel_mps2": [round(f_min, 2), round(f_max, 2)],
            "max_sideways_accel_mps2": round(math.sqrt(max(f_max**2 - g**2, 0.0)), 2),
            "takeoff_altitude_m": cfg.app.takeoff_altitude, "start": cfg.app.start, "on_close": cfg.app.on_close,
            "max_gates": cfg.app.max_gates, "setpoint_rate_hz": cfg.link.setpoint_rate}


def format_summary(s: dict[str, Any]) -> str:
    def v(x: Any, f: str = ".1f") -> str:
        return "?" if x is None else format(x, f) if isinstance(x, float) else str(x)

    arm = s["armable"]
    fs = s["failsafe"]
    cam = s["camera"]
    hv = s["hover_thrust"]
    env = s["envelope"]
    lines = [
        "==================== PRE-FLIGHT SUMMARY ====================",
        f"link          {s['link']['url']}  ({'OK' if s['link']['ok'] else 'NOT OK'}, telemetry "
        f"{s['link']['telemetry_age_s']:.2f} s old)",
        f"autopilot     {s['autopilot_version']}",
        f"vehicle       mode {s['mode']}, armed {s['armed']}, {s['landed_state']}, armable {arm['armable']}"
        + (f" (problems: {', '.join(arm['problems'])})" if arm["problems"] else ""),
        "failsafe      " + (fs.get("report") or ", ".join(f"{k} {v(x, 'g')}" for k, x in fs["values"].items())),
    ]
    for p in fs.get("problems", []):
        lines.append(f"  WARNING     {p}")
    lines += [
        f"hover thrust  {hv['value']:.3f} from {hv['source']}; in-flight estimate "
        f"{'ON (hover.estimate)' if hv['in_flight_estimate'] else 'off'}; config {hv['configured']:.3f}, PX4 "
        f"{v(hv.get('autopilot'), '.3f')}",
    ]
    if hv.get("mismatch"):
        lines.append(f"  WARNING     {hv['mismatch']}")
    for m in s.get("px4_params", {}).get("mismatches", []):
        lines.append(f"params        {m}")
    lines += [
        f"camera        {cam['source']}: measured {v(cam.get('rate_hz'))} Hz (configured "
        f"{v(cam.get('configured_rate_hz'))} Hz)" + (f"; {cam['note']}" if cam.get("note") else "")
        + (f"; ERROR {cam['error']}" if cam.get("error") else ""),
        f"detector      {cam.get('detector', '-')}" + (f", {cam['detector_ms_p50']:.1f} ms per frame"
                                                       if cam.get("detector_ms_p50") is not None else ""),
        f"PN            k_pn {s['pn']['k_pn']:g}, gamma_bar {s['pn']['gamma_bar_deg']:g} deg, v_rel_bar "
        f"{s['pn']['v_rel_bar_mps']:g} m/s, fov {s['pn']['fov']}, LOS filter {s['pn']['los_cutoff_hz']:g} Hz",
        f"envelope      thrust {env['thrust_normalised'][0]:.2f}..{env['thrust_normalised'][1]:.2f}, accel "
        f"{env['accel_mps2'][0]}..{env['accel_mps2'][1]} m/s^2 (sideways <= {env['max_sideways_accel_mps2']}), "
        f"start={env['start']}, take-off {env['takeoff_altitude_m']:g} m, on_close={env['on_close']}, "
        f"max gates {env['max_gates']}",
        "safety        " + ", ".join(f"{k} {x}" for k, x in s["safety"].items()),
        "============================================================",
    ]
    return "\n".join(lines)


async def stdin_confirm(text: str) -> bool:
    """Ask on the terminal; True only for 'yes'. No answer within CONFIRM_TIMEOUT or end of input: False."""
    print(text, file=sys.stderr)
    print("Type 'yes' and Enter to arm and take off (anything else aborts on the ground): ", end="",
          file=sys.stderr, flush=True)
    loop = asyncio.get_running_loop()
    try:
        line = await asyncio.wait_for(loop.run_in_executor(None, sys.stdin.readline), CONFIRM_TIMEOUT)
    except TimeoutError:
        return False
    return line.strip().lower() == "yes"


async def run(app: Any, confirm: Confirm | None) -> str | None:
    """Summary, log, confirmation. Returns None to go on, or the reason the operator did not confirm."""
    s = await gather(app)
    text = format_summary(s)
    app.log.write_json("preflight.json", json.loads(json.dumps(s, default=str)))  # never raises (a full disk)
    report = getattr(app, "vehicle_report", None)
    if report is not None:  # summary.json "hover": what pre-flight compared
        report["preflight"] = {"hover_thrust": s["hover_thrust"], "px4_params": s["px4_params"]}
    for line in text.splitlines()[1:-1]:
        app.log.event("preflight: " + " ".join(line.split()))
    will_arm = app.cfg.app.start == "takeoff"
    cam_error = s["camera"].get("error")
    if cam_error:
        # A camera that fails on the ground fails in the air: never arm (or engage) on it (issue #22: wrong-size
        # frames showed ERROR here and the app still armed and climbed to 10 m).
        from companion.app.camera import CameraFailed

        if app.stderr is not None:
            print(text, file=app.stderr, flush=True)
        app.log.event(f"preflight: camera ERROR, refusing to arm: {cam_error}", "error")
        raise CameraFailed(f"pre-flight: camera {app.cfg.perception.source}: {cam_error}: refusing to arm")
    if confirm is None or not will_arm:
        if app.stderr is not None:
            print(text, file=app.stderr, flush=True)
        why = ("the pilot arms (app.start=pilot)" if not will_arm else "non-interactive (--yes)")
        app.log.event(f"preflight: confirmed: {why}")
        return None
    ok = await confirm(text)
    if not ok:
        app.log.event("preflight: NOT confirmed by the operator", "warn")
        return "the operator did not confirm the pre-flight summary"
    app.log.event("preflight: confirmed by the operator")
    return None
