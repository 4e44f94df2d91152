"""The report's figures on two cores: every figure drawn once, in the jobs' order, the same bytes as drawn in one
process; what goes wrong in the forked child is raised here or drawn here, never lost."""

import os
from pathlib import Path

import numpy as np
import pytest

from ground import plots
from ground.figure_jobs import FigureJob, draw, split

PARENT = os.getpid()


def _write(path: Path, text: str) -> Path:
    path.write_text(f"{text} by {'parent' if os.getpid() == PARENT else 'child'}")
    return path


def _fail(_path: Path) -> Path:
    raise ValueError("no such figure")


def _unpicklable(_path: Path) -> Path:
    class Local(Exception):
        pass
    raise Local("a local exception class does not pickle")


def _die_in_child(path: Path) -> Path:
    if os.getpid() != PARENT:
        os._exit(3)  # a child that dies without a word (a segfault in a drawing library, say)
    return _write(path, "redrawn")


def test_that_the_split_balances_the_cost_and_keeps_each_share_in_order():
    jobs = [FigureJob(n, _write, cost_s=c) for n, c in [("a", 0.5), ("b", 0.7), ("c", 0.4), ("d", 0.45), ("e", 0.6)]]
    one, two = split(jobs)
    assert sorted(j.name for j in one + two) == ["a", "b", "c", "d", "e"]
    cost = [sum(j.cost_s for j in share) for share in (one, two)]
    assert abs(cost[0] - cost[1]) <= 0.4  # the lightest job at most
    for share in (one, two):
        names = [j.name for j in share]
        assert names == sorted(names)


def test_that_both_processes_draw_and_the_paths_come_back_in_the_jobs_order(tmp_path):
    jobs = [FigureJob(n, _write, (tmp_path / f"{n}.txt", n), cost_s=1.0) for n in "abcd"]
    drawn = draw(jobs, parallel=True)
    assert list(drawn) == list("abcd") and all(drawn[n] == tmp_path / f"{n}.txt" for n in "abcd")
    by = {n: drawn[n].read_text().split(" by ")[1] for n in "abcd"}
    assert sorted(by.values()) == ["child", "child", "parent", "parent"]


def test_that_a_figure_drawn_in_the_child_is_the_figure_drawn_here(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 10, (2000, 3))

    def jobs(folder: Path):
        folder.mkdir()
        return [FigureJob(f"top{k}", plots.plot_cloud_top, (pts, pts[:50, :2], (10.0, 10.0), folder / f"{k}.png"))
                for k in range(2)]
    serial, forked = draw(jobs(tmp_path / "one"), parallel=False), draw(jobs(tmp_path / "two"), parallel=True)
    for name in serial:
        assert serial[name].read_bytes() == forked[name].read_bytes()


@pytest.mark.parametrize(("fn", "error", "words"), [(_fail, ValueError, "no such figure"),
                                                    (_unpicklable, RuntimeError, "does not pickle")])
def test_that_an_error_in_the_child_is_raised_here(tmp_path, fn, error, words):
    jobs = [FigureJob("bad", fn, (tmp_path / "bad.txt",), cost_s=9.0),  # the costliest: the child's share
            FigureJob("good", _write, (tmp_path / "good.txt", "good"), cost_s=1.0)]
    with pytest.raises(error, match=words):
        draw(jobs, parallel=True)
    assert (tmp_path / "good.txt").read_text() == "good by parent"  # this process's share was still drawn


def test_that_a_child_that_dies_has_its_share_drawn_here(tmp_path):
    jobs = [FigureJob("dies", _die_in_child, (tmp_path / "dies.txt",), cost_s=9.0),
            FigureJob("good", _write, (tmp_path / "good.txt", "good"), cost_s=1.0)]
    drawn = draw(jobs, parallel=True)
    assert drawn["dies"].read_text() == "redrawn by parent" and drawn["good"].read_text() == "good by parent"


def test_that_a_busy_machine_draws_in_one_process(tmp_path, monkeypatch):
    """Two test workers on two cores: a child would only add its start-up to the load."""
    import ground.figure_jobs as fj
    jobs = [FigureJob(n, _write, (tmp_path / f"{n}.txt", n)) for n in "ab"]
    monkeypatch.setattr(fj, "fork_is_safe", lambda: True)  # a test worker runs threads of its own
    monkeypatch.setattr(fj, "cores_available", lambda: 2)
    loadavg = tmp_path / "loadavg"
    monkeypatch.setattr(fj, "LOADAVG", loadavg)
    loadavg.write_text("0.10 0.20 0.30 3/412 12345\n")  # this process and two others runnable
    assert {p.read_text() for p in draw(jobs).values()} == {"a by parent", "b by parent"}
    loadavg.write_text("1.90 1.80 1.70 1/412 12345\n")  # this process alone, however busy it was a minute ago
    assert {p.read_text().split(" by ")[1] for p in draw(jobs).values()} == {"parent", "child"}


def test_that_without_a_runnable_count_the_load_average_says_whether_a_core_is_free(tmp_path, monkeypatch):
    import ground.figure_jobs as fj
    monkeypatch.setattr(fj, "cores_available", lambda: 2)
    monkeypatch.setattr(fj, "LOADAVG", tmp_path / "absent")
    monkeypatch.setattr(fj.os, "getloadavg", lambda: (1.5, 1.0, 1.0))
    assert not fj.spare_core()
    monkeypatch.setattr(fj.os, "getloadavg", lambda: (0.3, 1.0, 1.0))
    assert fj.spare_core()
    (tmp_path / "absent").write_text("garbage\n")  # unreadable: the same fallback
    assert fj.spare_core()


def test_that_a_process_running_other_threads_draws_in_one_process(tmp_path, monkeypatch):
    """A report made in a server's request thread: a child forked there could inherit a lock another thread held."""
    import threading

    import ground.figure_jobs as fj
    monkeypatch.setattr(fj, "spare_core", lambda: True)
    jobs = [FigureJob(n, _write, (tmp_path / f"{n}.txt", n)) for n in "ab"]
    stop = threading.Event()
    other = threading.Thread(target=stop.wait)
    other.start()
    try:
        assert {p.read_text() for p in draw(jobs).values()} == {"a by parent", "b by parent"}
    finally:
        stop.set()
        other.join()


def test_that_a_child_s_word_cut_short_has_its_share_drawn_here(tmp_path, monkeypatch):
    import ground.figure_jobs as fj
    monkeypatch.setattr(fj.pickle, "dumps", lambda _obj: b"\x80\x04\x95garbled")  # as if it died mid-write
    jobs = [FigureJob(n, _write, (tmp_path / f"{n}.txt", n)) for n in "ab"]
    assert {p.read_text() for p in draw(jobs, parallel=True).values()} == {"a by parent", "b by parent"}
