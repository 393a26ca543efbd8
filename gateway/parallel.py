"""One job per file on every core: what ``bsc analyze``, ``bsc sim --series`` and ``bsc replay``
of many logs share.

Each job runs in a worker process of its own (``forkserver``: nothing inherited from the
caller's threads, zenoh sessions or test harness), one session per process at a time; results
come back in the order of the jobs, whatever order they finish in. A progress bar counts jobs.
"""
from __future__ import annotations

import os
from typing import Callable, Iterable, TypeVar

T = TypeVar("T")
R = TypeVar("R")


def workers_for(n_jobs: int, workers: int | None = None) -> int:
    """How many processes for ``n_jobs`` (default: one per CPU, never more than the jobs)."""
    return max(1, min(workers or os.cpu_count() or 1, n_jobs))


def map_jobs(fn: Callable[[T], R], jobs: Iterable[T], *, workers: int | None = None,
             progress: str | None = None, unit: str = "file",
             done: Callable[[int, R], None] | None = None) -> list[R]:
    """``[fn(job) for job in jobs]``, the jobs spread over ``workers`` processes (one: in this
    process). ``fn`` must be a module-level function (it is pickled). ``progress``: the bar's
    label (None: no bar). ``done(i, result)`` is called here as each job finishes. An exception
    in a job is raised here, after the bar is closed (wrap ``fn`` to collect failures instead)."""
    jobs = list(jobs)
    n = workers_for(len(jobs), workers)
    bar = None
    if progress is not None and jobs:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs), unit=unit, desc=progress, leave=False)
    results: dict[int, R] = {}

    def finished(i: int, r: R) -> None:
        results[i] = r
        if done is not None:
            done(i, r)
        if bar is not None:
            bar.update(1)

    try:
        if n == 1:
            for i, job in enumerate(jobs):
                finished(i, fn(job))
        else:
            import concurrent.futures as cf
            import multiprocessing

            ctx = multiprocessing.get_context("forkserver")
            with cf.ProcessPoolExecutor(n, mp_context=ctx) as pool:
                futs = {pool.submit(fn, job): i for i, job in enumerate(jobs)}
                for fut in cf.as_completed(futs):
                    finished(futs[fut], fut.result())
    finally:
        if bar is not None:
            bar.close()
    return [results[i] for i in range(len(jobs))]
