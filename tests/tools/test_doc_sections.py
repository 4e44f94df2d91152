"""Marked page sections: each tool rewrites only its own, and a whole-page writer keeps the others'."""

import datetime as dt

import pytest

from tools.doc_sections import with_sections_of, write_block, write_dated_section, write_section


def test_that_a_section_is_replaced_in_place_or_appended(tmp_path):
    page = tmp_path / "p.md"
    page.write_text("# Page\n\ntext\n")
    write_section(page, "a", "first")
    write_section(page, "a", "second")
    assert page.read_text() == "# Page\n\ntext\n\n<!-- a:start -->\nsecond\n<!-- a:end -->\n"


def test_that_a_benchmark_writes_its_table_under_its_command_and_date_in_its_own_section(tmp_path):
    page = tmp_path / "README.md"
    page.write_text("intro\n\n<!-- bench-sitl:start -->\nold\n<!-- bench-sitl:end -->\n\nafter\n")
    write_dated_section(page, "tools.bench_sitl", "| median |")
    today = dt.date.today().isoformat()
    assert page.read_text() == (f"intro\n\n<!-- bench-sitl:start -->\n`python -m tools.bench_sitl` on {today}:\n\n"
                                "| median |\n<!-- bench-sitl:end -->\n\nafter\n")


def test_that_a_whole_page_rewrite_keeps_the_sections_it_does_not_write():
    old = "# Old\n\n<!-- t:start -->\nT\n<!-- t:end -->\n\n<!-- u:start -->\nU\n<!-- u:end -->\n"
    new = "# New\n\n<!-- u:start -->\nU2\n<!-- u:end -->\n"
    got = with_sections_of(old, new)
    assert got.startswith(new.rstrip("\n")) and "U2" in got and "\nU\n" not in got
    assert got.endswith("<!-- t:start -->\nT\n<!-- t:end -->\n")
    assert with_sections_of("", new) == new


def test_that_a_source_file_s_one_marked_block_is_replaced_and_none_or_two_are_refused(tmp_path):
    f = tmp_path / "model.py"
    f.write_text("A = 1\n# begin\nK = 1.0\n# end\nB = 2\n")
    write_block(f, "# begin", "# end", "K = 2.5\n", "tool")
    assert f.read_text() == "A = 1\n# begin\nK = 2.5\n# end\nB = 2\n"
    for text in ("A = 1\n", "# begin\nK = 1\n# end\n# begin\nK = 1\n# end\n"):
        f.write_text(text)
        with pytest.raises(SystemExit, match="not one"):
            write_block(f, "# begin", "# end", "K = 3", "tool")
        assert f.read_text() == text  # nothing written
