"""Running a suite's jobs on the local process pool: the in-process simulator (companion.sim.runner), forked
workers, a progress bar, results in job order whatever the number of workers."""

from __future__ import annotations

import multiprocessing as mp
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

from companion.config import config_as_dict
from companion.evaluation.stats import RATE_NOTE, add_intervals
from companion.evaluation.suites import PAPER, Job, build_suite
from companion.evaluation.tables import setpoint_table
from companion.sim.runner import run_once
from companion.sim.scoring import aggregate

if TYPE_CHECKING:
    from companion.config import Config


def _work(item: tuple[int, Job, list[float]]) -> tuple[int, dict]:
    i, job, radii = item
    r = run_once(job.cfg, job.spec)
    return i, {**job.group, **r.as_dict(radii)}


def run_jobs(jobs: Sequence[Job], radii: list[float], n_jobs: int = 2, progress: bool = True,
             desc: str = "runs", cluster: str | None = None) -> list[dict]:
    """Run every job (in ``n_jobs`` processes when > 1, or as Ray tasks on ``cluster``), results in job order."""
    from tqdm import tqdm

    if cluster is not None:
        from companion.evaluation.cluster import run_jobs_ray

        return run_jobs_ray(cluster, jobs, radii, progress, desc)

    items = [(i, j, radii) for i, j in enumerate(jobs)]
    out: list[dict | None] = [None] * len(items)
    bar = tqdm(total=len(items), desc=desc, unit="run", disable=not progress, file=sys.stderr)
    try:
        if n_jobs <= 1 or len(items) <= 1:
            for it in items:
                i, res = _work(it)
                out[i] = res
                bar.update()
        else:
            # fork: workers inherit the imported modules (fast start); each run is independent.
            ctx = mp.get_context("fork")
            with ctx.Pool(n_jobs) as pool:
                for i, res in pool.imap_unordered(_work, items, chunksize=1):
                    out[i] = res
                    bar.update()
    finally:
        bar.close()
    return [o for o in out if o is not None]


def run_suite(name: str, cfg: Config, *, runs: int | None = None, seed: int = 0, n_jobs: int = 2,
              progress: bool = True, camera: str = "geometric", protocol: str = "engagement",
              cluster: str | None = None) -> dict:
    """Run a suite; returns the JSON-able result (per-run, groups, total, markdown, paper)."""
    suite = build_suite(name, cfg, runs, seed)
    suite.jobs = [Job(j.cfg, replace(j.spec, camera=camera, protocol=protocol), j.group) for j in suite.jobs]
    t0 = time.perf_counter()
    results = run_jobs(suite.jobs, suite.radii, n_jobs, progress, desc=name, cluster=cluster)
    wall = time.perf_counter() - t0
    groups, md = suite.report(results, suite.radii)
    total = add_intervals(aggregate(results, suite.radii))
    md += f"\n\n{RATE_NOTE}\n\n" + setpoint_table(groups, total)
    sim_s = sum(r["sim_time_s"] for r in results)
    return {
        "suite": name,
        "seed": seed,
        "radii": suite.radii,
        "total": total,
        "groups": groups,
        "markdown": md,
        "paper": PAPER[name],
        "wall_time_s": wall,
        "sim_time_s": sim_s,
        "jobs": n_jobs,
        **({"cluster": cluster} if cluster is not None else {}),
        "camera": camera,
        "protocol": protocol,
        "config": config_as_dict(cfg),
        "runs": results,
    }
