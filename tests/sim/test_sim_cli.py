"""``companion sim --in-process``: one run, printed result, plot and JSON."""

from __future__ import annotations

import json

import pytest

from companion.cli import main


def test_sim_in_process_writes_plot_and_json(tmp_path, capsys):
    png, js = tmp_path / "run.png", tmp_path / "run.json"
    rc = main(["sim", "--in-process", "--motion", "knot", "--seed", "2", "--plot", str(png), "--json", str(js),
               "--set", "sim.camera.pixel_noise=0"])
    assert rc == 0
    res = json.loads(js.read_text())
    assert res["motion"] == "knot" and res["seed"] == 2 and set(res["success"]) == {"0.5", "1.0", "2.0"}
    out = capsys.readouterr().out
    assert ("crossed the gate plane" in out) == res["crossed"]
    assert png.stat().st_size > 20_000


def test_sim_bad_motion_is_rejected_by_the_parser(capsys):
    with pytest.raises(SystemExit) as e:
        main(["sim", "--in-process", "--motion", "spiral"])
    assert e.value.code == 2
    assert "invalid choice: 'spiral'" in capsys.readouterr().err
