"""The PX4 table's "what the app said against the truth" (companion/evaluation/tables.py ``claims_table``): the
app's confirmed passes against SIH's crossings, per motion. Checked on hand-made runs and on a real 100-run table."""

from __future__ import annotations

import json
from pathlib import Path

from companion.evaluation.tables import claims_table

REPO = Path(__file__).resolve().parents[2]


def _row(md: str, name: str) -> list[int]:
    line = next(ln for ln in md.splitlines() if ln.startswith(f"| {name} |"))
    return [int(c) for c in line.strip("|").split("|")[1:]]


def _run(motion: str, through: bool, claimed: int) -> dict:
    return {"motion": motion, "success": {"0.5": False, "1.0": through, "2.0": through},
            "gates_passed_app": claimed}


def test_claims_against_truth_on_hand_made_runs() -> None:
    runs = [_run("planar", True, 1), _run("planar", True, 0), _run("planar", False, 1), _run("planar", False, 0),
            _run("knot", True, 1), _run("knot", False, None)]  # a run the app never summarised: no claim
    md = claims_table(runs, "1.0")
    # runs, through, claimed, claimed and through, claimed not through, through not claimed
    assert _row(md, "planar") == [4, 2, 2, 1, 1, 1]
    assert _row(md, "knot") == [2, 1, 1, 1, 0, 0]
    assert _row(md, "total") == [6, 3, 3, 2, 1, 1]


def test_claims_on_a_real_px4_table_match_a_count_of_its_runs() -> None:
    res = json.loads((REPO / "docs/results/px4_sih_100_20261202e/results.json").read_text())
    runs = res["runs"]
    md = claims_table(runs, "1.0")
    through = [r["success"]["1.0"] for r in runs]
    claimed = [(r["gates_passed_app"] or 0) >= 1 for r in runs]
    unclaimed = sum(t and not c for t, c in zip(through, claimed, strict=True))
    false = sum(c and not t for t, c in zip(through, claimed, strict=True))
    assert _row(md, "total") == [100, sum(through), sum(claimed), sum(through) - unclaimed, false, unclaimed]
    assert (sum(through), unclaimed) == (75, 18)  # that table's 75 crossings, 18 of which the app never claimed
