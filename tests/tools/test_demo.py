from tools.demo import main


def test_that_the_demo_prints_the_summary_table_and_writes_the_report(tmp_path, capsys):
    """The demo's output, on the batch sampler: the firmware loop it flies by default is tested on its own
    (tests/sitl/test_cli.py, tests/sitl/runners/test_lockstep_payload.py); here it only cost time."""
    assert main(["--out", str(tmp_path), "--p-traj", "25", "--payload", "batch"]) == 0
    out = capsys.readouterr().out
    for label in ("volume", "true volume", "Ve (eq. 8)", "R_a (eq. 9)", "wall time", "report:"):
        assert label in out
    assert "batch payload" in out
    assert (tmp_path / "report" / "report.html").is_file()
