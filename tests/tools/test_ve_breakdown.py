"""The volume error split by cell kind: the parts add up to Ve, each lands where its cells are, and the
paper pile's exact surface averaged per cell holds the mesh's volume."""

import numpy as np
import pytest

from firmware_py.core.storage import Storage
from ground.surface import Grid
from sitl.world.stockpile import paper_pile, paper_pile_spec, surface_height
from tools.ve_breakdown import breakdown, main, occupied_cells, true_cell_means, wall_band


def test_that_each_part_lands_in_its_own_cells_and_the_parts_add_up_to_ve():
    true = np.full((4, 5), 2.0)
    heights = true.copy()
    heights[0, 0] += 0.5  # an occupied cell read high
    heights[1, 1] -= 0.25  # a bridged cell read low
    heights[3, 4] += 1.0  # a filled cell invented high
    fit = heights.copy()
    fit[3, 4] = np.nan
    occupied = np.zeros_like(true, dtype=bool)
    occupied[0, 0] = True
    volume = true.sum()  # cell area 1 m2
    b = breakdown(heights, fit, occupied, true, 1.0, volume)
    assert b.occupied_pct == pytest.approx(100 * 0.5 / volume)
    assert b.bridged_pct == pytest.approx(-100 * 0.25 / volume)
    assert b.filled_pct == pytest.approx(100 * 1.0 / volume)
    assert b.grid_pct == pytest.approx(0.0)
    assert b.ve_pct == pytest.approx(100 * (heights.sum() - volume) / volume)
    assert b.ve_pct == pytest.approx(b.occupied_pct + b.bridged_pct + b.filled_pct + b.grid_pct)


def test_that_the_exact_surface_averaged_per_cell_holds_the_piles_volume():
    storage = Storage(30, 20, 10)
    grid = Grid(30, 20, 0.25)
    means = true_cell_means(surface_height(paper_pile_spec("1"), storage), grid)
    assert means.sum() * 0.25**2 == pytest.approx(paper_pile("1", storage).volume_m3, rel=1e-3)


def test_that_a_cell_holding_a_point_is_occupied():
    occ = occupied_cells(np.array([[0.1, 0.1, 1.0], [29.9, 19.9, 0.0]]), Grid(30, 20, 0.25))
    assert occ.sum() == 2 and occ[0, 0] and occ[-1, -1]


def test_that_the_filled_cells_at_the_walls_are_split_from_the_rest():
    grid = Grid(10, 8, 1.0)
    true = np.full(grid.shape, 1.0)
    heights = true.copy()
    heights[0, 4] += 2.0  # a filled cell against the wall x = 0
    heights[5, 4] -= 1.0  # a filled cell 4.5 m from the nearest wall
    fit = heights.copy()
    fit[0, 4] = fit[5, 4] = np.nan
    band = wall_band(grid, 2.0)
    assert band[0, 4] and band[1, 4] and not band[2, 4] and not band[5, 4]
    b = breakdown(heights, fit, np.zeros(grid.shape, bool), true, 1.0, true.sum(), band)
    assert b.filled_pct == pytest.approx(100 * 1.0 / true.sum())
    assert b.filled_walls_pct == pytest.approx(100 * 2.0 / true.sum())
    assert breakdown(heights, fit, np.zeros(grid.shape, bool), true, 1.0, true.sum()).filled_walls_pct == 0.0


def test_that_bad_options_are_one_line_and_exit_2(capsys):
    for bad in (["--models", "fog"], ["--phases", "0,25"], ["--phases", "x"], ["--wall-band-m", "0"],
                ["--wall-band-m", "nan"], ["--surface-slopes", "spline"]):
        with pytest.raises(SystemExit) as exc:
            main(bad)
        assert exc.value.code == 2
    assert "--phases integers 0-19" in capsys.readouterr().err
