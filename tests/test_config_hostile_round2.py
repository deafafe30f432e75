"""Config and command-line findings of issue 22: a model path that is a FIFO, device or folder named as
such; terminal escapes in --set never echoed raw; outgoing links off this machine under the same rule as
listening ones; one lock per serial device however its path is spelled."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from companion.app.vehiclelock import VehicleBusy, VehicleLock, lock_name
from companion.config import load_config
from companion.configbase import ConfigError

pytestmark = pytest.mark.timeout(120)


def _check(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "companion.cli", "check", *args], capture_output=True, text=True,
                          timeout=100)


@pytest.mark.parametrize(("make", "what"), [
    (lambda p: os.mkfifo(p), "a FIFO (named pipe), not a model file"),
    (lambda p: p.mkdir(), "a folder, not a model file"),
    (None, "a character device, not a model file"),
])
def test_a_model_path_that_is_not_a_file_is_named(tmp_path, make, what):
    path = tmp_path / "model.onnx"
    if make is None:
        path = "/dev/zero"
    else:
        make(path)
    res = _check("--set", f"perception.model={path}")
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1
    assert what in res.stderr and "not found" not in res.stderr, res.stderr


def test_terminal_escapes_in_set_are_escaped(tmp_path):
    for override in ("camera.fx=\x1b[31mred", "came\x1b[2Jra.fx=1", "camera.fx=1\x9b2J"):
        res = _check("--set", override)
        assert res.returncode == 2, res.stderr
        assert "\x1b" not in res.stderr and "\x9b" not in res.stderr, repr(res.stderr)
        assert "\\x1b" in res.stderr or "\\x9b" in res.stderr
        assert len(res.stderr.strip().splitlines()) == 1
    # A value that is accepted and then shown (check's summary) is escaped too.
    res = _check("--no-detector", "--set", "perception.source=\x1b[31mcam")
    assert res.returncode == 0 and "\x1b" not in res.stdout and "\\x1b[31mcam" in res.stdout


def test_outgoing_link_off_this_machine_needs_the_same_permission():
    with pytest.raises(ConfigError, match=r"connects to 203\.0\.113\.5, off this machine"):
        load_config([], ["link.url=tcpout://203.0.113.5:5760"])
    for host in ("127.0.0.1", "localhost", "[::1]", "127.0.0.2"):
        assert load_config([], [f"link.url=tcpout://{host}:5760"]).link.url.startswith("tcpout://")
    cfg = load_config([], ["link.url=tcpout://203.0.113.5:5760", "link.allow_all_interfaces=true"])
    assert cfg.link.url == "tcpout://203.0.113.5:5760"


def test_one_lock_per_serial_device_however_it_is_reached(tmp_path):
    # /dev/null stands in for a serial device (a character device every machine has).
    (tmp_path / "by-id").mkdir()
    (tmp_path / "by-id" / "usb-PX4_FMU").symlink_to("/dev/null")
    names = {lock_name("serial:///dev/null:57600"), lock_name(f"serial://{tmp_path}/by-id/usb-PX4_FMU:921600"),
             lock_name("serial:///dev/../dev/null:57600")}
    assert len(names) == 1, names
    assert lock_name("serial:///dev/zero:57600") not in names  # another device, another lock
    with VehicleLock("serial:///dev/null:57600", tmp_path), pytest.raises(VehicleBusy, match="another companion app"):
        VehicleLock(f"serial://{tmp_path}/by-id/usb-PX4_FMU:921600", tmp_path).acquire()


def test_an_absurd_distortion_is_refused_where_the_camera_is_loaded(tmp_path):
    cam = tmp_path / "camera.yaml"
    cam.write_text("camera:\n  distortion: [50, -3000, .5, .5, 1e6]\n")
    res = _check("--no-detector", "--config", str(cam))
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1
    assert "camera: distortion" in res.stderr and "not a real lens" in res.stderr, res.stderr
    cam.write_text("camera:\n  distortion: [50, -3000, 0, 0, 1e6]\n")  # the radial part alone: squeezes the view
    with pytest.raises(ConfigError, match="implausible: the distortion moves pixels"):
        load_config([cam])
    cam.write_text("camera:\n  distortion: [-0.15, 0.04, 0.001, -0.0008, 0.0]\n")  # a real webcam lens
    assert load_config([cam]).camera.distortion[0] == -0.15
