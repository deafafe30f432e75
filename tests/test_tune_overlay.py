"""`companion eval tune --overlay`: the tuned values as a config overlay that fly and eval accept."""

from __future__ import annotations

from pathlib import Path

import pytest

from companion.config import load_config
from companion.evaluation.tune import write_tuned_overlay

ROOT = Path(__file__).resolve().parent.parent


def test_overlay_includes_the_vehicle_and_sets_the_tuned_values(tmp_path: Path) -> None:
    out = tmp_path / "tuned" / "sih-d.yaml"
    best = {"k_pn": 1.234, "gamma_bar": 9.876, "reward": 2.5, "success_1m": 0.9, "confirm_reward": 2.4,
            "confirm_success_1m": 0.88}
    write_tuned_overlay(out, best, "d", [str(ROOT / "config/vehicles/sih.yaml")], 0, 25, 5, 2)
    cfg = load_config([out])
    assert cfg.guidance.k_pn == pytest.approx(1.234) and cfg.guidance.gamma_bar == pytest.approx(9.876)
    assert cfg.airframe.name == "sih_quadx" and cfg.sim.quad.drag_lin == pytest.approx(1.0)  # the included vehicle
    text = out.read_text()
    assert "R_d (c_t 0, c_d 5, c 3)" in text and "--config" in text


@pytest.mark.parametrize("path", sorted((ROOT / "config/tuned").glob("*.yaml")), ids=lambda p: p.name)
def test_shipped_tuned_overlays_load(path: Path) -> None:
    profile = path.stem.split("-")[0]  # <profile>-<reward>[-<protocol>]
    cfg = load_config([path])
    vehicle = load_config([ROOT / "config/vehicles" / f"{profile}.yaml"])
    assert cfg.airframe == vehicle.airframe and cfg.sim.quad == vehicle.sim.quad
    assert 0.3 <= cfg.guidance.k_pn <= 3.0 and 5.0 <= cfg.guidance.gamma_bar <= 30.0  # the paper's search space
