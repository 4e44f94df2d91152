"""Run folders shared by careless users: two `fly`s into one --out (one is refused while the other flies), a
`fly --force` killed mid-run (the old truth is gone, never beside the new log), a failed `fly` (no folder left),
`serve --out` locked while it serves and refused on another run without --force.

The flights run as real processes; the tests wait on what they can observe (the lock file naming the writer, the
staged log appearing) and hold a writer still with SIGSTOP where they must, never on a fixed sleep.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from firmware_py.core.cli import ExitCode
from firmware_py.core.rundir import LOCK_FILE, SAMPLES_FILE, STAGING_DIR, TLOG_FILE, TRUTH_FILE, holder_pid
from firmware_py.core.samplelog import read_samplelog
from ground.cli import main as ground_main
from sitl.cli import main as sitl_main
from sitl.missions.rectangle import Mission
from sitl.runners import fly as fly_module
from sitl.runners.fly import FlyConfig, fly

ROOT = Path(__file__).resolve().parents[3]
LONG_FLY = ["fly", "--stockpile", "1", "--p-traj", "5", "-q"]  # the firmware in the loop: several seconds of work
WHOLE_FLY = ["fly", "--stockpile", "1", "--p-traj", "25", "--storage", "30x20x10", "--altitude", "9", "--payload",
             "batch", "-q"]
"""The JSBSim plant in the small building with the batch payload (what is tested is the folder, not the firmware,
whose flight in the loop cost 5 s of CPU more): a whole JSBSim flight of work with the lock held (it is seen, then held
still), and a flight the test waits to the end of."""
QUICK_FLY = ["fly", "--stockpile", "1", "--p-traj", "25", "--plant", "ideal", "-q"]
WAIT_S = 120.0  # only a bound on a hung child: every wait below ends on an event


def start(argv: list[str]) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "-m", "sitl.cli", *argv], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_for(proc: subprocess.Popen, what: str, condition) -> None:
    """Poll condition() until true; fail if proc ends first (the event can no longer happen)."""
    end = time.monotonic() + WAIT_S
    while not condition():
        if proc.poll() is not None:
            _out, err = proc.communicate()
            pytest.fail(f"the writer ended (exit {proc.returncode}) before {what}: {err}")
        if time.monotonic() > end:
            proc.kill()
            pytest.fail(f"no {what} within {WAIT_S:g} s")
        time.sleep(0.005)


def test_that_a_second_fly_into_a_folder_being_written_is_refused_and_the_first_is_whole(tmp_path, capsys):
    run = tmp_path / "run"
    first = start([*WHOLE_FLY, "--out", str(run)])
    try:
        wait_for(first, "the lock", lambda: holder_pid(run / LOCK_FILE) == first.pid)
        first.send_signal(signal.SIGSTOP)  # held still: it keeps the lock while the second tries
        assert holder_pid(run / LOCK_FILE) == first.pid
        code = sitl_main([*QUICK_FLY, "--out", str(run)])
        err = capsys.readouterr().err
        assert code == ExitCode.RUNTIME
        assert err == (f"pilescan-sitl: error: {run} is being written by another process (pid {first.pid}); "
                       "wait for it to finish or choose another --out\n")
        code = sitl_main([*QUICK_FLY, "--out", str(run), "--force"])  # --force does not break a lock either
        assert code == ExitCode.RUNTIME and "being written" in capsys.readouterr().err
    finally:
        first.send_signal(signal.SIGCONT)
    _, err = first.communicate(timeout=WAIT_S)
    assert first.returncode == 0, err
    truth = json.loads((run / TRUTH_FILE).read_text())
    log = read_samplelog(run / SAMPLES_FILE)
    assert log.intact and truth["n_samples"] == len(log.samples)  # one run's truth beside that run's log
    assert truth["plant"] == "jsbsim" and truth["mission"]["p_traj"] == 0.25  # the first flight's, not the second's
    assert not (run / LOCK_FILE).exists() and not (run / STAGING_DIR).exists()


def test_that_a_fly_force_killed_mid_run_leaves_no_stale_truth(tmp_path, capsys):
    run = tmp_path / "run"
    assert sitl_main([*QUICK_FLY, "--out", str(run)]) == 0
    old_truth = (run / TRUTH_FILE).read_text()
    staged_log = run / STAGING_DIR / SAMPLES_FILE
    victim = start([*LONG_FLY, "--out", str(run), "--force"])
    wait_for(victim, "the new log", staged_log.exists)
    victim.send_signal(signal.SIGSTOP)
    assert staged_log.exists(), "the flight ended before it could be killed mid-run"
    victim.kill()
    victim.communicate(timeout=WAIT_S)
    assert victim.returncode == -signal.SIGKILL
    assert not (run / TRUTH_FILE).exists()  # neither the old truth nor a new one
    assert not (run / SAMPLES_FILE).exists()  # the old log went too; the new one is staged, unfinished
    capsys.readouterr()
    # What a user does next: the report has no run to score; fly refuses the unfinished folder without --force.
    assert ground_main(["report", str(run), "--out", str(tmp_path / "rep")]) == ExitCode.INPUT
    assert "without a samples.pslog" in capsys.readouterr().err
    assert sitl_main([*QUICK_FLY, "--out", str(run)]) == ExitCode.USAGE
    assert "unfinished" in capsys.readouterr().err
    assert sitl_main([*QUICK_FLY, "--out", str(run), "--force"]) == 0
    truth = json.loads((run / TRUTH_FILE).read_text())
    assert truth["n_samples"] == len(read_samplelog(run / SAMPLES_FILE).samples)
    assert (run / TRUTH_FILE).read_text() != old_truth or truth["plant"] == "ideal"
    assert not (run / STAGING_DIR).exists() and not (run / LOCK_FILE).exists()


def test_that_a_fly_that_fails_mid_flight_leaves_no_folder(tmp_path, monkeypatch):
    def broken(*_a, **_k):
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(fly_module, "sample_flight", broken)
    out = tmp_path / "new" / "nested" / "run"
    with pytest.raises(OSError, match="No space"):
        fly(FlyConfig(mission=Mission(p_traj=0.25), plant="ideal", payload="batch"), out)
    assert list(tmp_path.iterdir()) == []


def test_that_a_failed_fly_force_leaves_the_folder_without_the_old_run(tmp_path, monkeypatch):
    run = tmp_path / "run"
    fly(FlyConfig(mission=Mission(p_traj=0.25), plant="ideal", payload="batch"), run)
    monkeypatch.setattr(fly_module, "sample_flight", lambda *_a, **_k: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        fly(FlyConfig(mission=Mission(p_traj=0.25), plant="ideal", payload="batch"), run, force=True)
    assert list(run.iterdir()) == []  # the old run was removed, truth first; nothing new was put beside it


def test_that_a_fly_over_a_jsbsim_run_with_force_leaves_no_old_telemetry(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    for name in (SAMPLES_FILE, TRUTH_FILE, TLOG_FILE):
        (run / name).write_text("yesterday")
    assert sitl_main([*QUICK_FLY, "--out", str(run)]) == ExitCode.USAGE
    assert "already holds a run" in capsys.readouterr().err and (run / TRUTH_FILE).read_text() == "yesterday"
    assert sitl_main([*QUICK_FLY, "--out", str(run), "--force"]) == 0
    assert not (run / TLOG_FILE).exists()  # the ideal plant writes none: yesterday's must not pass for its
    assert json.loads((run / TRUTH_FILE).read_text())["plant"] == "ideal"


# ----- serve --out ---------------------------------------------------------------------------------

SERVE = ["serve", "--vehicle", "kinematic", "--mavlink", "udp:127.0.0.1:0"]


def test_that_serve_locks_its_folder_while_it_serves_and_commits_on_stop(tmp_path, capsys):
    out = tmp_path / "serve"
    server = start([*SERVE, "--out", str(out)])
    try:
        wait_for(server, "the lock", lambda: holder_pid(out / LOCK_FILE) == server.pid)
        wait_for(server, "the plan", (out / "mission.waypoints").exists)  # published at once, for a GCS
        assert sitl_main([*SERVE, "--duration", "0.1", "--out", str(out), "--force"]) == ExitCode.RUNTIME
        assert sitl_main([*QUICK_FLY, "--out", str(out), "--force"]) == ExitCode.RUNTIME
        assert capsys.readouterr().err.count("being written by another process") == 2
    finally:
        server.send_signal(signal.SIGTERM)
    _, err = server.communicate(timeout=WAIT_S)
    assert server.returncode == 0, err
    assert sorted(p.name for p in out.iterdir()) == ["mission.waypoints", TLOG_FILE]


def test_that_serve_refuses_a_folder_holding_a_run_without_force(tmp_path, capsys):
    run = tmp_path / "run"
    assert sitl_main([*QUICK_FLY, "--out", str(run)]) == 0
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    assert sitl_main([*SERVE, "--duration", "0.1", "--out", str(run)]) == ExitCode.USAGE
    assert "already holds a run" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in run.iterdir()} == before
    assert sitl_main([*SERVE, "--duration", "0.1", "--speedup", "10", "--out", str(run), "--force"]) == 0
    assert sorted(p.name for p in run.iterdir()) == ["mission.waypoints", TLOG_FILE]  # no truth of another run


def test_that_serve_with_a_tfmini_nobody_reads_stops_on_sigterm_and_finishes_its_folder(tmp_path):
    """The TFMini streams into a pseudo-terminal whether a payload reads it or not; serve stops on SIGTERM at once
    (its writer never waits on a full pty: `test_tfmini_emu` fills one) and puts its run in place, truth last."""
    out = tmp_path / "serve"
    server = start([*SERVE, "--devices", "tcp:127.0.0.1:0", "--rangefinder", "tfmini", "--storage", "30x20x10",
                    "--altitude", "9", "--p-traj", "25", "--out", str(out)])
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(server.stderr), daemon=True)  # the pipe never fills
    reader.start()
    try:
        wait_for(server, "the TFMini's pseudo-terminal", lambda: any("TFMini on /dev/" in line for line in lines))
    finally:
        t0 = time.monotonic()
        server.send_signal(signal.SIGTERM)
        try:
            server.wait(timeout=WAIT_S)
        finally:
            server.kill()
    took = time.monotonic() - t0
    reader.join(WAIT_S)
    assert server.returncode == 0, "".join(lines)
    assert took < 8.0, f"serve took {took:.1f} s to stop on SIGTERM"
    assert sorted(p.name for p in out.iterdir()) == sorted(["mission.waypoints", "pile.stl", TLOG_FILE, TRUTH_FILE])
    assert json.loads((out / TRUTH_FILE).read_text())["rangefinder"] == "tfmini"
    assert lines[-1].startswith("pilescan-sitl: stopped after ")
