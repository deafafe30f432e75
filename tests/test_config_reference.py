"""docs/config-reference.md is generated from the config schema; it must match what the generator writes now."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TOOL = REPO / "tools" / "config_reference.py"
COMMITTED = REPO / "docs" / "config-reference.md"


def test_config_reference_is_up_to_date(tmp_path: Path) -> None:
    out = tmp_path / "config-reference.md"
    env = {k: v for k, v in os.environ.items() if k != "COMPANION_CONFIG_DIR"}  # the repository's config/
    subprocess.run([sys.executable, str(TOOL), "--out", str(out)], check=True, cwd=REPO, env=env,
                   capture_output=True, text=True, timeout=120)
    assert out.read_text(encoding="utf-8") == COMMITTED.read_text(encoding="utf-8"), (
        "docs/config-reference.md is stale: run `.venv/bin/python tools/config_reference.py` and commit it"
    )


def test_every_config_key_has_a_row() -> None:
    from companion.config import Config

    def leaves(model: type, prefix: str) -> list[str]:
        out = []
        for name, field in model.model_fields.items():
            dotted = f"{prefix}.{name}"
            sub = field.annotation
            out += leaves(sub, dotted) if isinstance(sub, type) and hasattr(sub, "model_fields") else [dotted]
        return out

    text = COMMITTED.read_text(encoding="utf-8")
    keys = [k for name, f in Config.model_fields.items() for k in leaves(f.annotation, name)]
    missing = [k for k in keys if f"| `{k}` |" not in text]
    assert not missing, f"keys without a row in docs/config-reference.md: {missing}"
