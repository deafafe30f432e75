"""Config loading: every bad input is refused with one line naming the file, key and value."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest

from companion.config import Config, load_config
from companion.configbase import ConfigError


def overlay(tmp_path: Path, text: str, name: str = "overlay.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_default_config_has_the_papers_values() -> None:
    cfg = load_config()
    assert cfg.guidance.k_pn == 2.10
    assert cfg.guidance.gamma_bar == pytest.approx(21.05)
    assert cfg.guidance.v_rel_bar == 15.0
    assert cfg.airframe.mass == 2.0
    assert cfg.camera.half_fov == 33.5 and (cfg.camera.width, cfg.camera.height) == (640, 480)
    assert cfg.camera.rate == 30.0


def test_units_are_converted(tmp_path) -> None:
    p = overlay(tmp_path, "guidance:\n  gamma_bar: 0.2 rad\n  v_rel_bar: 54 km/h\nlos_filter:\n  max_dt: 250 ms\n")
    cfg = load_config([p])
    assert cfg.guidance.gamma_bar == pytest.approx(math.degrees(0.2))
    assert cfg.guidance.v_rel_bar == pytest.approx(15.0)
    assert cfg.los_filter.max_dt == pytest.approx(0.25)


@pytest.mark.parametrize(
    ("text", "key", "fragment"),
    [
        ("guidance:\n  k_nav: 3\n", "guidance.k_nav", "unknown key"),
        ("guidanse:\n  k_pn: 3\n", "guidanse", "unknown key"),
        ("guidance:\n  k_pn: fast\n", "guidance.k_pn", "'fast'"),
        ("guidance:\n  gamma_bar: 21 m/s\n", "guidance.gamma_bar", "not a unit of angle"),
        ("guidance:\n  gamma_bar: 95 deg\n", "guidance.gamma_bar", "less than 89"),
        ("airframe:\n  hover_thrust: 1.5\n", "airframe.hover_thrust", "1.5"),
        ("camera:\n  width: 64.5\n", "camera.width", "64.5"),
        ("camera:\n  distortion: [0.1, 0.2]\n", "camera", "distortion"),
        ("los_filter:\n  cutoff: .nan\n", "los_filter.cutoff", "finite"),
        ("airframe:\n  mass: true\n", "airframe.mass", "boolean"),
    ],
)
def test_bad_values_give_one_line_naming_file_key_value(tmp_path, text, key, fragment) -> None:
    p = overlay(tmp_path, text)
    with pytest.raises(ConfigError) as e:
        load_config([p])
    msg = str(e.value)
    assert "\n" not in msg
    assert msg.startswith(str(p)) and key in msg and fragment in msg


def test_yaml_syntax_error_names_file_and_line(tmp_path) -> None:
    p = overlay(tmp_path, "guidance:\n  k_pn: [1, 2\n")
    with pytest.raises(ConfigError, match=r"overlay.yaml: not valid YAML at line \d"):
        load_config([p])


def test_missing_file_and_include_loop(tmp_path) -> None:
    with pytest.raises(ConfigError, match="cannot read config file"):
        load_config([tmp_path / "nope.yaml"])
    a = overlay(tmp_path, "include: [b.yaml]\n", "a.yaml")
    overlay(tmp_path, "include: [a.yaml]\n", "b.yaml")
    with pytest.raises(ConfigError, match="include loop"):
        load_config([a])


def test_overrides_and_their_errors() -> None:
    cfg = load_config(overrides=["guidance.k_pn=2.5", "guidance.gamma_bar=10 deg"])
    assert cfg.guidance.k_pn == 2.5 and cfg.guidance.gamma_bar == 10.0
    with pytest.raises(ConfigError, match=r"^--set guidance.k_pn=-1: guidance.k_pn: .*-1"):
        load_config(overrides=["guidance.k_pn=-1"])
    with pytest.raises(ConfigError, match=r"expected section\.key=value"):
        load_config(overrides=["guidance.k_pn"])


def test_later_files_win_key_by_key(tmp_path) -> None:
    a = overlay(tmp_path, "guidance:\n  k_pn: 1.0\n  v_rel_bar: 20\n", "a.yaml")
    b = overlay(tmp_path, "guidance:\n  k_pn: 3.0\n", "b.yaml")
    cfg = load_config([a, b])
    assert cfg.guidance.k_pn == 3.0 and cfg.guidance.v_rel_bar == 20.0


def test_cross_check_camera_tilt_against_gamma_bar(tmp_path) -> None:
    # A tilt the solver does not model exactly (the paper's FOV bound, or a mount with roll/yaw) is
    # subtracted from gamma_bar: 25 deg off body x cannot be kept within 21.05 deg.
    p = overlay(tmp_path, "camera:\n  mount:\n    pitch: 25 deg\nguidance:\n  fov: paper\n")
    with pytest.raises(ConfigError, match="gamma_bar"):
        load_config([p])
    p = overlay(tmp_path, "camera:\n  mount:\n    pitch: 25 deg\n    roll: 2 deg\n", "b.yaml")
    with pytest.raises(ConfigError, match="gamma_bar"):
        load_config([p])
    # A pure pitch with the exact bound is part of the solver (tests/test_guidance_uptilt.py).
    p = overlay(tmp_path, "camera:\n  mount:\n    pitch: 25 deg\n", "c.yaml")
    assert load_config([p]).camera.mount.pitch == 25.0


def test_config_is_immutable() -> None:
    cfg = Config()
    with pytest.raises(Exception):  # noqa: B017 (pydantic's frozen-instance error)
        cfg.guidance.k_pn = 3.0  # type: ignore[misc]


def test_cli_prints_one_line_and_exits_2(tmp_path) -> None:
    p = overlay(tmp_path, "guidance:\n  k_pn: fast\n")
    r = subprocess.run([sys.executable, "-m", "companion.cli", "bench", "--config", str(p), "--quick"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "guidance.k_pn" in lines[0] and str(p) in lines[0]
