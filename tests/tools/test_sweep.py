"""The sweep engine (tools/sweep.py) on toy case functions: cache, resume, failures, processes, dask, CSV."""

from __future__ import annotations

import json
import math
import multiprocessing
import os
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from tests.tools import sweep_toys as toys
from tools.sweep import (
    Case,
    SweepError,
    cached,
    content_key,
    missing_cases,
    read_rows_csv,
    run_sweep,
    write_rows_csv,
)

REPO = Path(__file__).resolve().parents[2]


def _cases(n: int, group: str = "toy") -> list[Case]:
    return [Case.make(group, x=i) for i in range(n)]


@pytest.fixture
def call_log(tmp_path, monkeypatch) -> Path:
    d = tmp_path / "calls"
    d.mkdir()
    monkeypatch.setenv(toys.CALL_LOG, str(d))
    monkeypatch.delenv(toys.FAIL_AT, raising=False)
    monkeypatch.delenv(toys.KILL_AT, raising=False)
    return d


def _expected_rows(xs) -> list[dict]:
    out = []
    for x in xs:
        out.append({"group": "toy", "x": x, "y": x * x, "third": x / 3, "vec": [0, x, 2 * x], "i64": x,
                    "flag": x % 2 == 0, "missing": None})
        out.append({"group": "toy", "x": x, "y": -x, "label": f"neg{x}"})
    return out


# ----------------------------------------------------------------------------------------------------- Case


def test_that_a_case_key_is_stable_and_independent_of_parameter_order():
    a = Case.make("cell", pile="conical", p_traj=25, cell=0.1, ideal=True, note=None)
    b = Case.make("cell", note=None, ideal=True, cell=0.1, p_traj=25, pile="conical")
    assert a == b and a.key == b.key and hash(a) == hash(b)
    assert a.params == tuple(sorted(a.params))
    # Pinned: a change of the canonical form would silently orphan every existing cache.
    assert a.key == content_key({"group": "cell", "params": {"cell": 0.1, "ideal": True, "note": None,
                                                             "p_traj": 25, "pile": "conical"}})
    assert Case.make("g", x=1, s="a").key == "fb4f4f042d7da3e9"  # sha256('{"group":"g","params":{"s":"a","x":1}}')[:16]
    assert len(a.key) == 16 and int(a.key, 16) >= 0
    assert a.get("p_traj") == 25 and a.get("nope") is None and a.get("nope", 3) == 3


def test_that_a_case_key_changes_with_every_parameter_the_group_and_the_type():
    base = Case.make("g", x=1, s="a")
    others = [Case.make("h", x=1, s="a"), Case.make("g", x=2, s="a"), Case.make("g", x=1, s="b"),
              Case.make("g", x=1.0, s="a"), Case.make("g", x=True, s="a"), Case.make("g", x=1),
              Case.make("g", x=1, s="a", t=None)]
    keys = {c.key for c in others}
    assert base.key not in keys and len(keys) == len(others)
    assert Case.make("g", x=np.int64(1), s=np.str_("a")).key == base.key  # numpy scalars become Python ones
    assert Case.make("g", v=np.float32(0.5)).get("v") == 0.5


@pytest.mark.parametrize("bad", [[1, 2], {"a": 1}, float("nan"), math.inf, object()])
def test_that_a_case_rejects_parameters_that_are_not_finite_json_scalars(bad):
    with pytest.raises((TypeError, ValueError), match="case parameter"):
        Case.make("g", v=bad)


def test_that_group_is_not_a_parameter_name():
    with pytest.raises(ValueError, match="reserved"):
        Case("g", (("group", 1),))


# ----------------------------------------------------------------------------------------------------- in-process


def test_that_a_sweep_returns_rows_in_case_order_and_a_rerun_reads_them_from_the_cache(tmp_path, call_log):
    cases = [*_cases(4)[::-1], Case.make("toy", x=2)]  # out of order, with a duplicate
    rows = run_sweep(cases, toys.square, tmp_path / "c", jobs=1, progress=False)
    assert rows == _expected_rows([3, 2, 1, 0, 2])
    assert sorted(toys.calls(call_log)) == sorted(c.key for c in _cases(4))  # the duplicate ran once
    assert list(rows[0])[:2] == ["group", "x"]  # case columns first
    rec = json.loads((tmp_path / "c" / "cases" / f"{cases[0].key}.json").read_text())
    assert rec["case"] == {"group": "toy", "params": {"x": 3}} and rec["elapsed_s"] >= 0
    assert rec["fn"] == "tests.tools.sweep_toys.square" and "python" in rec["software"]

    again = run_sweep(cases, toys.square, tmp_path / "c", jobs=1, progress=False)
    assert again == rows
    assert len(toys.calls(call_log)) == 4  # nothing recomputed
    assert missing_cases(cases, tmp_path / "c") == []


def test_that_a_sweep_resumes_after_a_failing_case_and_computes_only_what_is_missing(tmp_path, call_log,
                                                                                      monkeypatch):
    cases = _cases(8)
    monkeypatch.setenv(toys.FAIL_AT, "1,4,6")
    with pytest.raises(SweepError) as err:
        run_sweep(cases, toys.square, tmp_path / "c", jobs=1, progress=False)
    e = err.value
    assert e.n_failed == 3 and e.n_total == 8
    assert [c.get("x") for c, _ in e.failures] == [1, 4, 6]
    msg = str(e)
    assert msg.startswith("3 of 8 case(s) failed") and "ValueError: toy failure at x=4" in msg
    assert "second line" not in msg  # one line per failure
    assert isinstance(e.__cause__, ValueError)  # jobs=1: the first failure's own traceback is chained
    assert len(list((tmp_path / "c" / "cases").glob("*.json"))) == 5
    assert "second line" in (tmp_path / "c" / "failures" / f"{cases[1].key}.txt").read_text()
    assert [c.get("x") for c in missing_cases(cases, tmp_path / "c")] == [1, 4, 6]
    assert len(toys.calls(call_log)) == 8

    monkeypatch.delenv(toys.FAIL_AT)
    rows = run_sweep(cases, toys.square, tmp_path / "c", jobs=1, progress=False)
    assert rows == _expected_rows(range(8))
    assert toys.calls(call_log)[8:] == [cases[i].key for i in (1, 4, 6)]
    assert list((tmp_path / "c" / "failures").iterdir()) == []  # stale tracebacks removed


def test_that_fail_fast_stops_at_the_first_failure(tmp_path, call_log, monkeypatch):
    monkeypatch.setenv(toys.FAIL_AT, "2")
    with pytest.raises(SweepError, match=r"1 of 6 case.*fail_fast") as err:
        run_sweep(_cases(6), toys.square, tmp_path / "c", jobs=1, progress=False, fail_fast=True)
    assert isinstance(err.value.__cause__, ValueError)
    assert len(toys.calls(call_log)) == 3
    assert len(list((tmp_path / "c" / "cases").glob("*.json"))) == 2


def test_that_a_sweep_killed_mid_case_resumes_from_the_cases_it_finished(tmp_path, call_log):
    """The whole sweep process dies (SIGKILL) in its fourth case; a rerun runs that case and the rest only."""
    script = ("import sys; from pathlib import Path; from tools.sweep import Case, run_sweep; "
              "from tests.tools import sweep_toys as t; "
              "run_sweep([Case.make('toy', x=i) for i in range(6)], t.square, Path(sys.argv[1]), jobs=1, "
              "progress=False)")
    env = {**os.environ, toys.KILL_AT: "3"}
    proc = subprocess.run([sys.executable, "-c", script, str(tmp_path / "c")], cwd=REPO, env=env,
                          capture_output=True, timeout=60)
    assert proc.returncode == -9, proc.stderr.decode()
    cases = _cases(6)
    assert toys.calls(call_log) == [c.key for c in cases[:4]]
    assert [c.get("x") for c in missing_cases(cases, tmp_path / "c")] == [3, 4, 5]

    rows = run_sweep(cases, toys.square, tmp_path / "c", jobs=1, progress=False)
    assert rows == _expected_rows(range(6))
    assert toys.calls(call_log)[4:] == [c.key for c in cases[3:]]


def test_that_a_corrupt_or_foreign_cache_file_is_recomputed_not_trusted(tmp_path, call_log, caplog):
    cases = _cases(4)
    run_sweep(cases, toys.square, tmp_path / "c", jobs=1, progress=False)
    d = tmp_path / "c" / "cases"
    good = (d / f"{cases[0].key}.json").read_text()
    (d / f"{cases[0].key}.json").write_text(good[: len(good) // 2])  # half-written, as by a non-atomic writer
    (d / f"{cases[1].key}.json").write_text(good)  # valid JSON, but another case's record
    (d / f"{cases[2].key}.json").write_bytes(b"\xff\xfe\x00garbage")
    (d / f".{cases[3].key}.json.abc.tmp").write_text("{")  # a temp file left by a kill mid-write: ignored
    with caplog.at_level("WARNING", logger="tools.sweep"):
        rows = run_sweep(cases, toys.square, tmp_path / "c", jobs=1, progress=False)
    assert rows == _expected_rows(range(4))
    assert toys.calls(call_log)[4:] == [c.key for c in cases[:3]]
    assert "3 cached case file(s) unusable" in caplog.text


def test_that_case_functions_returning_unstorable_rows_fail_clearly(tmp_path):
    cases = _cases(2)
    for fn, text in [(toys.contradicts, "contradicts the case's x=0"), (toys.unstorable, "cannot store a "),
                     (toys.not_a_list, "must return a list of dicts")]:
        with pytest.raises(SweepError, match="2 of 2") as err:
            run_sweep(cases, fn, tmp_path / fn.__name__, jobs=1, progress=False)
        assert text in str(err.value)
        assert not list((tmp_path / fn.__name__ / "cases").glob("*.json"))


def test_that_non_picklable_case_functions_are_rejected_before_any_work(tmp_path):
    def local(case):
        return []

    for jobs, addr in [(2, None), (1, "tcp://127.0.0.1:9")]:  # the check comes before any connection
        for fn in (lambda case: [], local):
            with pytest.raises(ValueError, match=r"picklable case function.*module level"):
                run_sweep(_cases(2), fn, tmp_path / "c", jobs=jobs, dask_address=addr, progress=False)
    assert run_sweep(_cases(2), lambda case: [{"z": 1}], tmp_path / "c", jobs=1, progress=False) == [
        {"group": "toy", "x": 0, "z": 1}, {"group": "toy", "x": 1, "z": 1}]  # in-process: anything goes


def test_that_a_missing_dask_says_how_to_install_it(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(ImportError, match=r"pip install 'dask\[distributed\]'"):
        run_sweep(_cases(1), toys.square, tmp_path / "c", dask_address="tcp://127.0.0.1:9", progress=False)


# ----------------------------------------------------------------------------------------------------- processes


def test_that_two_worker_processes_give_the_rows_of_one_and_resume_alike(tmp_path, call_log, monkeypatch):
    cases = _cases(6)
    monkeypatch.setenv(toys.FAIL_AT, "5")  # read by the workers at spawn
    with pytest.raises(SweepError, match="1 of 6") as err:
        run_sweep(cases, toys.square, tmp_path / "par", jobs=2, progress=False)
    assert "ValueError: toy failure at x=5" in str(err.value)
    monkeypatch.delenv(toys.FAIL_AT)
    par = run_sweep(cases, toys.square, tmp_path / "par", jobs=2, progress=False)
    assert toys.calls(call_log)[6:] == [cases[5].key]
    assert par == run_sweep(cases, toys.square, tmp_path / "one", jobs=1, progress=False) == _expected_rows(range(6))
    pids = [line.split()[1] for line in (call_log / "calls.log").read_text().splitlines()]
    assert str(os.getpid()) not in pids[:7] and set(pids[7:]) == {str(os.getpid())}  # jobs=2 ran in workers


def test_that_fail_fast_with_worker_processes_reports_the_one_failure(tmp_path, call_log, monkeypatch):
    monkeypatch.setenv(toys.FAIL_AT, "0")
    with pytest.raises(SweepError, match=r"^1 of 8 case.*fail_fast") as err:
        run_sweep(_cases(8), toys.square, tmp_path / "c", jobs=2, progress=False, fail_fast=True)
    assert err.value.n_failed == 1
    done = len(list((tmp_path / "c" / "cases").glob("*.json")))
    assert len(toys.calls(call_log)) == done + 1  # whatever ran was cached


def test_that_worker_processes_use_one_blas_thread_each(tmp_path, monkeypatch):
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # not the suite's own limit
        monkeypatch.setenv(name, "2")
    rows = run_sweep(_cases(2, "threads"), toys.threads, tmp_path / "c", jobs=2, progress=False)
    for r in rows:
        assert r["omp"] == "1" and r["openblas"] == "1" and r["max_threads"] == 1


# ----------------------------------------------------------------------------------------------------- dask


def test_that_a_dask_cluster_on_loopback_gives_the_rows_of_one_process(tmp_path, call_log, monkeypatch):
    distributed = pytest.importorskip("distributed")
    monkeypatch.setenv(toys.FAIL_AT, "99")  # before the workers start: they inherit it
    cases = _cases(5)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as cluster:
        rows = run_sweep(cases, toys.square, tmp_path / "dask", dask_address=cluster.scheduler_address,
                         progress=False)
        with distributed.Client(cluster) as client:
            again = run_sweep(cases, toys.square, tmp_path / "dask", client=client, progress=False)
            with pytest.raises(SweepError, match="1 of 6") as err:
                run_sweep([*cases, Case.make("toy", x=99)], toys.square, tmp_path / "dask", client=client,
                          progress=False)
            assert "ValueError: toy failure at x=99" in str(err.value)
            assert client.status == "running"  # a client passed in is left open
    assert rows == again == run_sweep(cases, toys.square, tmp_path / "one", jobs=1, progress=False)
    assert len(toys.calls(call_log)) == 5 + 1 + 5  # dask: 5, cached rerun: 0, failing case: 1, jobs=1: 5
    pids = [line.split()[1] for line in (call_log / "calls.log").read_text().splitlines()]
    assert str(os.getpid()) not in pids[:6]  # dask ran them in its worker processes


# ----------------------------------------------------------------------------------------------------- cached()


def test_that_cached_computes_once_and_returns_the_stored_value_after(tmp_path):
    n = []

    def compute():
        n.append(1)
        return {"a": np.arange(3), "b": (1, 2)}

    first = cached(tmp_path, "k1", compute)
    second = cached(tmp_path, "k1", compute)
    assert len(n) == 1 and np.array_equal(second["a"], first["a"]) and second["b"] == (1, 2)
    assert cached(tmp_path, "k1.json", compute, kind="json") == {"a": [0, 1, 2], "b": [1, 2]}
    assert cached(tmp_path, "k1.json", compute, kind="json") == {"a": [0, 1, 2], "b": [1, 2]}
    assert len(n) == 2
    (tmp_path / "k1.pkl").write_bytes(b"not a pickle")
    cached(tmp_path, "k1", compute)
    assert len(n) == 3
    key = content_key({"pile": "conical", "p_traj": 25})
    assert cached(tmp_path, key, lambda: 7) == 7 and (tmp_path / f"{key}.pkl").exists()
    for bad in ("../x", "a/b", ".hidden", ""):
        with pytest.raises(ValueError, match="plain file name"):
            cached(tmp_path, bad, compute)
    with pytest.raises(ValueError, match="kind"):
        cached(tmp_path, "k", compute, kind="npz")


def test_that_two_processes_asking_cached_for_one_key_at_once_compute_it_once(tmp_path):
    log = tmp_path / "calls"
    log.mkdir()
    args = (str(tmp_path / "cache"), str(log))
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        a, b = pool.map(toys.cached_flight, [args, args])
    assert toys.calls(log) == ["flight"]
    assert a["pid"] == b["pid"] and np.array_equal(a["samples"], b["samples"])


# ----------------------------------------------------------------------------------------------------- CSV


def test_that_rows_round_trip_through_csv(tmp_path):
    rows = [
        {"group": "g", "x": 1, "v": 0.1, "tiny": 1e-300, "third": 1 / 3, "neg": -2.5e17, "ok": True, "s": "a,b\"c"},
        {"group": "g", "x": 2, "v": None, "extra": "only here", "ok": False, "big": 2**62},
    ]
    write_rows_csv(rows, tmp_path / "out" / "rows.csv")
    back = read_rows_csv(tmp_path / "out" / "rows.csv")
    header = (tmp_path / "out" / "rows.csv").read_text().splitlines()[0]
    assert header == "group,x,v,tiny,third,neg,ok,s,extra,big"  # union of keys, first-seen order
    cols = header.split(",")
    assert back == [{k: r.get(k) for k in cols} for r in rows]  # exact floats, missing cells None
    write_rows_csv([{"nan": math.nan, "inf": -math.inf, "vec": [1, 2.5]}], tmp_path / "odd.csv")
    assert read_rows_csv(tmp_path / "odd.csv") == [{"nan": None, "inf": -math.inf, "vec": "[1, 2.5]"}]


def test_that_sweep_rows_survive_csv(tmp_path):
    rows = run_sweep(_cases(3), toys.square, tmp_path / "c", jobs=1, progress=False)
    write_rows_csv(rows, tmp_path / "rows.csv")
    back = read_rows_csv(tmp_path / "rows.csv")
    assert [r["y"] for r in back] == [r["y"] for r in rows]
    assert [r["third"] for r in back[::2]] == [x / 3 for x in range(3)]


def test_that_a_sweep_s_workers_end_when_the_sweep_is_killed(tmp_path, call_log):
    """A sweep killed outright (SIGKILL: no Ctrl-C to the process group) leaves no worker computing for nobody."""
    script = ("import sys; from pathlib import Path; from tools.sweep import Case, run_sweep; "
              "from tests.tools import sweep_toys as t; "
              "run_sweep([Case.make('toy', x=i) for i in range(2)], t.waits, Path(sys.argv[1]), jobs=2, "
              "progress=False)")
    parent = subprocess.Popen([sys.executable, "-c", script, str(tmp_path / "c")], cwd=REPO, env=os.environ.copy(),
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120.0  # two spawned interpreters importing numpy on two busy cores
        while time.monotonic() < deadline and len(toys.calls(call_log)) < 2 and parent.poll() is None:
            time.sleep(0.2)
        log = call_log / "calls.log"
        pids = [int(line.split()[1]) for line in log.read_text().splitlines()] if log.exists() else []
        assert len(pids) == 2, "the sweep's two workers did not both start their case"
    finally:
        parent.kill()
        parent.wait(timeout=30)
    assert toys.ended_within(pids, 60.0)  # generous: the workers look every ORPHAN_CHECK_S
