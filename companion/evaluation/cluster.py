"""Studies on a Ray cluster (``companion eval SUITE --cluster ADDRESS|auto``): the optional engine beside the
local process pool (companion.evaluation.pool), for studies that outgrow one machine (docs/cluster.md).

In-process suites: one Ray task per run, each the same ``run_once(cfg, spec)`` the local pool runs, so the
same seeds give the same numbers whichever engine ran them; results come back in job order. PX4 SITL: one Ray
actor per PX4 instance (companion.evaluation.px4ray), placed by Ray where a node has the CPUs for it.

Ray is an optional extra (``pip install .[cluster]``); nothing imports it unless ``--cluster`` is given.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from companion.evaluation.suites import Job


class ClusterError(ValueError):
    """Ray is missing, or the cluster cannot be reached."""


def connect(address: str) -> Any:
    """``ray`` connected to the cluster at ``address`` (``auto``: the one running on this machine; ``local``: a
    fresh one in this process). Raises ClusterError naming the address when that fails."""
    try:
        import ray
    except ImportError as e:
        raise ClusterError(f"--cluster {address}: Ray is not installed (pip install '.[cluster]')") from e
    if ray.is_initialized():
        return ray
    _reachable(address)
    # The driver's import path goes to the workers: a source checkout (PYTHONPATH) works like an installed one.
    env = {"PYTHONPATH": os.environ["PYTHONPATH"]} if os.environ.get("PYTHONPATH") else {}
    try:
        ray.init(address=address, include_dashboard=False, log_to_driver=False, logging_level="ERROR",
                 runtime_env={"env_vars": env} if env else None)
    except Exception as e:  # ConnectionError, RuntimeError ...: one line naming what could not be reached
        raise ClusterError(f"--cluster {address}: cannot connect to the Ray cluster ({type(e).__name__}: "
                           f"{str(e).splitlines()[0] if str(e) else ''})") from e
    return ray


def _reachable(address: str, timeout: float = 5.0) -> None:
    """A host:port that nobody answers on fails here in seconds (Ray itself retries for minutes)."""
    import socket

    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit():
        return  # auto, local, ray://...: Ray's own checks
    try:
        with socket.create_connection((host, int(port)), timeout=timeout):
            pass
    except OSError as e:
        raise ClusterError(f"--cluster {address}: no Ray head answers there ({e.strerror or e})") from e


def cluster_cpus(ray: Any) -> int:
    return int(ray.cluster_resources().get("CPU", 1))


def _run_one(i: int, job: Job, radii: list[float]) -> tuple[int, dict]:
    """What the local pool's worker does with a job (companion.evaluation.pool._work), on a Ray worker."""
    from companion.sim.runner import run_once

    return i, {**job.group, **run_once(job.cfg, job.spec).as_dict(radii)}


def gather(ray: Any, refs: Sequence[Any], on_result: Callable[[Any], None]) -> None:
    """Wait for every ref, calling ``on_result`` with each result as it arrives (the progress bar)."""
    pending = list(refs)
    while pending:
        done, pending = ray.wait(pending, num_returns=1)
        for ref in done:
            on_result(ray.get(ref))


def run_jobs_ray(address: str, jobs: Sequence[Job], radii: list[float], progress: bool = True,
                 desc: str = "runs") -> list[dict]:
    """Every job as a Ray task (one CPU each); results in job order, as companion.evaluation.pool.run_jobs."""
    from tqdm import tqdm

    ray = connect(address)
    task = ray.remote(num_cpus=1, max_retries=2)(_run_one)  # a lost node's runs are run again elsewhere
    out: list[dict | None] = [None] * len(jobs)
    bar = tqdm(total=len(jobs), desc=f"{desc} on Ray", unit="run", disable=not progress, file=sys.stderr)

    def keep(res: tuple[int, dict]) -> None:
        out[res[0]] = res[1]
        bar.update()

    try:
        refs = [task.remote(i, j, radii) for i, j in enumerate(jobs)]
        gather(ray, refs, keep)
    finally:
        bar.close()
    return [o for o in out if o is not None]
