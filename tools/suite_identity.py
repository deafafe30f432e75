"""Check that a change leaves the in-process studies bit-identical: run 8 deterministic suites on two checkouts
and compare every number of every run (wall time ignored).

    python tools/suite_identity.py OLD_CHECKOUT NEW_CHECKOUT [--out DIR]

Each checkout runs with PYTHONPATH set to it (a `git archive` copy works). Exit 1 on any difference. Results are
identical between code versions on one machine, not across machines: numpy's BLAS kernel depends on the CPU.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

SUITES = [  # (name, companion eval arguments)
    ("table1", ["table1", "--runs", "100", "--seed", "0"]),
    ("table1_sih", ["table1", "--runs", "40", "--seed", "3", "--config", "config/vehicles/sih.yaml"]),
    ("table1_ctrl", ["table1", "--runs", "30", "--seed", "1", "--protocol", "controller"]),
    ("latency", ["latency", "--runs", "24", "--seed", "0"]),
    ("vrel", ["vrel", "--runs", "12", "--seed", "0"]),
    ("baseline", ["baseline", "--runs", "12", "--seed", "0"]),
    ("intercept", ["intercept", "--runs", "30", "--seed", "0"]),
    ("rendered", ["table1", "--runs", "10", "--seed", "0", "--camera", "rendered"]),
]
IGNORED = {"wall_time_s"}


def run_suites(checkout: Path, out: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(checkout)}
    for name, args in SUITES:
        cmd = [sys.executable, "-m", "companion.cli", "eval", *args, "--jobs", "1", "--no-plots", "--no-progress",
               "--out", str(out / name)]
        subprocess.run(cmd, cwd=checkout, env=env, check=True, stdout=subprocess.DEVNULL)


def _strip(o: Any) -> Any:
    if isinstance(o, dict):
        return {k: _strip(v) for k, v in o.items() if k not in IGNORED}
    if isinstance(o, list):
        return [_strip(v) for v in o]
    return o


def differences(a: Any, b: Any, path: str = "") -> list[str]:
    if type(a) is not type(b):
        return [f"{path}: {a!r} != {b!r}"]
    if isinstance(a, dict):
        out = [f"{path}.{k}: missing" for k in set(a) ^ set(b)]
        for k in set(a) & set(b):
            out += differences(a[k], b[k], f"{path}.{k}")
        return out
    if isinstance(a, list):
        if len(a) != len(b):
            return [f"{path}: {len(a)} != {len(b)} items"]
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True)) for d in differences(x, y, f"{path}[{i}]")]
    same = a == b or (isinstance(a, float) and a != a and b != b)  # NaN equals NaN here
    return [] if same else [f"{path}: {a!r} != {b!r}"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("old", type=Path)
    ap.add_argument("new", type=Path)
    ap.add_argument("--out", type=Path, default=None, help="keep the results here (default: a temporary folder)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        for tag, checkout in (("old", args.old), ("new", args.new)):
            run_suites(checkout.resolve(), out / tag)
        bad = 0
        for name, _ in SUITES:
            a, b = (json.loads((out / tag / name / "results.json").read_text()) for tag in ("old", "new"))
            diff = differences(_strip(a), _strip(b), name)
            print(f"{name}: {'identical' if not diff else f'{len(diff)} differences'}")
            for line in diff[:5]:
                print("   ", line)
            bad += bool(diff)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
