"""The echo check over stored evaluation runs: each run's echo record and warning, the table by noise and P_traj."""

import pytest

from tests.tools.golden_run import store_golden_run
from tools.echo_check import echo_row, main, summary


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    """The golden flight stored as an evaluation run (samples.npy, header.json, truth.json)."""
    root = tmp_path_factory.mktemp("evalset")
    store_golden_run(root, true_volume_m3=1.0, p_traj_pct=20)
    return root


def test_that_a_run_gets_its_echo_record_and_no_warning_where_every_beam_reached(stored):
    row = echo_row(str(stored / "runs" / "golden-cone-0-none"))
    assert row["echo"]["samples_aimed"] > 0 and row["noise"] == "none" and row["p_traj"] == 20
    assert row["warned"] is False


def test_that_the_table_counts_the_warnings_the_high_runs_and_the_needless_ones():
    echo = {"no_echo": 10, "samples_aimed": 100}
    rows = [{"noise": "datasheet", "p_traj": 30, "ve_pct": 5.0, "echo": echo, "warned": True},
            {"noise": "datasheet", "p_traj": 30, "ve_pct": 3.0, "echo": echo, "warned": False},
            {"noise": "datasheet", "p_traj": 30, "ve_pct": 0.5, "echo": echo, "warned": True},
            {"noise": "none", "p_traj": 5, "ve_pct": 0.0, "echo": None, "warned": False}]
    lines = summary(rows)
    assert "| datasheet | 30 % | 3 | 10.0 % | 2 | 2 | 1 | 1 |" in lines
    assert "| none | 5 % | 1 | 0.0 % | 0 | 0 | 0 | 0 |" in lines


def test_that_the_command_prints_the_table_writes_it_into_its_section_and_refuses_bad_options(stored, tmp_path,
                                                                                               capsys):
    page = tmp_path / "page.md"
    page.write_text("before\n<!-- echo-check:start -->\nold\n<!-- echo-check:end -->\nafter\n")
    assert main(["--root", str(stored), "--write", str(page)]) == 0
    assert "| none | 20 % | 1 |" in capsys.readouterr().out
    text = page.read_text()
    assert "old" not in text and "`python -m tools.echo_check --jobs 1 --write" in text
    assert "(1 run of the evaluation set" in text
    assert text.startswith("before\n") and text.endswith("after\n")
    assert main(["--root", str(stored), "--stride", "0"]) == 2
    assert main(["--root", str(stored), "--noise", "appendix-a"]) == 2
    assert main(["--root", str(tmp_path)]) == 2
    assert "no stored runs" in capsys.readouterr().err
