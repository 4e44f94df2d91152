"""The report's figures drawn on two cores: half in a forked child, half here, each a pure function writing a PNG.

A report's figures are independent and CPU-bound (matplotlib holds the GIL while it draws, so threads would not
help): on the benchmark's 100k-sample survey they were 3.2 s of a 3.4 s report. A child forked from this process
already has matplotlib and the survey's arrays in memory, so it starts in milliseconds; it draws its share, sends
back the paths (or the exception it met) through a pipe and leaves with `os._exit`, running nothing of the
parent's. It is forked only from a process of one thread, when a core is free for it. Whatever goes wrong
with the child (no fork on this platform, a child that dies) its share is drawn here instead: a slower report,
never a missing figure.
"""

from __future__ import annotations

import os
import pickle
import sys
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class FigureJob:
    """One figure: `fn(*args, **kwargs)` writes it and returns its path. cost_s: a rough drawing time, to split
    the jobs evenly (only their ratio matters)."""

    name: str
    fn: Callable[..., Path]
    args: tuple = ()
    kwargs: dict[str, Any] = field(default_factory=dict)
    cost_s: float = 1.0

    def run(self) -> Path:
        return self.fn(*self.args, **self.kwargs)


def cores_available() -> int:
    """The cores this process may run on (its affinity, not the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def fork_is_safe() -> bool:
    """This platform forks, and this process runs one thread: a child forked beside other threads inherits any
    lock they held at that instant (a stream's, say) and could wait on it for ever. A report made in a server's
    request thread draws in one process."""
    return hasattr(os, "fork") and sys.platform != "darwin" and threading.active_count() == 1


LOADAVG = Path("/proc/loadavg")


def others_running() -> float:
    """How many other tasks want a core now: Linux's count of runnable tasks (`/proc/loadavg`'s fourth field) less
    this process, or elsewhere the 1-minute load average. Not the load average where the count is there: it lags a
    minute, so work started seconds ago is missed, and it counts this process itself once it has been busy (a
    benchmark's or a campaign's reports, one after another, then read their own load as a busy machine)."""
    try:
        return max(0.0, float(LOADAVG.read_text().split()[3].split("/")[0]) - 1.0)
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.getloadavg()[0]
    except OSError:  # no load average on this platform: assume the machine is the report's
        return 0.0


def spare_core() -> bool:
    """A core is free for a second process: on a machine already busy (a test suite, a campaign's workers) a child
    adds its start-up and its cold caches to the load and the report comes out later, not sooner (measured: 5 %
    more CPU for the same reports with two test workers on two cores)."""
    return cores_available() - others_running() >= 1.0


def split(jobs: Sequence[FigureJob]) -> tuple[list[FigureJob], list[FigureJob]]:
    """Two shares of about equal cost (longest first, each to the lighter share), in the jobs' own order."""
    shares: tuple[list[FigureJob], list[FigureJob]] = ([], [])
    load = [0.0, 0.0]
    for job in sorted(jobs, key=lambda j: -j.cost_s):
        k = 0 if load[0] <= load[1] else 1
        shares[k].append(job)
        load[k] += job.cost_s
    order = {id(j): i for i, j in enumerate(jobs)}
    return sorted(shares[0], key=lambda j: order[id(j)]), sorted(shares[1], key=lambda j: order[id(j)])


def _serial(jobs: Sequence[FigureJob]) -> dict[str, Path]:
    return {j.name: j.run() for j in jobs}


def _read_all(fd: int) -> bytes:
    chunks = []
    while chunk := os.read(fd, 1 << 16):
        chunks.append(chunk)
    return b"".join(chunks)


def draw(jobs: Sequence[FigureJob], parallel: bool | None = None) -> dict[str, Path]:
    """Every job's path by name, in the jobs' order. parallel None: in a forked child too when this process can
    fork safely (`fork_is_safe`) and a core is free for it (`spare_core`); False: all here."""
    if parallel is None:
        parallel = len(jobs) > 1 and fork_is_safe() and spare_core()
    if not parallel or len(jobs) < 2:
        return _serial(jobs)
    theirs, ours = split(jobs)
    read_fd, write_fd = os.pipe()
    try:
        pid = os.fork()
    except OSError:  # out of processes or memory: draw everything here
        os.close(read_fd)
        os.close(write_fd)
        return _serial(jobs)
    if pid == 0:  # the child: draw its share, report, and leave without running anything of the parent's
        os.close(read_fd)
        code = 0
        try:
            try:
                result: object = _serial(theirs)
            except BaseException as exc:  # sent to the parent, which raises it
                result = exc
            try:
                payload = pickle.dumps(result)
            except Exception as exc:  # an exception that does not pickle: its words do
                payload = pickle.dumps(RuntimeError(f"figure drawing failed: {exc!r}: {result!r}"))
            with os.fdopen(write_fd, "wb") as w:
                w.write(payload)
        except BaseException:  # the pipe is gone: the parent draws the share itself
            code = 1
        finally:
            os._exit(code)
    os.close(write_fd)
    try:
        mine = _serial(ours)
    finally:
        payload = _read_all(read_fd)
        os.close(read_fd)
        os.waitpid(pid, 0)
    try:
        result = pickle.loads(payload) if payload else None
    except Exception:  # the child died half way through its word
        result = None
    if isinstance(result, BaseException):
        raise result
    if not isinstance(result, dict):  # the child died before it could say: its share is drawn here
        result = _serial(theirs)
    drawn = {**mine, **result}
    return {j.name: drawn[j.name] for j in jobs}
