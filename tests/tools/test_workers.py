"""The tools' worker processes: one BLAS thread each, gone when the tool that started them is, and their progress
shown on a terminal."""

from __future__ import annotations

import ast
import io
import os
import select
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from tests.tools.sweep_toys import blas_threads, ended_within
from tools.workers import progress_map, worker_pool

REPO = Path(__file__).resolve().parents[2]

ORPHAN_PARENT = """
import os, sys, time
from tools.workers import worker_pool
if __name__ == "__main__":
    pool = worker_pool(1, start_method=sys.argv[1] if len(sys.argv) > 1 else None)
    print(pool.submit(os.getpid).result(), flush=True)
    pool.submit(time.sleep, 600)
    time.sleep(600)
"""


@pytest.mark.parametrize("start_method", [None, "spawn"])
def test_that_a_worker_ends_when_the_tool_that_started_it_is_killed(tmp_path, start_method):
    """A tool killed outright (SIGKILL: no Ctrl-C to the process group) leaves no worker computing for nobody, with
    the platform's start method (fork) and with spawn."""
    script = tmp_path / "parent.py"
    script.write_text(ORPHAN_PARENT)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    args = [sys.executable, str(script)] + ([start_method] if start_method else [])
    parent = subprocess.Popen(args, stdout=subprocess.PIPE, text=True, env=env)
    try:
        ready, _, _ = select.select([parent.stdout], [], [], 60.0)  # never wait on a parent that failed to start
        assert ready, "the tool did not report its worker within 60 s"
        worker = int(parent.stdout.readline())
    finally:
        parent.kill()
        parent.wait(timeout=30)
    assert ended_within([worker], 60.0)  # generous: two busy cores; the worker checks every ORPHAN_CHECK_S


def test_that_a_forked_worker_runs_one_blas_thread():
    """A forked worker inherits the parent's BLAS with its thread count (a thread per core unless limited; the suite's
    own processes are limited, so two are set here); the initializer brings it to one."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(2), worker_pool(1) as pool:
        assert pool.submit(blas_threads).result(timeout=60) == 1


def test_that_every_process_pool_in_tools_is_made_by_worker_pool():
    """A pool made directly would lose both guarantees; only tools.workers names ProcessPoolExecutor."""
    offenders = []
    for path in sorted((REPO / "tools").glob("*.py")):
        if path.name == "workers.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Name | ast.Attribute) and "ProcessPoolExecutor" in (
                    getattr(node, "id", None), getattr(node, "attr", None)):
                offenders.append(f"{path.name}:{node.lineno}")
    assert offenders == []


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_that_progress_map_returns_the_maps_results_in_order_and_counts_them_on_a_terminal():
    out = Terminal()
    with ThreadPoolExecutor(3) as pool:
        got = progress_map(pool, pow, [2, 3, 4, 5], [3, 2, 1, 0], desc="check", unit="run", file=out)
    assert got == [8, 9, 4, 1]
    assert "check" in out.getvalue() and "4/4" in out.getvalue() and "run" in out.getvalue()


def test_that_progress_map_draws_nothing_into_a_log_or_pipe_unless_asked():
    log, asked = io.StringIO(), io.StringIO()
    with ThreadPoolExecutor(2) as pool:
        assert progress_map(pool, abs, [-1, 2], desc="check", file=log) == [1, 2]
        assert progress_map(pool, abs, [-1, 2], desc="check", file=asked, show=True) == [1, 2]
    assert log.getvalue() == "" and "2/2" in asked.getvalue()


def test_that_a_worker_s_exception_reaches_the_tool_through_progress_map():
    with ThreadPoolExecutor(2) as pool, pytest.raises(ZeroDivisionError):
        progress_map(pool, lambda x: 1 / x, [1, 0, 2], desc="check", show=False)
