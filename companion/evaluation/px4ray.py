"""The PX4 SITL evaluation on a Ray cluster (``companion eval table1 --autopilot px4 --cluster ADDRESS``).

One Ray actor per PX4 instance, each asking Ray for ``px4.cpus_per_instance``-many CPUs (PX4 + the app ~ one
core in real time): Ray places the actors where a node has them free, so a node flies as many PX4 instances as
its cores allow. Each actor starts its own PX4 on the node that runs it (instance numbers and ports picked
there, as on one machine: companion.px4sitl.launcher) and flies runs as the driver hands them out, one at a
time (a slow node takes fewer). A run's flight folder comes back to the caller as bytes and lands in
``out_dir``/flights/runNNN, as with the local workers. Every node needs the same PX4 build path and this
package installed (docs/cluster.md).
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from collections import deque
from dataclasses import replace
from pathlib import Path
from typing import Any

from companion.evaluation.px4 import Px4Flyer, Px4Job

CPUS_PER_INSTANCE = 1.0  # PX4 SIH + the app + the synthetic camera: about one core in real time


class Px4Actor:
    """One PX4 instance on whichever node Ray placed this actor; flights in a node-local folder until sent."""

    def __init__(self, sitl_dir: str, files: list[str], overrides: list[str], radii: list[float],
                 candidates: list[int]) -> None:
        self.tmp = Path(tempfile.mkdtemp(prefix="companion-px4ray-"))
        self.log = open(self.tmp / "worker.log", "a", buffering=1)  # noqa: SIM115 (the actor's lifetime)
        self.flyer = Px4Flyer(sitl_dir, files, overrides, str(self.tmp), radii, candidates, self.log)

    def fly(self, job: Px4Job) -> tuple[Px4Job, dict[str, Any] | None, dict[str, bytes]]:
        """(job, result or None for "fly again", the run's flight folder as {relative path: bytes})."""
        res = self.flyer.fly(job)
        run_dir = self.tmp / "flights" / f"run{job.index:03d}"
        files = {str(f.relative_to(run_dir)): f.read_bytes() for f in sorted(run_dir.rglob("*")) if f.is_file()} \
            if res is not None and run_dir.is_dir() else {}
        shutil.rmtree(run_dir, ignore_errors=True)
        if res is not None and "folder" in res:  # this node's path means nothing to the caller: make it relative
            res["folder"] = str(Path(res["folder"]).relative_to(run_dir)) \
                if Path(res["folder"]).is_relative_to(run_dir) else ""
        return job, res, files

    def worker_log(self) -> str:
        return (self.tmp / "worker.log").read_text(errors="replace")

    def close(self) -> None:
        self.flyer.close()
        self.log.close()
        shutil.rmtree(self.tmp, ignore_errors=True)


def fly_on_ray(address: str, jobs: list[Px4Job], n_jobs: int, sitl_dir: str, files: list[str],
               overrides: list[str], out_dir: Path, radii: list[float], candidates: list[int], progress: bool,
               desc: str) -> tuple[dict[int, dict], int]:
    """Every run on Ray actors (``n_jobs`` of them, at most one per run): ({index: result}, actors).
    companion.evaluation.px4.run_px4_suite's ``runner`` with the address bound (functools.partial)."""
    from tqdm import tqdm

    from companion.evaluation.cluster import connect

    ray = connect(address)
    n = max(1, min(n_jobs, len(jobs)))
    actor_cls = ray.remote(num_cpus=CPUS_PER_INSTANCE)(Px4Actor)
    actors = [actor_cls.remote(sitl_dir, files, overrides, radii, candidates) for _ in range(n)]
    todo: deque[Px4Job] = deque(jobs)
    running: dict[Any, Any] = {}  # ref -> actor
    out: dict[int, dict] = {}
    bar = tqdm(total=len(jobs), desc=f"{desc} (Ray)", unit="run", disable=not progress, file=sys.stderr)
    try:
        for a in actors:
            if todo:
                running[a.fly.remote(todo.popleft())] = a
        while running:
            done, _ = ray.wait(list(running), num_returns=1)
            ref = done[0]
            actor = running.pop(ref)
            job, res, flight = ray.get(ref)
            if res is None:
                todo.append(replace(job, attempt=1))  # the harness failed, not the flight: once more
            else:
                run_dir = out_dir / "flights" / f"run{job.index:03d}"
                for rel, data in flight.items():
                    (run_dir / rel).parent.mkdir(parents=True, exist_ok=True)
                    (run_dir / rel).write_bytes(data)
                if "folder" in res:
                    res["folder"] = str(run_dir / res["folder"])
                out[job.index] = res
                ok = sum(r["success"].get("1.0", False) for r in out.values())
                bar.set_postfix_str(f"1 m: {ok}/{len(out)}")
                bar.update()
            if todo:
                running[actor.fly.remote(todo.popleft())] = actor
    finally:
        bar.close()
        for k, a in enumerate(actors):
            try:  # the workers' logs beside the flights, as the local workers leave them
                (out_dir / f"worker{k}.log").write_text(ray.get(a.worker_log.remote(), timeout=30))
                ray.get(a.close.remote(), timeout=120)
            except Exception as e:  # an actor lost with its node: nothing left to stop there
                print(f"companion eval: PX4 actor {k}: {type(e).__name__}: {e}", file=sys.stderr)
            ray.kill(a)
    return out, n
