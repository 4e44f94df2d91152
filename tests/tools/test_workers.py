"""The tools' worker processes: one BLAS thread each, and gone when the tool that started them is."""

from __future__ import annotations

import ast
import os
import select
import subprocess
import sys
from pathlib import Path

import pytest

from tests.tools.sweep_toys import blas_threads, ended_within
from tools.workers import worker_pool

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
