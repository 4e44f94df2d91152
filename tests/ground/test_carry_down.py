"""The unseen cells filled from the nearest seen height, carried on down where the seen surface falls towards them."""

import numpy as np
import pytest

from ground.carry_down import carry_down, window_slopes
from ground.surface import fill_empty, grid_volume
from ground.unseen import MAX_SLOPE

CELL = 0.25
NX, NY = 80, 40  # 20 x 10 m


def x_centres() -> np.ndarray:
    return (np.arange(NX)[:, None] + 0.5) * CELL * np.ones((1, NY))


def seen_up_to(heights: np.ndarray, x_m: float) -> np.ndarray:
    """The surface seen for x < x_m, unseen beyond (NaN)."""
    return np.where(x_centres() < x_m, heights, np.nan)


def test_that_a_window_recovers_a_planes_slope_and_a_line_of_cells_gives_none():
    z = 3.0 + 0.4 * x_centres() - 0.2 * (np.arange(NY)[None, :] + 0.5) * CELL
    gx, gy = window_slopes(z, CELL, CELL)
    assert np.allclose(gx[5:-5, 5:-5], 0.4) and np.allclose(gy[5:-5, 5:-5], -0.2)
    line = np.full((NX, NY), np.nan)
    line[:, 20] = x_centres()[:, 20]  # one row of cells: no plane through them
    gx, gy = window_slopes(line, CELL, CELL)
    assert np.all(gx == 0.0) and np.all(gy == 0.0)


def test_that_a_flank_falling_towards_the_unseen_cells_is_carried_down_at_its_slope_to_the_floor():
    z = 8.0 - 0.5 * x_centres()  # 3 m at the edge x = 10 m, at the floor at x = 16 m
    filled = carry_down(seen_up_to(z, 10.0), CELL, CELL)
    beyond = x_centres() >= 10.0
    # the nearest seen cell is the last one before the edge, whose slope carries on
    assert np.allclose(filled[beyond], np.maximum(z[beyond], 0.0), atol=1e-9)
    assert filled[beyond].min() == 0.0


def test_that_a_rising_or_level_surface_is_copied_level_as_the_nearest_copy_does():
    for z in (0.5 * x_centres(), np.full((NX, NY), 2.0)):
        seen = seen_up_to(z, 10.0)
        assert np.array_equal(carry_down(seen, CELL, CELL), fill_empty(seen, "nearest"))


def test_that_the_carried_slope_is_never_steeper_than_max_slope():
    z = 30.0 - 2.0 * x_centres()  # steeper than any pile stands
    filled = carry_down(seen_up_to(z, 10.0), CELL, CELL)
    edge = z[39, 0]  # the last seen cell, x = 9.875 m
    assert np.allclose(filled[40:, 0], edge - MAX_SLOPE * (x_centres()[40:, 0] - x_centres()[39, 0]))


def test_that_a_fill_is_never_pushed_below_the_floor_nor_lifted_from_a_height_already_under_it():
    z = -0.1 - 0.5 * x_centres()  # a noisy fit dipping under the floor, falling on
    seen = seen_up_to(z, 10.0)
    filled = carry_down(seen, CELL, CELL)
    assert np.array_equal(filled, fill_empty(seen, "nearest"))


def test_that_a_grid_with_nothing_unseen_or_nothing_seen_is_returned_as_it_is():
    z = 8.0 - 0.5 * x_centres()
    assert np.array_equal(carry_down(z, CELL, CELL), z)
    empty = np.full((NX, NY), np.nan)
    assert np.isnan(carry_down(empty, CELL, CELL)).all()


def test_that_the_carry_down_policy_carries_only_the_shadow_cells_under_the_ceiling_and_needs_the_cell_sides():
    z = 8.0 - 0.5 * x_centres()
    seen = seen_up_to(z, 10.0)
    ceiling = np.full((NX, NY), 1.5)
    beyond = x_centres() >= 10.0
    shadow = beyond & (np.arange(NY)[None, :] < NY // 2)  # a beam passed over half of the unseen strip
    filled = fill_empty(seen, "carry-down", ceiling, None, (CELL, CELL), shadow)
    level = fill_empty(seen, "wall-contact", ceiling)
    assert np.allclose(filled[shadow], np.minimum(np.maximum(z[shadow], 0.0), 1.5))
    assert np.array_equal(filled[~shadow], level[~shadow])
    assert np.array_equal(fill_empty(seen, "carry-down", ceiling, None, (CELL, CELL)), level)  # no shadow known
    with pytest.raises(ValueError, match="cell sides"):
        fill_empty(seen, "carry-down", ceiling)


def test_that_on_a_flown_survey_carry_down_lowers_only_shadow_cells_and_reads_nearer_the_truth():
    """The golden flight (pile 1, JSBSim, every 20th sample) surveyed with the default `wall-contact` and with
    `carry-down`: the fitted cells and the unseen cells no beam passed over are filled alike; some of the shadow
    cells (a beam passed over them) are carried down, none up; the volume reads nearer the truth."""
    import json
    from pathlib import Path

    from firmware_py.core.rundir import SAMPLES_FILE
    from firmware_py.core.samplelog import read_samplelog
    from ground.pointcloud import SensorErrorModel
    from ground.report import ReportOptions, header_geometry, survey_from_samples
    from ground.unseen import beam_angle_sigma_rad, free_space_ceilings_m

    run = Path("tests/golden")
    log = read_samplelog(run / SAMPLES_FILE)
    storage, frame, lever = header_geometry(log, run)
    level, down = (survey_from_samples(log.samples, log.header, storage, frame, lever,
                                       ReportOptions(plots=False, empty_cells=policy))
                   for policy in ("wall-contact", "carry-down"))
    unseen = ~np.isfinite(level.heights_fit)
    own, _ = free_space_ceilings_m(level.cloud, level.grid, storage, SensorErrorModel.from_header(log.header),
                                   beam_angle_sigma_rad(log.header), where=unseen)
    shadow = unseen & (own < storage.height_m)
    change = down.heights - level.heights
    assert np.array_equal(down.heights[~shadow], level.heights[~shadow])
    assert np.all(change <= 0.0) and np.count_nonzero(change < 0.0) > 50
    true_m3 = json.loads((run / "truth.json").read_text())["true_volume_m3"]
    error = [abs(grid_volume(s.heights, s.grid) - true_m3) for s in (level, down)]
    assert error[1] < error[0]
