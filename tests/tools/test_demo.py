from tools.demo import README_FIGURE, main


def test_that_the_demo_prints_the_summary_table_and_writes_the_report(tmp_path, capsys):
    """The demo's output, on the batch sampler: the firmware loop it flies by default is tested on its own
    (tests/sitl/test_cli.py, tests/sitl/runners/test_lockstep_payload.py); here it only cost time."""
    assert main(["--out", str(tmp_path), "--p-traj", "25", "--payload", "batch"]) == 0
    out = capsys.readouterr().out
    for label in ("volume", "true volume", "Ve (eq. 8)", "R_a (eq. 9)", "wall time", "report:"):
        assert label in out
    assert "batch payload" in out
    assert (tmp_path / "report" / "report.html").is_file()


def test_that_the_demo_writes_its_summary_and_its_figure_into_the_readme(tmp_path, capsys):
    """The README's summary block and its picture of the demo flight come from one run of the tool, not by hand."""
    readme = tmp_path / "page" / "README.md"
    readme.parent.mkdir()
    readme.write_text("# x\n<!-- demo-summary:start -->\nSTALE SUMMARY\n<!-- demo-summary:end -->\n")
    assert main(["--out", str(tmp_path / "demo"), "--p-traj", "30", "--payload", "batch",
                 "--write-readme", str(readme)]) == 0
    capsys.readouterr()
    text = readme.read_text()
    assert "STALE SUMMARY" not in text and "true volume" in text
    figure = readme.parent / README_FIGURE
    assert figure.read_bytes() == (tmp_path / "demo" / "report" / "cloud_top.png").read_bytes()
