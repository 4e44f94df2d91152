"""The floor-level check over stored evaluation runs: each run's floor measured as logged and with the lever arm's z
off, the table split by noise model and by the families whose piles may hide the floor."""

import pytest

from tests.tools.golden_run import store_golden_run
from tools.floor_level_check import floor_row, main, summary


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    """The golden flight stored as an evaluation run (samples.npy, header.json, truth.json)."""
    root = tmp_path_factory.mktemp("evalset")
    store_golden_run(root, true_volume_m3=1.0)
    return root


def test_that_a_run_s_floor_is_measured_at_z0_and_at_the_offset_of_a_lever_arm_entered_off(stored):
    run = str(stored / "runs" / "golden-cone-0-none")
    logged = floor_row(run, 0.0)["floor"]
    low = floor_row(run, 0.1)["floor"]
    assert logged is not None and abs(logged["level_m"]) < 0.01
    assert low["level_m"] == pytest.approx(logged["level_m"] - 0.1, abs=0.01)


def test_that_the_table_counts_the_floors_below_z0_and_those_with_a_fall_apart_for_the_hiding_families():
    rows = [{"run": "a", "family": "cone", "noise": "none", "floor_area_m2": 600.0,
             "floor": {"level_m": -0.2, "std_error_m": 0.001, "fall_pct": 1.5}},
            {"run": "b", "family": "cone", "noise": "none", "floor_area_m2": 600.0,
             "floor": {"level_m": 0.001, "std_error_m": 0.001, "fall_pct": 0.1}},
            {"run": "c", "family": "irregular", "noise": "none", "floor_area_m2": 600.0, "floor": None}]
    lines = summary(rows, 0.2)
    # the floors' falls: their median, the largest, and how many the report names (0.5 % or more)
    assert "| the rest (2) | none | 0 | -20.00 cm | -9.95 cm | +0.10 cm | 1 | 0.80 % | 1.50 % | 1 |" in lines
    assert any(line.startswith("| piles that may hide the floor (1) | none | 1 |") for line in lines)
    assert "moved +20 cm down" in lines[-1]


def test_that_the_command_prints_the_table_writes_it_into_its_section_and_refuses_bad_options(stored, tmp_path,
                                                                                               capsys):
    page = tmp_path / "page.md"
    page.write_text("before\n<!-- floor-level-dz10:start -->\nold\n<!-- floor-level-dz10:end -->\nafter\n")
    assert main(["--root", str(stored), "--lever-dz", "0.1", "--write", str(page)]) == 0
    assert "| the rest (1) | none | 0 |" in capsys.readouterr().out
    text = page.read_text()
    assert "old" not in text and "`python -m tools.floor_level_check --lever-dz 0.1` (1 run)" in text
    assert text.startswith("before\n") and text.endswith("after\n") and "| the rest (1) | none | 0 |" in text
    assert main(["--root", str(stored), "--stride", "0"]) == 2
    assert main(["--root", str(tmp_path)]) == 2
    assert "no stored runs" in capsys.readouterr().err
