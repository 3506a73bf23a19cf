"""Where the benchmark suite's jobs run: in this process, in worker processes on this
machine, or on a Dask distributed cluster (`dask.distributed`, the `dask` extra).

Each executor takes jobs as module-level functions with picklable arguments and yields
(job index, what the job returned or the exception that ended it) as jobs finish. Worker
processes start with 'spawn' (the Dask nanny's default too), so Open3D and OpenMP start
clean in each.
"""

from __future__ import annotations

import concurrent.futures
import logging
import multiprocessing
import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from typing import Any

from planeslam.core.errors import ConfigError

log = logging.getLogger(__name__)

CONNECT_TIMEOUT_S = 20.0
"""How long to try reaching a Dask scheduler before giving up [s]."""


@dataclass(frozen=True)
class Job:
    """One call to run somewhere."""

    fn: Callable[..., Any]
    """A module-level function (workers import it by name)."""
    args: tuple[Any, ...]
    """Its positional arguments (pickled to reach a worker)."""


Outcome = tuple[int, Any]
"""(job index, the job's return value or the exception it raised)."""


def run_here(jobs: Sequence[Job]) -> Iterator[Outcome]:
    """Every job in this process, one after the other, in order."""
    for k, job in enumerate(jobs):
        try:
            yield k, job.fn(*job.args)
        except Exception as exc:  # noqa: BLE001 - handed to the caller as the job's outcome
            yield k, exc


def run_in_processes(jobs: Sequence[Job], workers: int) -> Iterator[Outcome]:
    """The jobs in `workers` spawned processes of this machine, as they finish."""
    context = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(
        max_workers=max(1, min(workers, len(jobs))), mp_context=context
    ) as pool:
        futures = {pool.submit(job.fn, *job.args): k for k, job in enumerate(jobs)}
        for future in concurrent.futures.as_completed(futures):
            try:
                yield futures[future], future.result()
            except Exception as exc:  # noqa: BLE001 - a crashed worker is the job's outcome
                yield futures[future], exc


def run_on_dask(
    jobs: Sequence[Job], scheduler: str | None = None, workers: int | None = None
) -> Iterator[Outcome]:
    """The jobs on a Dask distributed cluster, as they finish: the scheduler at `scheduler`
    ('tcp://host:8786'; its workers need planeslam installed and the data at the same
    paths), or a LocalCluster of `workers` single-threaded worker processes on 127.0.0.1
    (default: one per core) that is shut down afterwards."""
    try:
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise ConfigError(
            "the dask executor needs dask and distributed: pip install 'planeslam[dask]'"
        ) from None
    with ExitStack() as stack:
        if scheduler is None:
            n_workers = workers or os.cpu_count() or 1
            cluster = stack.enter_context(
                LocalCluster(
                    n_workers=n_workers,
                    threads_per_worker=1,
                    processes=True,
                    host="127.0.0.1",
                    dashboard_address=":0",  # any free port: never clashes with 8787
                    memory_limit=0,  # as the local executor: no worker is paused or killed
                )
            )
            client = stack.enter_context(Client(cluster))
            log.info(
                "dask: LocalCluster with %d workers at %s", n_workers, cluster.scheduler_address
            )
        else:
            try:
                client = stack.enter_context(Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s"))
            except (OSError, TimeoutError, ValueError) as exc:
                reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                raise ConfigError(
                    f"dask scheduler {scheduler!r}: cannot connect ({reason})"
                ) from None
            threads = sum(client.nthreads().values())
            log.info("dask: scheduler %s, %d worker threads", scheduler, threads)
            if threads == 0:
                log.warning("dask: scheduler %s has no workers yet; jobs wait for them", scheduler)
        futures = [client.submit(job.fn, *job.args, pure=False) for job in jobs]
        index = {future.key: k for k, future in enumerate(futures)}
        for future in as_completed(futures):
            try:
                yield index[future.key], future.result()
            except Exception as exc:  # noqa: BLE001 - a failed or lost task is its outcome
                yield index[future.key], exc
