"""The contact check over stored evaluation runs: each run's wall contacts against its true ground, by noise."""

import pytest

from tests.tools.golden_run import RUN, golden_true_volume_m3, store_golden_run
from tools.contact_check import OFF_M, contact_row, main, summary


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    """The golden flight (the paper's pile 1, no noise) stored as an evaluation run naming its stockpile."""
    root = tmp_path_factory.mktemp("evalset")
    store_golden_run(root, true_volume_m3=golden_true_volume_m3(), p_traj_pct=20, stockpile="1")
    return root


def test_that_each_contact_is_scored_against_the_true_ground_and_the_bounds_hold_without_noise(stored):
    row = contact_row(str(stored / "runs" / RUN))
    assert row["noise"] == "none" and row["p_traj"] == 20 and row["contacts"] > 0
    assert row["leaning_n"] + row["allowance_n"] == row["contacts"]
    assert row["leaning_outside"] == row["allowance_outside"] == 0  # a noise-free contact's bounds hold its truth
    for g in ("leaning", "allowance"):
        assert row[f"{g}_sumsq_m2"] >= row[f"{g}_sum_m"] ** 2 / max(row[f"{g}_n"], 1) - 1e-9
        assert 0 <= row[f"{g}_off"] <= row[f"{g}_n"]


def test_that_a_run_without_a_true_surface_is_left_out(tmp_path):
    store_golden_run(tmp_path, true_volume_m3=1.0, p_traj_pct=20)  # names no stockpile and no generated pile
    assert contact_row(str(tmp_path / "runs" / RUN)) is None
    assert main(["--root", str(tmp_path)]) == 2


def test_that_the_table_sums_each_group_over_the_runs():
    def row(noise, n_lean, sum_lean, sq_lean, off_lean, n_allow, sum_allow, sq_allow, off_allow, out_allow):
        return {"noise": noise, "contacts": n_lean + n_allow, "leaning_n": n_lean, "leaning_sum_m": sum_lean,
                "leaning_sumsq_m2": sq_lean, "leaning_off": off_lean, "leaning_outside": 0, "allowance_n": n_allow,
                "allowance_sum_m": sum_allow, "allowance_sumsq_m2": sq_allow, "allowance_off": off_allow,
                "allowance_outside": out_allow}

    rows = [row("appendix-a", 10, -1.0, 1.0, 0, 4, 8.0, 36.0, 2, 1),
            row("appendix-a", 10, 1.0, 1.0, 1, 0, 0.0, 0.0, 0, 0),
            row("none", 5, 0.0, 0.05, 0, 0, 0.0, 0.0, 0, 0)]
    lines = summary(rows)
    assert f"> {OFF_M:g} m off" in lines[0]
    assert lines[2] == "| none | 1 | 5 | 5 | +0.00 | 0.10 | 0.0 % | 0.0 % | 0 | - | - | - | - |"
    assert lines[3] == ("| appendix-a | 2 | 24 | 20 | +0.00 | 0.32 | 5.0 % | 0.0 % | 4 | +2.00 | 3.00 | 50.0 % | "
                        "25.0 % |")


def test_that_the_command_prints_the_table_writes_it_into_its_section_and_refuses_bad_options(stored, tmp_path,
                                                                                               capsys):
    page = tmp_path / "page.md"
    page.write_text("before\n<!-- contact-check:start -->\nSTALE TABLE\n<!-- contact-check:end -->\nafter\n")
    assert main(["--root", str(stored), "--write", str(page)]) == 0
    assert "| none | 1 |" in capsys.readouterr().out
    text = page.read_text()
    assert "STALE TABLE" not in text and "`python -m tools.contact_check --jobs 1 --write" in text
    assert "(1 run of the evaluation set" in text and text.startswith("before\n") and text.endswith("after\n")
    assert main(["--root", str(stored), "--stride", "0"]) == 2
    assert main(["--root", str(stored), "--noise", "appendix-a"]) == 2
    assert main(["--root", str(tmp_path / "nowhere")]) == 2
    assert "no stored runs" in capsys.readouterr().err
