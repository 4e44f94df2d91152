"""tools.coverage_campaign --spread: one plan flown at every servo start position, summarised per pile."""

import argparse

import pytest

from tools import coverage_campaign as camp


def _row(pile: str, mission: str, phase: int, ra: float, ve: float) -> camp.Row:
    return camp.Row(pile, mission, phase, 99.9 - phase / 100, 99.9, ra, ve, 90.0, 13e3, 160.0)


def test_that_the_spread_table_gives_mean_sd_max_of_ve_and_min_of_ra_per_pile_and_mission():
    rows = [_row("1", "coverage-99.8", k, 99.0 + k / 10, ve) for k, ve in enumerate((0.1, 0.3, 0.2))]
    rows += [_row("1", "rect-20", 0, 98.0, 0.5)]
    args = argparse.Namespace(plan_phase=0, plan_all_phases=False, piles=["1"], phases=[0, 1, 2],
                              coverage=[99.8], spread_rect=[20])
    table = camp.spread_page(rows, args)
    assert "| 1 | coverage-99.8 | 3 | 99.88 | 99.10 | 99.00 | 0.200 | 0.082 | 0.300 (1) | 13.00 |" in table
    assert "| 1 | rect-20 | 1 |" in table
    assert "flown at all 3 start positions" in table


@pytest.mark.parametrize("argv", [["--spread", "--phases", "20"], ["--spread", "--plan-phase", "-1"]])
def test_that_a_servo_start_position_out_of_range_is_refused(argv, capsys):
    with pytest.raises(SystemExit) as e:
        camp.main(argv)
    assert e.value.code == 2 and "servo start positions are 0..19" in capsys.readouterr().err
