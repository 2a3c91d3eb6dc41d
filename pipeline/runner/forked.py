"""Independent jobs of a stage in forked worker processes, one per core: the same results as one after the
other, in about a core's share of the time.

A stage whose items are independent (calibrate's terrains, extract's bags: each its own inputs, outputs and
stamp) maps them with :func:`map_forked`. Fork, not spawn: the workers share the stage's imports and arguments
instead of loading them again (a fresh interpreter takes seconds to import the stack), and they start before
the stage has opened any store or thread pool of its own, or they never use one: compare's figures
(:func:`skidbench.benchmark.report.compare_figures.draw_figures`) are drawn after the MLflow store was read,
from the
board and the files they inherit, and a worker ends without closing what it inherited. How many processes
compute the results changes nothing in them, so it is not a setting (every config key is a parameter of the
MLflow runs).
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any


def cores() -> int:
    """The processors this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def _share_cores(threads: int) -> None:
    """A worker's start: its numerical libraries (BLAS, OpenMP) at ``threads`` threads. A forked worker
    inherits the parent's thread pools sized for every core; a worker per core with that many threads each
    oversubscribes the cores, and OpenBLAS's waiting threads spin on them (`skidbench calibrate force=true`
    on mini, 2026-11-27, alternated runs: 14.5 / 12.5 s wall and 17.8 / 17.4 CPU-s without this limit,
    11.6 / 9.7 s and 14.0 / 12.2 CPU-s with it; the same calibrations)."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=threads)


def map_forked(
    fn: Callable[..., Any],
    calls: Sequence[tuple],
    done: Callable[[int, Any], None] | None = None,
    jobs: int | None = None,
) -> list[Any]:
    """``[fn(*args) for args in calls]``, in forked worker processes when there are two or more calls and
    cores (at most one process per call, and at most ``jobs`` when given), else in this one; the calls
    start in their order. ``done(i, result)`` runs in this process as each call finishes (in the order they
    finish). An exception of a call is raised here, as in the plain loop; the calls not started by then are
    not run (those running finish). Each worker's BLAS and OpenMP get ``cores // workers`` threads."""
    jobs = min(len(calls), cores(), jobs or len(calls))
    results: list[Any] = [None] * len(calls)
    if jobs < 2:
        for i, args in enumerate(calls):
            results[i] = fn(*args)
            if done is not None:
                done(i, results[i])
        return results
    context = multiprocessing.get_context("fork")
    share = (max(1, cores() // jobs),)
    with ProcessPoolExecutor(jobs, mp_context=context, initializer=_share_cores, initargs=share) as pool:
        futures = {pool.submit(fn, *args): i for i, args in enumerate(calls)}
        try:
            for fut in as_completed(futures):
                i = futures[fut]
                results[i] = fut.result()
                if done is not None:
                    done(i, results[i])
        except BaseException:
            pool.shutdown(cancel_futures=True)  # the calls not started yet are not run
            raise
    return results
