"""Studies on a real local Ray cluster (companion/evaluation/cluster.py), bound to 127.0.0.1: the same results
as the local pool for the same seeds. Skipped when Ray (the ``cluster`` extra) is not installed."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

pytest.importorskip("ray")

from companion.cli import main

WALL_KEYS = ("wall_time_s", "cluster", "jobs", "markdown")  # how it ran, not what it found


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# The test cluster lives for seconds on 127.0.0.1: no token (Ray >= 2.5x keeps one in ~/.ray, shared by every
# Ray user of this account; another one overwriting it would fail the test).
ENV = {**os.environ, "RAY_AUTH_MODE": "disabled", "PYTHONPATH": str(Path(__file__).resolve().parents[2])}


@pytest.fixture(scope="module")
def ray_head():
    """``ray start --head`` on 127.0.0.1 in its own process group and temp dir (never ``ray stop``: that would
    stop every Ray on the machine); the group is killed afterwards."""
    port = _free_port()
    tmp = tempfile.mkdtemp(prefix="rayt")  # short: Ray's socket paths must fit 107 characters
    ray_bin = Path(sys.executable).parent / "ray"
    proc = subprocess.Popen(
        [str(ray_bin), "start", "--head", "--block", "--node-ip-address", "127.0.0.1", "--port", str(port),
         "--num-cpus", "2", "--include-dashboard", "false", "--disable-usage-stats", "--temp-dir", tmp,
         # A port Ray would otherwise take fixed (52365): a free one, so two test workers' heads can coexist.
         "--dashboard-agent-listen-port", str(_free_port())],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True, env=ENV)
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                break
        if proc.poll() is not None:
            pytest.fail(f"ray start exited with {proc.returncode}")
        time.sleep(0.5)
    else:
        os.killpg(proc.pid, signal.SIGKILL)
        pytest.fail("the Ray head did not open its port in 90 s")
    yield f"127.0.0.1:{port}"
    os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)


def _strip(res: dict) -> dict:
    return {k: v for k, v in res.items() if k not in WALL_KEYS}


def test_table1_on_ray_equals_the_local_pool(ray_head, tmp_path):
    local, ray_out = tmp_path / "local", tmp_path / "ray"
    common = ["eval", "table1", "--runs", "4", "--seed", "0", "--no-plots", "--no-progress"]
    assert main([*common, "--jobs", "1", "--out", str(local)]) == 0
    # The CLI in a process of its own, as a user runs it: a fresh driver connecting to the cluster's address.
    r = subprocess.run([sys.executable, "-m", "companion.cli", *common, "--out", str(ray_out),
                        "--cluster", ray_head], env=ENV, capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stderr[-2000:]
    a = json.loads((local / "results.json").read_text())
    b = json.loads((ray_out / "results.json").read_text())
    assert b["cluster"] == ray_head
    assert len(a["runs"]) == 5 and a["runs"] == b["runs"]  # 4 runs over 5 motions: one each
    assert _strip(a) == _strip(b)
    assert main(["eval", "compare", str(local / "results.json"), str(ray_out / "results.json")]) == 0


def test_tune_on_ray_equals_the_local_tune(ray_head, monkeypatch):
    from companion.config import Config
    from companion.evaluation.tune import tune

    monkeypatch.setenv("PYTHONPATH", ENV["PYTHONPATH"])
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    kw = {"iterations": 1, "init_points": 2, "runs_per_motion": 1, "seed": 5, "n_jobs": 1, "progress": False,
          "confirm_top": 1, "confirm_runs": 1}
    try:
        a = tune(Config(), **kw)
        b = tune(Config(), **kw, cluster=ray_head)
    finally:
        import ray

        ray.shutdown()
    assert json.dumps(a["history"]) == json.dumps(b["history"])
    assert a["best"] == b["best"]


def test_unreachable_cluster_is_a_one_line_error(capsys):
    port = _free_port()  # nothing listens there
    rc = main(["eval", "table1", "--runs", "1", "--no-plots", "--no-progress", "--jobs", "1",
               "--cluster", f"127.0.0.1:{port}", "--out", tempfile.mkdtemp(prefix="rayt")])
    assert rc == 2
    err = capsys.readouterr().err
    assert f"--cluster 127.0.0.1:{port}" in err and len(err.strip().splitlines()) == 1
