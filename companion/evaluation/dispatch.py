"""One way to run a suite whatever flies it: ``evaluate(..., autopilot="in-process" | "px4")``.

``in-process``: the simulator in this machine's process pool (companion.evaluation.pool), as many workers as
``n_jobs`` but no more than the CPUs. ``px4``: real PX4 SITL (SIH) and the complete app in real time, one PX4
instance per ``n_jobs`` (companion.evaluation.px4). Both return the same JSON-able result (PX4 adds its own
keys, ``"autopilot": "px4"`` among them). With ``cluster`` (a Ray address, or ``auto``) both run on that Ray
cluster instead (companion.evaluation.cluster): the same results for the same seeds.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from companion.evaluation.pool import run_suite
from companion.evaluation.px4 import run_px4_suite

if TYPE_CHECKING:
    from companion.config import Config

AUTOPILOTS = ("in-process", "px4")


def evaluate(name: str, cfg: Config, *, autopilot: str = "in-process", runs: int | None = None, seed: int = 0,
             n_jobs: int = 2, progress: bool = True, camera: str = "geometric", protocol: str = "engagement",
             out_dir: Path | None = None, px4_dir: str | None = None, motions: list[str] | None = None,
             config_files: Sequence[str] = (), overrides: Sequence[str] = (),
             cluster: str | None = None) -> dict[str, Any]:
    """Run suite ``name`` on ``autopilot``; the result as run_suite returns it.

    Only PX4 reads ``out_dir`` (its worker logs and flight logs; required there), ``px4_dir``, ``motions``
    (only these gate motions) and ``config_files`` / ``overrides`` (its workers load ``cfg`` again from
    them); PX4 flies the app's own protocol, whatever ``protocol`` says.
    Raises ValueError for what cannot run (unknown suite, a detector model missing, a suite PX4 does not
    fly), PX4SitlError when PX4 cannot start."""
    if autopilot == "in-process":
        return run_suite(name, cfg, runs=runs, seed=seed, n_jobs=min(n_jobs, os.cpu_count() or 1),
                         progress=progress, camera=camera, protocol=protocol, cluster=cluster)
    if autopilot == "px4":
        if out_dir is None:
            raise ValueError("--autopilot px4 needs an output folder (worker and flight logs)")
        runner = None
        if cluster is not None:
            from functools import partial

            from companion.evaluation.px4ray import fly_on_ray

            runner = partial(fly_on_ray, cluster)
        res = run_px4_suite(name, cfg, out_dir, runs=runs, seed=seed, n_jobs=n_jobs, progress=progress,
                            camera=camera, px4_dir=px4_dir, motions=motions, config_files=list(config_files),
                            overrides=list(overrides), runner=runner)
        return res if cluster is None else {**res, "cluster": cluster}
    raise ValueError(f"eval: unknown autopilot {autopilot!r} (use one of: {', '.join(AUTOPILOTS)})")
