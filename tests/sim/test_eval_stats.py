"""Success rates with their uncertainty (companion/evaluation/stats.py, compare.py), checked against
published values and the closed-form Wilson interval computed here independently."""

from __future__ import annotations

import json
import math

import pytest

from companion.cli import main
from companion.evaluation.stats import add_intervals, fmt_rate, newcombe, wilson

Z95 = 1.959963984540054  # the standard normal's 97.5 % quantile


def wilson_closed_form(k: int, n: int) -> tuple[float, float]:
    p = k / n
    centre = (p + Z95**2 / (2 * n)) / (1 + Z95**2 / n)
    half = Z95 / (1 + Z95**2 / n) * math.sqrt(p * (1 - p) / n + Z95**2 / (4 * n * n))
    return centre - half, centre + half


@pytest.mark.parametrize(("k", "n"), [(0, 10), (8, 10), (28, 30), (50, 50), (37, 100), (1, 3)])
def test_wilson_matches_the_closed_form(k, n):
    assert wilson(k, n) == pytest.approx(wilson_closed_form(k, n), abs=1e-12)


def test_wilson_published_values():
    # Newcombe (1998), "Two-sided confidence intervals for the single proportion", table I: 81/263 and 0/20.
    assert wilson(81, 263) == pytest.approx((0.2553, 0.3662), abs=1e-4)
    lo, hi = wilson(0, 20)
    assert lo == pytest.approx(0.0, abs=1e-12) and hi == pytest.approx(0.1611, abs=1e-4)


def test_newcombe_difference_published_value():
    # Newcombe (1998), "Interval estimation for the difference between independent proportions", example (a):
    # 56/70 - 48/80, method 10 (hybrid score): 0.0524 to 0.3339.
    d, lo, hi = newcombe(56, 70, 48, 80)
    assert d == pytest.approx(0.2)
    assert (lo, hi) == pytest.approx((0.0524, 0.3339), abs=1e-4)


def test_add_intervals_and_cell():
    g = add_intervals({"runs": 30, "success": {"1.0": 28 / 30, "2.0": 1.0}})
    assert g["success_k"] == {"1.0": 28, "2.0": 30}
    assert g["success_ci95"]["1.0"] == pytest.approx(list(wilson_closed_form(28, 30)))
    assert fmt_rate(g, "1.0") == "0.93 [0.79, 0.98] n=30"
    assert fmt_rate(None, "1.0") == "-"


def _result(path, rates: dict[str, tuple[int, int]]):
    groups = {name: {"runs": n, "success": {"1.0": k / n}} for name, (k, n) in rates.items() if name != "total"}
    k, n = rates["total"]
    path.write_text(json.dumps({"suite": "table1", "groups": groups, "total": {"runs": n, "success": {"1.0": k / n}}}))
    return str(path)


def test_compare_exit_codes(tmp_path, capsys):
    a = _result(tmp_path / "a.json", {"planar": (10, 20), "total": (40, 50)})
    same = _result(tmp_path / "b.json", {"planar": (11, 20), "total": (38, 50)})
    worse = _result(tmp_path / "c.json", {"planar": (10, 20), "total": (20, 50)})
    assert main(["eval", "compare", a, same]) == 0
    assert main(["eval", "compare", a, worse]) == 1
    out = capsys.readouterr().out
    # 40/50 - 20/50 = +0.40; its Newcombe interval, from the closed-form Wilson intervals:
    l1, u1 = wilson_closed_form(40, 50)
    l2, u2 = wilson_closed_form(20, 50)
    lo, hi = 0.4 - math.hypot(0.8 - l1, u2 - 0.4), 0.4 + math.hypot(u1 - 0.8, 0.4 - l2)
    assert f"+0.40 [{lo:+.2f}, {hi:+.2f}] | yes" in out
    assert "1 of 2 row(s) differ" in out
    assert main(["eval", "compare", a]) == 2
    assert main(["eval", "compare", a, str(tmp_path / "missing.json")]) == 2
    assert "missing.json" in capsys.readouterr().err
