"""Hostile config input through the real CLI: each probe is refused with exit 2 and ONE line on stderr
naming the source (file or --set) and the key, quickly, and nothing is created or lost.

The probes run `companion fly` (config errors must stop it before it logs, connects or arms) or
`companion bench` (a command that would finish in a second if a probe were wrongly accepted).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.timeout(120)

# Generous: a refused config takes well under a second; this only guards against a hang on a slow machine.
TIMEOUT = 20.0


def run_cli(args: list[str], cwd: Path) -> tuple[subprocess.CompletedProcess[str], float]:
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "companion.cli", *args], cwd=cwd, capture_output=True, text=True,
                       timeout=TIMEOUT, env={**os.environ, "PYTHONWARNINGS": "ignore"})
    return r, time.monotonic() - t0


def one_line(r: subprocess.CompletedProcess[str]) -> str:
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr[-2000:]
    assert len(lines[0]) < 300, lines[0][:400]
    return lines[0]


def alias_bomb() -> str:
    """The billion-laughs shape: 9 levels of 9 aliases = 9^9 (387 million) strings once expanded."""
    lines = ['l0: &l0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for i in range(1, 10):
        lines.append(f"l{i}: &l{i} [" + ",".join([f"*l{i - 1}"] * 9) + "]")
    return "\n".join(lines) + "\nguidance:\n  k_pn: *l9\n"


FILE_PROBES = [
    # (name, file content as bytes, fragment of the one line)
    ("alias_bomb", alias_bomb().encode(), "YAML aliases (*l0) are not allowed"),
    ("binary", b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", "binary file (NUL bytes)"),
    ("latin1", "guidance:\n  k_pn: 2.1 # r\xe9glage\n".encode("latin-1"), "not UTF-8 text (byte 0xe9"),
    ("deep_nesting", ("[" * 100_000 + "]" * 100_000).encode(), "nested deeper than"),
    ("deep_mapping", ("a:\n" + "".join(" " * i + "b:\n" for i in range(1, 200))).encode(), "nested deeper than"),
    ("k_pn_true", b"guidance:\n  k_pn: true\n", "guidance.k_pn: expected a value of this key's type, got a boolean"),
    ("duplicate_key", b"guidance:\n  k_pn: 2.0\n  k_pn: 6.0\n", "line 3: duplicate key 'k_pn'"),
    ("duplicate_section", b"guidance:\n  k_pn: 2.0\nguidance:\n  v_rel_bar: 9\n", "duplicate key 'guidance'"),
    ("fx_inf", b"camera:\n  fx: .inf\n", "camera.fx: must be finite"),
    ("cx_nan", b"camera:\n  cx: .nan\n", "camera.cx: must be finite"),
    ("wind_nan", b"sim:\n  wind:\n    mean: [.nan, 0, 0]\n", "sim.wind.mean.0: must be finite"),
    ("gate_radii", b"sim:\n  scenario:\n    gate_radii: [-1, 1.0]\n", "sim.scenario.gate_radii.0"),
    ("gate_radii_nan", b"sim:\n  scenario:\n    gate_radii: [1.0, .nan]\n", "must be finite"),
    ("inf_spelled", b"guidance:\n  k_pn: '1e999'\n", "guidance.k_pn: must be finite"),
    ("nan_string", b"guidance:\n  k_pn: nan\n", "guidance.k_pn: expected a number"),
    ("cx_outside", b"camera:\n  cx: 5000\n", "cx 5000.0 lies outside the image"),
]


@pytest.mark.parametrize(("name", "content", "fragment"), FILE_PROBES, ids=[p[0] for p in FILE_PROBES])
def test_hostile_config_file_is_refused_with_one_line(tmp_path: Path, name: str, content: bytes,
                                                      fragment: str) -> None:
    p = tmp_path / f"{name}.yaml"
    p.write_bytes(content)
    r, _ = run_cli(["fly", "--config", str(p), "--log-dir", str(tmp_path / "flights")], tmp_path)
    line = one_line(r)
    assert r.returncode == 2, line
    assert line.startswith("companion: config error: ") and f"{name}.yaml" in line and fragment in line, line
    assert not (tmp_path / "flights").exists()  # refused before the flight log (or anything else) began
    assert p.read_bytes() == content  # the file is read, never touched


def test_alias_bomb_is_refused_fast(tmp_path: Path) -> None:
    """Exit 2, no hang (this used to run out of memory after 154 s). The time is measured, not asserted
    tightly: the subprocess timeout (20 s) is the only limit, so a slow machine cannot fail it."""
    p = tmp_path / "bomb.yaml"
    p.write_text(alias_bomb())
    r, dt = run_cli(["bench", "--quick", "--only", "controller_step_us", "--config", str(p)], tmp_path)
    assert r.returncode == 2 and "YAML aliases" in one_line(r)
    print(f"alias bomb refused in {dt:.2f} s (process start included)")


@pytest.mark.parametrize(
    ("override", "fragment"),
    [
        ("guidance.k_pn=yes", "--set guidance.k_pn=yes: guidance.k_pn: expected a value of this key's type, got a "
                              "boolean"),
        ("guidance.k_pn=[&a [1, 1], *a, *a]", "YAML aliases (*a) are not allowed"),
        ("camera.fx=.inf", "--set camera.fx=.inf: camera.fx: must be finite"),
        ("camera.cx=.nan", "camera.cx: must be finite"),
        ("sim.wind.mean=[.nan, 0, 0]", "sim.wind.mean.0: must be finite"),
        ("safety.loop_stall_timeout=20ms", "safety.loop_stall_timeout: Input should be greater than or equal to 0.5"),
        ("safety.perception_stall_timeout=2", "must exceed the link's loop guard"),
        ("a" + ".a" * 100 + "=1", "nested deeper than"),
        ("guidance.k_pn=" + "[" * 5000 + "]" * 5000, "too long"),
    ],
)
def test_hostile_set_is_refused_with_one_line(tmp_path: Path, override: str, fragment: str) -> None:
    r, _ = run_cli(["fly", "--set", override, "--log-dir", str(tmp_path / "flights")], tmp_path)
    line = one_line(r)
    assert r.returncode == 2 and fragment in line, line
    assert not (tmp_path / "flights").exists()


def test_dev_zero_and_other_non_files_are_refused(tmp_path: Path) -> None:
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)  # nobody ever writes: reading it would block forever
    for path in ("/dev/zero", str(fifo), str(tmp_path)):
        r, _ = run_cli(["fly", "--config", path], tmp_path)
        line = one_line(r)
        assert r.returncode == 2 and f"{path}: not a regular file" in line, line


def test_huge_config_file_is_refused_unread(tmp_path: Path) -> None:
    p = tmp_path / "huge.yaml"
    with open(p, "wb") as f:
        f.truncate(3 << 30)  # 3 GB sparse file: reading it would take the memory, not the size check
    r, _ = run_cli(["fly", "--config", str(p)], tmp_path)
    assert r.returncode == 2 and "too large for a config file" in one_line(r)


def test_cross_section_error_is_short_and_blames_the_set_value(tmp_path: Path) -> None:
    """The camera tilt is valid alone and gamma_bar is valid alone: the error names the --set that broke it.

    A camera turned sideways (yaw) eats into gamma_bar (a pure pitch is an uptilt the solver keeps exactly)."""
    p = tmp_path / "ok.yaml"
    p.write_text("camera:\n  mount:\n    yaw: 15 deg\n")  # valid with the default gamma_bar 21 deg
    r, _ = run_cli(["fly", "--config", str(p), "--set", "guidance.gamma_bar=10 deg"], tmp_path)
    line = one_line(r)
    assert r.returncode == 2
    assert line.startswith("companion: config error: --set guidance.gamma_bar=10 deg: camera.mount tilts"), line
    assert "default.yaml" not in line and "ok.yaml" not in line
    # A file that breaks the defaults alone is the one named.
    p.write_text("camera:\n  mount:\n    yaw: 25 deg\n")
    r, _ = run_cli(["fly", "--config", str(p)], tmp_path)
    line = one_line(r)
    assert r.returncode == 2 and line.startswith(f"companion: config error: {p}: camera.mount tilts"), line


def test_replay_refuses_nan_intrinsics_at_config_load(tmp_path: Path) -> None:
    p = tmp_path / "cam.yaml"
    p.write_text("camera:\n  cx: .nan\n")
    r, _ = run_cli(["replay", str(tmp_path / "video.mp4"), "--config", str(p)], tmp_path)
    line = one_line(r)
    assert r.returncode == 2 and "camera.cx: must be finite" in line, line  # before the video is even looked at


def _video(path: Path) -> Path:
    import cv2
    import numpy as np

    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (640, 480))
    for i in range(3):
        w.write(np.full((480, 640, 3), 40 * i, np.uint8))
    w.release()
    return path


def test_replay_unwritable_out_and_binary_log(tmp_path: Path) -> None:
    video = _video(tmp_path / "v.avi")
    r, _ = run_cli(["replay", str(video), "--out", "/dev/null/x", "--quiet"], tmp_path)
    line = one_line(r)
    assert r.returncode == 2 and line == "companion replay: /dev/null/x: Not a directory", line
    log = tmp_path / "log.csv"
    log.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\xff\xfe")
    r, _ = run_cli(["replay", str(video), "--log", str(log), "--out", str(tmp_path / "o"), "--quiet"], tmp_path)
    line = one_line(r)
    assert r.returncode == 2 and f"{log}: not a text flight log" in line, line
    assert video.stat().st_size > 0  # the input is untouched


def test_bench_only_unknown_section(tmp_path: Path) -> None:
    r, _ = run_cli(["bench", "--only", "bogus"], tmp_path)
    line = one_line(r)
    assert r.returncode == 2 and "--only bogus: no such section" in line and "controller_step_us" in line, line
