"""A study's grid of independent jobs, run in this process or on a Dask cluster, resumable.

Every job has a stable key. Its result (a JSON-able dict) is written to ``results_dir/<key>.json``
as soon as it is back, so a study started again skips the jobs already done and keeps their
results. A job that raises is reported (logged, and returned as a :class:`JobFailure`) while the
others go on.

Engines (``scheduler``):

- ``"local"`` (the default): a Dask ``LocalCluster`` on this machine, one single-threaded worker
  process per core (``n_workers`` to choose), started and stopped by the study: nothing to set up;
- ``"serial"``: one job after the other in this process (no Dask);
- an address such as ``tcp://10.0.0.5:8786``: an existing Dask scheduler, when a study outgrows
  one machine (its workers need this package installed).

The results do not depend on the engine: each job runs the same deterministic code on its own.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from dem_graph.errors import DatasetError, DemGraphError, one_line
from dem_graph.progress import progress

log = logging.getLogger(__name__)

SERIAL = "serial"
LOCAL = "local"
CONNECT_TIMEOUT_S = 20.0  # how long to wait for a scheduler given by address


@dataclass(frozen=True)
class GridJob:
    key: str  # stable and unique in the grid: names the result file
    fn: Callable[..., dict]  # a module-level function (the workers import it), returning a JSON-able dict
    args: tuple = ()


@dataclass(frozen=True)
class JobFailure:
    key: str
    error: str  # one line


def _result_path(results_dir: Path | None, key: str) -> Path | None:
    return None if results_dir is None else results_dir / f"{key}.json"


def _load_done(results_dir: Path | None, jobs: list[GridJob]) -> dict[str, dict]:
    done = {}
    for job in jobs:
        path = _result_path(results_dir, job.key)
        if path is not None and path.is_file():
            try:
                done[job.key] = json.loads(path.read_text())
            except (OSError, ValueError) as exc:  # a file cut short by a stop: the job runs again
                log.warning("%s: unreadable (%s): the job runs again", path, one_line(exc))
    return done


def _keep(results_dir: Path | None, key: str, result: dict) -> None:
    path = _result_path(results_dir, key)
    if path is None:
        return
    tmp = path.with_suffix(".json.tmp")
    try:
        tmp.write_text(json.dumps(result, indent=1))
        tmp.replace(path)
    except OSError as exc:
        raise DatasetError(path, f"cannot write a study's result ({exc.strerror or exc})") from None


def run_grid(
    jobs: list[GridJob], results_dir: str | Path | None = None, scheduler: str = LOCAL, n_workers: int | None = None, desc: str = "study"
) -> dict[str, dict | JobFailure]:
    """Every job's result (or its :class:`JobFailure`), by key, in the jobs' order; jobs whose result
    file is already in ``results_dir`` are not run again."""
    keys = [j.key for j in jobs]
    if len(set(keys)) != len(keys):
        raise ValueError("the jobs' keys must be unique")
    results_dir = Path(results_dir) if results_dir is not None else None
    if results_dir is not None:
        try:
            results_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DatasetError(results_dir, f"cannot create the folder ({exc.strerror or exc})") from None
    out: dict[str, dict | JobFailure] = dict(_load_done(results_dir, jobs))
    todo = [j for j in jobs if j.key not in out]
    if out:
        log.info("%s: %d of %d jobs already done in %s, kept", desc, len(out), len(jobs), results_dir)
    if todo:
        runner = _run_serial if scheduler == SERIAL else _run_dask
        for key, result in runner(todo, scheduler, n_workers, desc):
            if isinstance(result, JobFailure):
                log.error("%s: job %s failed: %s", desc, key, result.error)
            else:
                _keep(results_dir, key, result)
            out[key] = result
    return {k: out[k] for k in keys}


def _run_serial(jobs: list[GridJob], scheduler: str, n_workers: int | None, desc: str):
    for job in progress(jobs, total=len(jobs), desc=desc, unit="job"):
        try:
            yield job.key, job.fn(*job.args)
        except Exception as exc:  # a job's own error: reported, the others go on
            yield job.key, JobFailure(job.key, f"{type(exc).__name__}: {one_line(exc)}")


def _run_dask(jobs: list[GridJob], scheduler: str, n_workers: int | None, desc: str):
    from distributed import Client, LocalCluster, as_completed

    logging.getLogger("distributed").setLevel(max(logging.WARNING, logging.getLogger("distributed").getEffectiveLevel()))  # its start-up chatter
    if scheduler == LOCAL:
        cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=logging.ERROR)
        client = Client(cluster)
    else:
        cluster = None
        try:
            client = Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s")
        except OSError as exc:
            raise DemGraphError(f"no Dask scheduler answers at {scheduler} ({one_line(exc)}): give --scheduler local for a cluster on this machine") from None
    try:
        futures = {client.submit(job.fn, *job.args, key=f"{job.key}-{id(job)}", pure=False): job.key for job in jobs}
        for future in progress(as_completed(futures), total=len(futures), desc=desc, unit="job"):
            key = futures[future]
            exc = future.exception()
            if exc is not None:
                yield key, JobFailure(key, f"{type(exc).__name__}: {one_line(exc)}")
            else:
                yield key, future.result()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


__all__ = ["LOCAL", "SERIAL", "GridJob", "JobFailure", "run_grid"]
