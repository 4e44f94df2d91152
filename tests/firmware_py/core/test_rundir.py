"""Output folders (`firmware_py.core.rundir`): locked while written, refused when taken, staged and renamed with
the marker last, --force clearing the marker first, nothing left behind by a failed writer."""

from __future__ import annotations

import os

import pytest

from firmware_py.core import rundir
from firmware_py.core.cli import ExitCode, RunFailure, UserError, exit_code_of
from firmware_py.core.rundir import LOCK_FILE, RUN_FILES, STAGING_DIR, TRUTH_FILE, OutputFolder, publish_file


def folder(path, force=False) -> OutputFolder:
    return OutputFolder(path, RUN_FILES, TRUTH_FILE, force=force)


def write_run(f: OutputFolder, tag: str, names=RUN_FILES) -> None:
    for n in names:
        f.staged(n).write_text(tag)
    f.commit()


def test_that_a_committed_folder_holds_the_files_and_no_lock_or_staging(tmp_path):
    with folder(tmp_path / "run") as f:
        write_run(f, "new")
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == sorted(RUN_FILES)


def test_that_a_second_writer_is_refused_while_the_first_holds_the_folder(tmp_path):
    with folder(tmp_path / "run") as first:
        with pytest.raises(RunFailure, match=f"being written by another process \\(pid {os.getpid()}\\)") as exc:
            with folder(tmp_path / "run", force=True):
                pass
        assert exit_code_of(exc.value) == ExitCode.RUNTIME
        write_run(first, "first")  # the refused writer removed nothing of the first's
    assert (tmp_path / "run" / TRUTH_FILE).read_text() == "first"


def test_that_a_folder_holding_a_run_is_refused_without_force_and_left_alone(tmp_path):
    with folder(tmp_path / "run") as f:
        write_run(f, "old")
    with pytest.raises(UserError, match=r"already holds a run .*--force") as exc:
        with folder(tmp_path / "run"):
            pass
    assert exit_code_of(exc.value) == ExitCode.USAGE
    assert all((tmp_path / "run" / n).read_text() == "old" for n in RUN_FILES)


def test_that_force_removes_every_old_file_before_anything_new_is_written(tmp_path):
    with folder(tmp_path / "run") as f:
        write_run(f, "old")
    with folder(tmp_path / "run", force=True) as f:
        assert not any((tmp_path / "run" / n).exists() for n in RUN_FILES)
        write_run(f, "new", names=(rundir.SAMPLES_FILE, TRUTH_FILE))  # a run without a tlog: none stays
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == [rundir.SAMPLES_FILE, TRUTH_FILE]


def test_that_force_removes_the_old_marker_first(tmp_path, monkeypatch):
    with folder(tmp_path / "run") as f:
        write_run(f, "old")
    removed = []
    real_unlink = type(tmp_path).unlink
    monkeypatch.setattr(type(tmp_path), "unlink", lambda p, missing_ok=False: (removed.append(p.name),
                                                                                real_unlink(p, missing_ok)))
    with folder(tmp_path / "run", force=True) as f:
        write_run(f, "new")
    assert removed[0] == TRUTH_FILE


def test_that_commit_puts_the_marker_in_place_last(tmp_path, monkeypatch):
    moved = []
    real_replace = os.replace
    monkeypatch.setattr(rundir.os, "replace", lambda a, b: (moved.append(os.path.basename(b)), real_replace(a, b)))
    with folder(tmp_path / "run") as f:
        write_run(f, "new")
    assert moved[-1] == TRUTH_FILE and sorted(moved) == sorted(RUN_FILES)


def test_that_a_failed_writer_leaves_no_file_and_removes_the_folders_it_created(tmp_path):
    with pytest.raises(ZeroDivisionError):
        with folder(tmp_path / "a" / "b" / "run") as f:
            f.staged(rundir.PLAN_FILE).write_text("plan")
            f.publish(rundir.PLAN_FILE)
            f.staged(rundir.SAMPLES_FILE).write_text("half")
            raise ZeroDivisionError
    assert list(tmp_path.iterdir()) == []


def test_that_a_failed_writer_leaves_an_existing_folder_and_its_other_files(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(ZeroDivisionError):
        with folder(tmp_path):
            raise ZeroDivisionError
    assert [p.name for p in tmp_path.iterdir()] == ["notes.txt"]


def test_that_a_killed_writers_leftovers_count_as_an_unfinished_run(tmp_path):
    run = tmp_path / "run"
    (run / STAGING_DIR).mkdir(parents=True)
    (run / STAGING_DIR / rundir.SAMPLES_FILE).write_text("half")
    (run / LOCK_FILE).write_text("999999\n")  # its holder is dead: the kernel released the lock
    with pytest.raises(UserError, match="unfinished"):
        with folder(run):
            pass
    with folder(run, force=True) as f:
        write_run(f, "new")
    assert sorted(p.name for p in run.iterdir()) == sorted(RUN_FILES)


def test_that_an_undeclared_staged_file_is_a_bug_not_a_silent_extra(tmp_path):
    with pytest.raises(RuntimeError, match="does not declare"):
        with folder(tmp_path / "run") as f:
            (f.staging / "stray.bin").write_bytes(b"x")
            f.commit()
    assert not (tmp_path / "run").exists()


def test_that_an_empty_path_is_refused(tmp_path):
    with pytest.raises(UserError, match="non-empty"):
        folder("  ")


def test_that_publish_file_refuses_an_existing_file_without_force_and_replaces_it_with(tmp_path):
    dst = tmp_path / "plan.waypoints"
    dst.write_text("old")
    tmp = tmp_path / ".tmp"
    tmp.write_text("new")
    with pytest.raises(UserError, match="--force"):
        publish_file(tmp, dst, force=False)
    assert dst.read_text() == "old" and not tmp.exists()
    tmp.write_text("new")
    publish_file(tmp, dst, force=True)
    assert dst.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["plan.waypoints"]


def test_that_an_out_that_is_a_file_is_refused_before_any_work_and_left_alone(tmp_path):
    path = tmp_path / "report"
    path.write_text("precious")
    with pytest.raises(UserError, match=r"report directory \(--out\) .*report exists and is not a folder"):
        rundir.check_free(path, RUN_FILES, force=True, what="report")
    with pytest.raises(UserError, match="exists and is not a folder") as exc:
        with folder(path, force=True):
            pass
    assert exit_code_of(exc.value) == ExitCode.RUNTIME  # an output that cannot be written, as a full disk
    assert path.read_text() == "precious"


def test_that_an_out_that_cannot_be_created_says_why_in_one_line_and_leaves_no_folder(tmp_path, monkeypatch):
    (tmp_path / "file").write_text("x")
    with pytest.raises(UserError, match=r"cannot create the run directory \(--out\) .*file/run: Not a directory"):
        with folder(tmp_path / "file" / "run"):
            pass
    made = []
    real_mkdir = rundir.Path.mkdir

    def mkdir_twice(self, *a, **kw):  # the second level fails (no space left, say) after the first was made
        if made:
            raise OSError(28, "No space left on device")
        made.append(self)
        return real_mkdir(self, *a, **kw)
    monkeypatch.setattr(rundir.Path, "mkdir", mkdir_twice)
    with pytest.raises(UserError, match="No space left on device") as exc:
        with folder(tmp_path / "new" / "run"):
            pass
    assert exit_code_of(exc.value) == ExitCode.RUNTIME
    assert made == [tmp_path / "new"] and not (tmp_path / "new").exists()
