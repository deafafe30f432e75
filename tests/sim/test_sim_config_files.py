"""config/sim.yaml documents the simulator defaults; every scenario overlay loads."""

from __future__ import annotations

from pathlib import Path

import pytest

from companion.config import load_config
from companion.configbase import ConfigError, read_yaml
from companion.sim.config import SimConfig

CONFIG = Path(__file__).resolve().parents[2] / "config"


def test_sim_yaml_equals_the_schema_defaults():
    data = read_yaml(CONFIG / "sim.yaml")
    assert SimConfig.model_validate(data["sim"]) == SimConfig()


@pytest.mark.parametrize("path", sorted((CONFIG / "scenarios").glob("*.yaml")), ids=lambda p: p.name)
def test_scenario_overlays_load_and_change_something(path):
    cfg = load_config([path], base=CONFIG / "sim.yaml")
    assert cfg.sim != SimConfig()


def test_bad_sim_value_names_file_and_key(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("sim:\n  camera:\n    delay: 3 furlongs\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: sim\.camera\.delay"):
        load_config([bad], base=CONFIG / "sim.yaml")
