"""How uncertain a study's success rates are: the 95 % Wilson interval of each rate (with its n), and whether
two result files differ beyond their noise (Newcombe's hybrid score interval of the difference).

Wilson comes from scipy (``binomtest(k, n).proportion_ci(method="wilson")``); Newcombe's interval (method 10 of
Newcombe 1998, "Interval estimation for the difference between independent proportions") is built from the two
Wilson intervals: the difference differs from 0 beyond the noise when that interval excludes 0.
"""

from __future__ import annotations

import math
from typing import Any

CONFIDENCE = 0.95


def successes(rate: float, n: int) -> int:
    """The number of successes behind a rate over n runs (rates are k / n, stored as floats)."""
    return round(rate * n)


def wilson(k: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Wilson score interval of k successes in n runs (no continuity correction); (0, 1) when n is 0."""
    if n <= 0:
        return 0.0, 1.0
    if not 0 <= k <= n:
        raise ValueError(f"wilson: successes {k} outside 0..{n}")
    from scipy.stats import binomtest

    ci = binomtest(k, n).proportion_ci(confidence_level=confidence, method="wilson")
    return float(ci.low), float(ci.high)


def newcombe(k1: int, n1: int, k2: int, n2: int, confidence: float = CONFIDENCE) -> tuple[float, float, float]:
    """(p1 - p2, low, high): Newcombe's hybrid score interval of the difference of two independent rates."""
    p1, p2 = k1 / n1, k2 / n2
    l1, u1 = wilson(k1, n1, confidence)
    l2, u2 = wilson(k2, n2, confidence)
    d = p1 - p2
    return d, d - math.sqrt((p1 - l1) ** 2 + (u2 - p2) ** 2), d + math.sqrt((u1 - p1) ** 2 + (p2 - l2) ** 2)


def add_intervals(g: dict[str, Any]) -> dict[str, Any]:
    """Adds to an aggregate (companion.sim.scoring.aggregate) the successes and 95 % Wilson interval of every
    success rate: ``success_k`` {radius: k} and ``success_ci95`` {radius: [low, high]}; n is ``runs``."""
    n = int(g.get("runs", 0))
    if "success" in g:
        g["success_k"] = {r: successes(p, n) for r, p in g["success"].items()}
        g["success_ci95"] = {r: list(wilson(k, n)) for r, k in g["success_k"].items()}
    return g


def fmt_rate(g: dict[str, Any] | None, radius: str) -> str:
    """A success rate for a Markdown cell: ``0.93 [0.79, 0.98] n=30`` (rate, 95 % Wilson interval, runs)."""
    if g is None or "success" not in g:
        return "-"
    p, n = g["success"][radius], int(g["runs"])
    lo, hi = g["success_ci95"][radius] if "success_ci95" in g else wilson(successes(p, n), n)
    return f"{p:.2f} [{lo:.2f}, {hi:.2f}] n={n}"


RATE_NOTE = "Success: rate [95 % Wilson interval] n=runs."
