"""Toy case functions for test_sweep.py, at module level so spawned and dask worker processes can import them.

They are steered by environment variables, which worker processes inherit when they start, so that a test can
make a case fail or kill its process without changing the case (and so its cache key).
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np

from tools.sweep import Case, cached

CALL_LOG = "SWEEP_TOYS_CALL_LOG"  # a directory: every call appends "<case key> <pid>" to calls.log there
FAIL_AT = "SWEEP_TOYS_FAIL_AT"  # comma-separated x values whose case raises
KILL_AT = "SWEEP_TOYS_KILL_AT"  # the x value whose case SIGKILLs its own process


def _note(what: str) -> None:
    d = os.environ.get(CALL_LOG)
    if d:
        with open(Path(d) / "calls.log", "a") as f:  # one short O_APPEND write per call: safe across processes
            f.write(f"{what} {os.getpid()}\n")


def calls(log_dir: Path) -> list[str]:
    """What was noted, one entry per call, in call order."""
    p = Path(log_dir) / "calls.log"
    return [line.split()[0] for line in p.read_text().splitlines()] if p.exists() else []


def alive(pid: int) -> bool:
    """Whether pid is a running process (a zombie, ended but not yet reaped by its new parent, counts as ended)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def ended_within(pids: list[int], timeout_s: float) -> bool:
    """Whether every process in pids has ended within timeout_s (polled every 0.2 s)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and any(alive(p) for p in pids):
        time.sleep(0.2)
    return not any(alive(p) for p in pids)


def blas_threads() -> int:
    """The most threads any BLAS/OpenMP library loaded in this process runs."""
    from threadpoolctl import threadpool_info

    np.dot(np.ones((4, 4)), np.ones((4, 4)))  # make sure numpy's BLAS is loaded
    return max([p["num_threads"] for p in threadpool_info()] or [1])


def square(case: Case) -> list[dict]:
    """Two rows with numpy values and a NaN, to exercise the JSON conversions."""
    _note(case.key)
    x = case.get("x")
    if str(x) in os.environ.get(FAIL_AT, "").split(","):
        raise ValueError(f"toy failure at x={x}\nsecond line that the summary leaves out")
    if str(x) == os.environ.get(KILL_AT):
        os.kill(os.getpid(), signal.SIGKILL)
    return [
        {"y": x * x, "third": np.float64(x) / 3, "vec": np.arange(3) * x, "i64": np.int64(x),
         "flag": np.bool_(x % 2 == 0), "missing": float("nan")},
        {"y": -x, "label": f"neg{x}"},
    ]


def threads(case: Case) -> list[dict]:
    """What a worker sees of the BLAS/OpenMP thread limits."""
    return [{"omp": os.environ.get("OMP_NUM_THREADS"), "openblas": os.environ.get("OPENBLAS_NUM_THREADS"),
             "max_threads": blas_threads()}]


def waits(case: Case) -> list[dict]:
    """Notes its call, then holds its worker for ten minutes: a case still in flight when its sweep is killed."""
    _note(case.key)
    time.sleep(600)
    return [{"x": case.get("x")}]


def contradicts(case: Case) -> list[dict]:
    """A row whose 'x' disagrees with the case's x: must fail the case."""
    return [{"x": case.get("x") + 1}]


def unstorable(case: Case) -> list[dict]:
    return [{"obj": object()}]


def not_a_list(case: Case) -> dict:
    return {"y": 1}


def cached_flight(args: tuple[str, str]) -> dict:
    """Two processes ask cached() for the same expensive value at once: it must be computed once."""
    cache_dir, log_dir = args
    os.environ[CALL_LOG] = log_dir

    def compute() -> dict:
        _note("flight")
        time.sleep(0.3)  # long enough that the second process asks while the first computes
        return {"samples": np.arange(5), "pid": os.getpid()}

    return cached(Path(cache_dir), "flight", compute)
