"""Worker processes for the tools' process pools: one BLAS thread each, and gone when the tool that started them is.

A tool that spreads its cases over a process pool has as many processes as cores; a BLAS that also starts a thread
per core in each of them oversubscribes the cores. And a tool killed outright (SIGKILL, or `kill` of its process
alone: no Ctrl-C to the process group) leaves its workers computing for nobody on the cores the next run needs:
measured, a killed `tools.reproduce` left its two workers running for 25 minutes (docs/design-notes.md, "A tool's
workers end with it"). Every pool in `tools/` is made here so both hold everywhere.

Usage:
    with worker_pool(args.jobs) as pool:
        rows = progress_map(pool, one_row, cases, desc="lever_arm_check", unit="run")

`progress_map` is `pool.map` with a progress bar on a terminal (tqdm's, as `tools.sweep` draws): a check that
reports a thousand stored runs works for ten or twenty minutes, and without it said nothing until its table.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import Executor, ProcessPoolExecutor
from typing import IO, Any

__all__ = ["ORPHAN_CHECK_S", "init_worker", "limit_threads_env", "progress_map", "worker_pool"]

THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")

ORPHAN_CHECK_S = 0.5
"""How often a worker looks whether the process that started it is still there (`exit_when_orphaned`)."""


def limit_threads_env() -> None:
    """Set before numpy loads in a worker: one BLAS/OpenMP thread per process, since the processes use the cores."""
    for name in THREAD_ENV:
        os.environ[name] = "1"


def exit_when_orphaned(check_s: float = ORPHAN_CHECK_S) -> None:
    """Watch, on a daemon thread, for this worker's parent to go away and end the worker then (no cleanup to run: the
    case in flight is lost either way, and the tools that cache keep what finished)."""
    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(check_s)
        os._exit(1)

    threading.Thread(target=watch, name="exit-when-orphaned", daemon=True).start()


def init_worker() -> None:
    """A pool's initializer: one BLAS thread, and an end with the parent.

    The env vars reach a BLAS a spawned worker has yet to load; `threadpool_limits` covers one already loaded (a
    forked worker's, inherited from the parent, or one the parent's __main__ imported in a spawned one)."""
    limit_threads_env()
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    exit_when_orphaned()


def worker_pool(jobs: int, *, start_method: str | None = None) -> ProcessPoolExecutor:
    """A process pool of max(1, jobs) workers made by `init_worker`.

    start_method None keeps the platform's default (fork on Linux with Python 3.11: the workers start in
    milliseconds and share the parent's loaded modules); `tools.sweep` asks for "spawn", a fresh interpreter per
    worker, whose BLAS reads the one-thread env vars as it loads (docs/design-notes.md, "Threads")."""
    ctx = multiprocessing.get_context(start_method)
    return ProcessPoolExecutor(max_workers=max(1, jobs), mp_context=ctx, initializer=init_worker)


def progress_map(pool: Executor, fn: Callable[..., Any], *iterables: Iterable, desc: str, unit: str = "case",
                 chunksize: int = 1, show: bool | None = None, file: IO[str] | None = None) -> list:
    """`pool.map(fn, *iterables)` as a list, in order, with a progress bar of the items done (tqdm's: the count, the
    rate and the time left). show None draws it only when the output is a terminal (a log file or a pipe gets no
    bar, as from `tools.sweep`), True always, False never; file: where to (stderr by default)."""
    from tqdm.auto import tqdm

    args = [list(it) for it in iterables]
    total = min((len(a) for a in args), default=0)  # map stops at the shortest
    with tqdm(total=total, desc=desc, unit=unit, disable=None if show is None else not show, file=file,
              dynamic_ncols=True) as bar:
        out = []
        for result in pool.map(fn, *args, chunksize=chunksize):
            out.append(result)
            bar.update(1)
    return out
