"""Executors: how shard tasks are run.  They wrap the pipeline's stages, never the reverse.

An executor has one method, ``map_unordered(fn, tasks, progress=None)``, yielding
``fn(task)`` results in any order.  ``fn`` must be a picklable top-level function of one
argument returning ``(shard_index, record)``; in-process executors may pass a
``progress(n_images)`` callback as a keyword argument.
"""

from __future__ import annotations

import multiprocessing as mp
import os
from typing import Callable, Iterable, Iterator


class SerialExecutor:
    """Run tasks one after another in this process (reports progress per object)."""

    def map_unordered(self, fn: Callable, tasks: Iterable, progress=None) -> Iterator:
        for task in tasks:
            yield fn(task, progress=progress)


def _worker_init() -> None:
    # One llvmpipe rasteriser thread per worker: the pool provides the parallelism.
    os.environ.setdefault("LP_NUM_THREADS", "1")


class ProcessExecutor:
    """Run tasks in ``workers`` local processes (spawned: GL contexts never cross a fork)."""

    def __init__(self, workers: int):
        if workers < 1:
            raise ValueError("workers must be >= 1")
        self.workers = workers

    def map_unordered(self, fn: Callable, tasks: Iterable, progress=None) -> Iterator:
        tasks = list(tasks)
        if not tasks:
            return
        ctx = mp.get_context("spawn")
        with ctx.Pool(processes=min(self.workers, len(tasks)), initializer=_worker_init) as pool:
            for result in pool.imap_unordered(fn, tasks):
                if progress is not None:
                    progress(result[1]["n_images"])
                yield result


def local_executor(workers: int):
    """Serial for one worker, a process pool otherwise."""
    return SerialExecutor() if workers <= 1 else ProcessExecutor(workers)
