"""The link campaign's tool: one small flood of each target through its own functions (counts only, no
timing thresholds), and its section of the reliability page written between its markers."""

from __future__ import annotations

import os

import pytest

from tools.doc_sections import write_section
from tools.listen_campaign import END, SECTION, START, Case, Kind, Settings, main, run_link_case, run_listen_case

SMALL = Settings(seconds=0.5, rate_hz=400.0, max_log_mb=1.0)


def test_that_a_truncated_header_flood_on_the_payload_link_is_counted_and_its_sources_are_never_answered():
    row = run_link_case(Case(Kind.TRUNCATED, 2, signed=False), SMALL)
    assert row["flood_sent"] > 0 and 0 < row["truncated"] <= row["flood_sent"]
    assert row["legit_delivered"] > 0 and row["peers"] == 1  # the autopilot, and only it
    assert row["flood_answered"] == 0 and row["forged_delivered"] == 0


def test_that_forged_frames_are_refused_on_a_signed_link():
    row = run_link_case(Case(Kind.FORGED_SEQ, 1, signed=True), SMALL)
    assert row["flood_sent"] > 0 and row["refused_auth"] > 0
    assert row["forged_delivered"] == 0 and row["flood_answered"] == 0 and row["legit_delivered"] > 0


def test_that_forged_sequence_numbers_sent_to_listen_are_resyncs_and_the_log_stays_readable(tmp_path):
    os.chmod(tmp_path, 0o700)
    row = run_listen_case(Case(Kind.FORGED_SEQ, 2, signed=False), SMALL, tmp_path)
    assert row["exit"] == 0 and row["log_intact"] and row["flood_sent"] > 0
    assert row["resyncs"] > 0
    assert row["lost"] <= row["legit_sent"] // 20 + 1  # at most the payload's own datagrams, never billions
    assert row["legit_logged"] > 0 and row["log_mb"] <= SMALL.max_log_mb * 1.048576


def test_that_the_section_replaces_its_markers_and_leaves_the_rest_of_the_page(tmp_path):
    page = tmp_path / "reliability.md"
    page.write_text("# Reliability\n\nfault table\n")
    write_section(page, SECTION, "first\n")
    assert page.read_text() == f"# Reliability\n\nfault table\n\n{START}\nfirst\n{END}\n"
    page.write_text(page.read_text() + "\nafter\n")
    write_section(page, SECTION, "second\n")
    text = page.read_text()
    assert "first" not in text and f"{START}\nsecond\n{END}" in text and text.endswith("\nafter\n")
    assert text.startswith("# Reliability\n\nfault table\n")


@pytest.mark.parametrize("args", [["--seconds", "0"], ["--rate", "1e9"], ["--write", "/no/such/dir/x.md"]])
def test_that_bad_options_are_one_line_and_exit_2(capsys, args):
    assert main(args) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
