"""tools.experiments: the per-survey metrics every sweep tabulates."""

import pytest


def test_that_the_default_policys_ve_is_the_surveys_own_fill_not_a_refill_of_the_fitted_cells():
    """The default fills from the cloud's wall contacts and the beams' shadows, which a refill of the fitted heights
    cannot see: its column must be the survey's heights (it had silently repeated `nearest`'s figure)."""
    from types import SimpleNamespace

    import numpy as np

    from ground.surface import DEFAULT_EMPTY_CELLS, Grid
    from tools.experiments import _metrics

    grid = Grid(4.0, 4.0, 1.0)
    fit = np.full((4, 4), 1.0)
    fit[0, :] = np.nan  # a row the points did not reach
    own = np.where(np.isfinite(fit), fit, 3.0)  # the survey's own fill put 3 m there (its wall contacts)
    m = _metrics(SimpleNamespace(heights_fit=fit, heights=own, grid=grid, n_cells_clipped=0, heights_hull=None),
                 true_m3=24.0)
    assert m[f"ve_{DEFAULT_EMPTY_CELLS}_pct"] == pytest.approx(0.0, abs=1e-12)  # 12 cells of 1 m + 4 of 3 m
    assert m["ve_nearest_pct"] == pytest.approx(100.0 * 8.0 / 24.0)  # nearest copies 1 m into the row: 16 m³


def test_that_no_policy_is_swept_under_a_name_a_refill_of_the_fitted_cells_would_misreport():
    """The contact policies other than the default would be refilled without their contacts and shadows: left out."""
    from ground.surface import CONTACT_POLICIES, DEFAULT_EMPTY_CELLS
    from tools.experiments import SWEPT_POLICIES

    assert SWEPT_POLICIES[0] == DEFAULT_EMPTY_CELLS
    assert not set(SWEPT_POLICIES[1:]) & set(CONTACT_POLICIES)
    assert {"nearest", "leave"} <= set(SWEPT_POLICIES)  # Table 2's other columns


def test_that_the_other_policies_fill_the_points_own_fit_not_the_one_the_strip_rule_emptied():
    """`wall-strip` leaves strip cells its contacts contradict to its fill (`Survey.heights_hull` keeps the points'
    own fit): `nearest` and `leave` must be given what they themselves would fill."""
    from types import SimpleNamespace

    import numpy as np

    from ground.surface import Grid
    from tools.experiments import _metrics

    grid = Grid(4.0, 4.0, 1.0)
    hull = np.full((4, 4), 1.0)
    stripped = hull.copy()
    stripped[0, :] = np.nan  # the strip rule took the row along a wall
    filled = np.where(np.isfinite(stripped), stripped, 3.0)
    m = _metrics(SimpleNamespace(heights_fit=stripped, heights=filled, grid=grid, n_cells_clipped=0,
                                 heights_hull=hull), true_m3=16.0)
    assert m["ve_leave_pct"] == pytest.approx(0.0, abs=1e-12)  # the hull's fit covers every cell: 16 m³
    assert m["ve_nearest_pct"] == pytest.approx(0.0, abs=1e-12)
