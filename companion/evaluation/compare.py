"""``companion eval compare A/results.json B/results.json``: does each success rate differ beyond its noise?

Per row (every group both files have, and ``total``) and radius: both rates with n and their 95 % Wilson
intervals, the difference A - B with its 95 % Newcombe (hybrid score) interval, and "yes" when that interval
excludes 0. Exit code: 0 no row differs, 1 at least one row differs, 2 the files cannot be compared.
Each row is its own test at 95 %: with many rows, one "yes" in twenty is expected from noise alone.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from companion.evaluation.stats import newcombe, successes, wilson


class CompareError(ValueError):
    """A result file that cannot be read or compared."""


def load_result(path: Path) -> dict[str, Any]:
    try:
        res = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise CompareError(f"{path}: cannot read a results.json ({e})") from e
    if not isinstance(res, dict) or "total" not in res:
        raise CompareError(f"{path}: no 'total' (not a companion eval results.json)")
    return res


def _rows(res: dict[str, Any]) -> dict[str, dict[str, Any]]:
    rows = {name: g for name, g in res.get("groups", {}).items() if isinstance(g, dict) and "success" in g}
    if "success" in res["total"]:
        rows["total"] = res["total"]
    return rows


def compare(a: dict[str, Any], b: dict[str, Any]) -> list[dict[str, Any]]:
    """One entry per (row, radius) both results have: k, n, rate and interval of each, the difference."""
    ra, rb = _rows(a), _rows(b)
    out = []
    for name in [n for n in ra if n in rb]:
        ga, gb = ra[name], rb[name]
        na, nb = int(ga["runs"]), int(gb["runs"])
        for radius in [r for r in ga["success"] if r in gb["success"]]:
            ka, kb = successes(ga["success"][radius], na), successes(gb["success"][radius], nb)
            d, lo, hi = newcombe(ka, na, kb, nb)
            out.append({"row": name, "radius": radius, "a": (ka, na, *wilson(ka, na)), "b": (kb, nb, *wilson(kb, nb)),
                        "diff": d, "diff_ci95": (lo, hi), "differs": lo > 0.0 or hi < 0.0})
    return out


def compare_markdown(rows: list[dict[str, Any]], name_a: str, name_b: str) -> str:
    lines = [f"A = {name_a}  \nB = {name_b}\n",
             "| Row | radius m | A k/n rate [95 % Wilson] | B k/n rate [95 % Wilson] | A - B [95 % Newcombe] "
             "| differs |",
             "|---|---|---|---|---|---|"]

    def cell(x: tuple) -> str:
        k, n, lo, hi = x
        return f"{k}/{n} {k / n:.2f} [{lo:.2f}, {hi:.2f}]"

    for r in rows:
        lo, hi = r["diff_ci95"]
        lines.append(f"| {r['row']} | {r['radius']} | {cell(r['a'])} | {cell(r['b'])} | "
                     f"{r['diff']:+.2f} [{lo:+.2f}, {hi:+.2f}] | {'yes' if r['differs'] else 'no'} |")
    return "\n".join(lines)


def run_compare(paths: list[Path]) -> int:
    """The command: prints the table, returns the exit code (0 same within noise, 1 differs, 2 bad input)."""
    import sys

    if len(paths) != 2:
        print(f"companion eval compare: needs two results.json files (got {len(paths)})", file=sys.stderr)
        return 2
    try:
        a, b = (load_result(p) for p in paths)
    except CompareError as e:
        print(f"companion eval compare: {e}", file=sys.stderr)
        return 2
    if a.get("suite") != b.get("suite"):
        print(f"companion eval compare: different suites ({a.get('suite')} in {paths[0]}, {b.get('suite')} in "
              f"{paths[1]})", file=sys.stderr)
        return 2
    rows = compare(a, b)
    if not rows:
        print("companion eval compare: no success rate in common", file=sys.stderr)
        return 2
    print(compare_markdown(rows, str(paths[0]), str(paths[1])))
    n = sum(r["differs"] for r in rows)
    print(f"\n{n} of {len(rows)} row(s) differ beyond the noise (95 % Newcombe interval of the difference excludes 0)")
    return 1 if n else 0
