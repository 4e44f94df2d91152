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


# ----- --compare: the Must-show table ------------------------------------------------------------

def _s1(pile: str, mission: str, phase: int, ra: float, ve: float, energy_j: float) -> camp.Survey1:
    return camp.Survey1(pile, mission, phase, ra, ve, 100.0, energy_j, energy_j, 150.0)


def test_that_the_comparison_marks_each_target_met_or_missed_against_the_20_percent_rectangle():
    rows = [_s1("2", "rect-20", k, 93.0, 1.2, 18_620.0) for k in (0, 1)]
    rows += [_s1("2", "coverage-99.8", k, ra, ve, 14_800.0) for k, ra, ve in ((0, 99.7, 0.01), (1, 99.2, 0.05))]
    rows += [_s1("2", "rect-5", k, 99.1, 0.02, 27_200.0) for k in (0, 1)]
    args = argparse.Namespace(piles=["2"], phases=[0, 1], coverage=[99.8], yaw_p_traj=20)
    table = camp.compare_page(rows, args)
    assert "| 2 | coverage-99.8 | 99.45 (99.20) | 0.030 (0.050) | 100.0 | 14.80 | 14.80 | 150 | met |" in table
    assert "| 2 | rect-20 | 93.00 (93.00) | 1.200 (1.200) |" in table and "missed: R_a, Ve |" in table
    assert "| 2 | rect-5 | 99.10 (99.10) | 0.020 (0.020) | 100.0 | 27.20 |" in table and "missed: energy |" in table
    assert "Ve over the 2 servo start positions" in table
    assert "| 2 | coverage-99.8 | 0.030 | 0.020 | 0.050 (1) | 99.20 |" in table


def test_that_the_rectangles_share_the_experiments_flight_cache():
    from tools.experiments import ALL_EXPERIMENTS
    missions = camp.compare_missions([], 20)
    assert camp.flight_key(missions["rect-5"]) == ALL_EXPERIMENTS["baseline"].flight_key(5)
    assert camp.flight_key(missions["rect-20-yaw1"]) == ALL_EXPERIMENTS["yaw-1"].flight_key(20)
