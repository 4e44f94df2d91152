"""ground.pile_change: per-pile change between two surveys, matched by the cells the piles share."""

import numpy as np
import pytest

from ground.compare import compare_surfaces
from ground.pile_change import format_pile_changes, pile_changes
from ground.surface import Grid, grid_volume
from ground.surface_file import SavedSurface

GRID = Grid(40.0, 20.0, 0.5)


def _saved(h: np.ndarray, sigma_m: float = 0.02) -> SavedSurface:
    return SavedSurface(h, GRID.length_m, GRID.width_m, 10.0, GRID.cell_m, grid_volume(h, GRID), 20.0, 20.0, sigma_m)


def _cone(x0: float, y0: float, r: float, top: float) -> np.ndarray:
    cx, cy = GRID.centres()
    return np.clip(top * (1 - np.hypot(cx - x0, cy - y0) / r), 0.0, None)


def test_that_a_scoop_taken_from_one_of_two_piles_is_that_pile_s_change():
    a, b = _cone(10, 10, 6, 4), _cone(30, 10, 6, 3)
    old = a + b
    cx, cy = GRID.centres()
    scoop = (cx > 8) & (cx < 12) & (cy > 8) & (cy < 12)
    new = old - np.where(scoop, 1.0, 0.0)  # 16 m² x 1 m off pile a's top
    recs = pile_changes(_saved(old), _saved(new), compare_surfaces(_saved(old), _saved(new)))
    by_x = sorted(recs, key=lambda r: r["centroid_m"][0])
    assert [r["status"] for r in by_x] == ["matched", "matched"]
    assert by_x[0]["change_m3"] == pytest.approx(-16.0, rel=0.02)
    assert by_x[1]["change_m3"] == pytest.approx(0.0, abs=0.05)
    lo, hi = by_x[0]["change_interval_m3"]
    assert lo < by_x[0]["change_m3"] < hi
    assert by_x[0]["old_volume_m3"] == pytest.approx(grid_volume(a, GRID), rel=0.01)


def test_that_a_pile_brought_in_or_taken_away_is_reported_new_or_gone_with_its_volume():
    a, b = _cone(10, 10, 6, 4), _cone(30, 10, 6, 3)
    brought = pile_changes(_saved(a), _saved(a + b), compare_surfaces(_saved(a), _saved(a + b)))
    new = [r for r in brought if r["status"] == "new"]
    assert len(new) == 1 and new[0]["old_pile"] is None
    assert new[0]["change_m3"] == pytest.approx(grid_volume(b, GRID), rel=0.01)
    taken = pile_changes(_saved(a + b), _saved(a), compare_surfaces(_saved(a + b), _saved(a)))
    gone = [r for r in taken if r["status"] == "gone"]
    assert len(gone) == 1 and gone[0]["change_m3"] == pytest.approx(-grid_volume(b, GRID), rel=0.01)
    assert any("gone" in line for line in format_pile_changes(taken))


def test_that_an_empty_building_twice_has_no_piles_to_compare():
    flat = np.zeros(GRID.shape)
    assert pile_changes(_saved(flat), _saved(flat), compare_surfaces(_saved(flat), _saved(flat))) == []


def test_that_a_speck_within_its_own_interval_of_zero_is_not_reported_as_a_new_pile():
    a = _cone(10, 10, 6, 4)
    later = a + 0.02  # a second flight 2 cm high everywhere (under its 5 cm noise): the change is that uncertain
    later[70:72, 30:32] = 0.17  # and four cells just over the pile threshold along a wall: 0.17 m³
    old, new = _saved(a, 0.05), _saved(later, 0.05)
    recs = pile_changes(old, new, compare_surfaces(old, new))
    assert [r["status"] for r in recs] == ["matched"]
    brought = later.copy()
    brought[60:72, 24:36] = 1.0  # a real 36 m³ heap there is reported
    assert "new" in [r["status"] for r in pile_changes(old, _saved(brought, 0.05),
                                                       compare_surfaces(old, _saved(brought, 0.05)))]
