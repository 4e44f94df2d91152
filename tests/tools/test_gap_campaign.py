"""tools.gap_campaign: the two-flight table (first flight, then --fill-gaps merged) and its arguments."""

import argparse

import pytest

from tools import gap_campaign as camp


def test_that_the_table_gives_each_flight_and_the_merged_figures_after_the_second():
    rows = [camp.Flight("1", "rect-30", 1, "rect-30", 80.0, 88.4, 12_950.0, 12_890.0, None, None, None, 95.27, 0.16),
            camp.Flight("1", "rect-30", 2, "fill-gaps", 177.0, 95.2, 13_800.0, 14_120.0, 98.84, 99.95, 1818, 99.95,
                        0.004, 212)]
    args = argparse.Namespace(piles=["1"], first=["rect-30"], phase=0, gap_coverage=95.0, plant="jsbsim")
    page = camp.page(rows, args)
    assert "--plant jsbsim`: the JSBSim F450" in page
    assert "| 1 | 1 | rect-30 | 80 | 88.4 | 12.95 | 12.89 | - | - | 95.27 | 0.160 |" in page
    assert "| 1 | 2 | fill-gaps | 177 | 95.2 | 13.80 | 14.12 | 1818 (212) | 98.8 / 99.95 | 99.95 | 0.004 |" in page


@pytest.mark.parametrize("argv, message", [(["--phase", "20"], "servo start positions are 0..19"),
                                           (["--first", "lawnmower"], "first flights are rect-P or coverage-PCT")])
def test_that_bad_arguments_are_refused(argv, message, capsys):
    with pytest.raises(SystemExit) as e:
        camp.main(argv)
    assert e.value.code == 2 and message in capsys.readouterr().err
