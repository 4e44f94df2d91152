from itertools import groupby

import numpy as np
import pytest

from ground.smoothing import CubicLimit, NodeSlopes, SmoothingOptions
from ground.surface import (
    Grid,
    bridged_cells,
    clip_to_building,
    fill_empty,
    fit_heights,
    grid_volume,
    reconstructed_ratio_pct,
    shaping_points,
    volume_error_pct,
)


def test_that_cells_tile_the_floor_exactly():
    g = Grid(60, 40, 0.33)
    nx, ny = g.shape
    assert g.cell_area_m2 * nx * ny == pytest.approx(2400)
    assert g.x_edges[-1] == 60 and g.y_edges[-1] == 40


def test_that_a_plane_through_scattered_points_gives_its_exact_volume():
    rng = np.random.default_rng(0)
    xy = np.vstack([rng.uniform(0, 10, (500, 2)) * [1, 0.5], [[0, 0], [10, 0], [0, 5], [10, 5]]])
    z = 1.0 + 0.2 * xy[:, 0] + 0.1 * xy[:, 1]
    g = Grid(10, 5, 0.25)
    h = fit_heights(np.column_stack([xy, z]), g)
    assert reconstructed_ratio_pct(h) == pytest.approx(100.0)
    # integral of 1 + 0.2x + 0.1y over [0,10]x[0,5]: 50 + 50 + 12.5
    assert grid_volume(h, g) == pytest.approx(112.5, rel=1e-9)


def test_that_cells_outside_the_data_are_left_or_filled_by_policy():
    pts = np.array([[2, 2, 1.0], [8, 2, 1.0], [8, 8, 1.0], [2, 8, 1.0]])
    g = Grid(10, 10, 0.5)
    h = fit_heights(pts, g)
    assert reconstructed_ratio_pct(h) == pytest.approx(36.0)
    assert grid_volume(fill_empty(h, "leave"), g) == pytest.approx(36.0)
    assert grid_volume(fill_empty(h, "nearest"), g) == pytest.approx(100.0)
    with pytest.raises(ValueError, match="policy"):
        fill_empty(h, "guess")


def test_that_degenerate_clouds_give_no_surface_instead_of_an_error():
    g = Grid(10, 10, 1.0)
    assert np.isnan(fit_heights(np.zeros((0, 3)), g)).all()
    line = np.column_stack([np.linspace(0, 10, 20), np.linspace(0, 10, 20), np.ones(20)])
    assert np.isnan(fit_heights(line, g)).all()


def test_that_volume_error_follows_eq_8():
    assert volume_error_pct(101.0, 100.0) == pytest.approx(1.0)
    assert volume_error_pct(99.0, 100.0) == pytest.approx(1.0)
    assert volume_error_pct(99.0, None) is None


def test_that_silly_cell_sizes_are_refused():
    for cell in (0.0, -1.0, float("nan"), 50.0):
        with pytest.raises(ValueError, match="cell size"):
            Grid(60, 40, cell)


def test_that_contradictory_points_overshoot_and_their_cells_are_emptied_and_counted():
    rng = np.random.default_rng(0)
    top = np.column_stack([rng.uniform(0, 20, (3000, 2)), np.ones(3000)])  # material 1 m deep
    line = np.column_stack([np.linspace(1, 19, 200), np.full(200, 10.0)])
    # The floor "seen" 2 mm from points on the top: what a LiDAR buried in the pile reports.
    floor = np.column_stack([line, np.zeros(200)])
    above = np.column_stack([line + np.array([0.0, 0.002]), np.ones(200)])
    pts = np.vstack([top, floor, above])
    raw = fit_heights(pts, Grid(20, 20, 0.25), "cubic")
    assert np.nanmin(raw) < -1.0 or np.nanmax(raw) > 10.0  # the paper's cubic runs away
    limited = fit_heights(pts, Grid(20, 20, 0.25))  # the default keeps each triangle within its data
    assert np.nanmin(limited) >= 0.0 and np.nanmax(limited) <= 1.0
    assert np.array_equal(np.isnan(limited), np.isnan(raw))
    h, n_off = clip_to_building(raw, 8.0)
    assert n_off > 0 and np.nanmin(h) >= -0.5 and np.nanmax(h) <= 8.5
    assert np.isnan(h).sum() == np.isnan(raw).sum() + n_off  # those cells are uncovered now
    small = np.array([[-0.2, 8.3, np.nan, 1.0]])
    assert np.array_equal(clip_to_building(small, 8.0)[0], small, equal_nan=True)  # noise-level dips stay


@pytest.mark.parametrize("method", ["cubic-limited", "cubic", "linear"])
def test_that_every_fit_is_exact_on_a_plane(method):
    rng = np.random.default_rng(1)
    xy = np.vstack([rng.uniform(0, 10, (400, 2)) * [1, 0.5], [[0, 0], [10, 0], [0, 5], [10, 5]]])
    g = Grid(10, 5, 0.25)
    h = fit_heights(np.column_stack([xy, 2.0 + 0.3 * xy[:, 0] - 0.1 * xy[:, 1]]), g, method)
    assert grid_volume(h, g) == pytest.approx(50 * 2.0 + 0.3 * 50 * 5 - 0.1 * 10 * 12.5, rel=1e-9)


def test_that_the_limited_cubic_keeps_the_cubic_on_a_smooth_dome_and_tames_noise():
    rng = np.random.default_rng(2)
    xy = rng.uniform(0, 20, (3000, 2))
    dome = 5.0 * np.exp(-((xy[:, 0] - 10) ** 2 + (xy[:, 1] - 10) ** 2) / 30.0)
    g = Grid(20, 20, 0.25)
    exact = {m: fit_heights(np.column_stack([xy, dome]), g, m) for m in ("cubic-limited", "cubic")}
    assert np.nanmax(np.abs(exact["cubic-limited"] - exact["cubic"])) < 0.02  # the limit hardly bites
    noisy = np.column_stack([xy + rng.normal(0, 0.2, xy.shape), dome + rng.normal(0, 0.2, len(dome))])
    lim, cub = fit_heights(noisy, g), fit_heights(noisy, g, "cubic")
    assert np.nanmax(lim) <= noisy[:, 2].max() and np.nanmin(lim) >= noisy[:, 2].min()
    assert np.nanmax(np.abs(cub - lim)) > 0.05  # the unlimited one overshoots somewhere


def test_that_where_the_cubic_would_leave_a_long_triangle_the_linear_limit_keeps_the_lean_and_the_clip_a_flat():
    # A steep slope seen densely up to x = 4 m, then nothing until a flat seen from x = 16 m: the cubic across the
    # 12 m bridge leaves the slope's top at the slope's own gradient and overshoots its corners' range.
    x, y = np.meshgrid(np.arange(0.1, 20, 0.2), np.arange(0.1, 10, 0.2), indexing="ij")
    x, y = x.ravel(), y.ravel()
    seen = (x < 4) | (x > 16)
    z = np.where(x < 4, 1.5 * x, 3.0)[seen]
    pts = np.column_stack([x[seen], y[seen], z])
    g = Grid(20, 10, 0.25)
    clip, linear = (fit_heights(pts, g, "cubic-limited", smoothing=SmoothingOptions(limit=limit))
                    for limit in (CubicLimit.CLIP, CubicLimit.LINEAR))
    cx, _ = g.centres()
    bridge = (cx > 5) & (cx < 15) & np.isfinite(clip)
    top = z.max()  # the slope's last height seen
    assert np.count_nonzero(np.isclose(clip[bridge], top, atol=1e-6)) > 0.2 * np.count_nonzero(bridge)  # the flat
    changed = bridge & ~np.isclose(clip, linear, atol=1e-9)
    assert np.count_nonzero(changed) > 0.2 * np.count_nonzero(bridge)
    assert np.all((linear[bridge] >= 3.0 - 1e-9) & (linear[bridge] <= top + 1e-9))  # within the corners' range
    cols = bridge.any(axis=1)  # along x across the bridge: the clip stands still for metres, the linear limit falls

    def longest_level_m(h: np.ndarray) -> float:
        level = np.isclose(np.diff(h[cols], axis=0), 0.0, atol=1e-9)  # a cell the same height as the one before it
        return g.cell_xy_m[0] * max((sum(1 for _ in run) for row in level.T for same, run in groupby(row) if same),
                                    default=0)
    assert longest_level_m(clip) > 2.0 and longest_level_m(linear) == 0.0
    seen_cells = (cx < 3.5) | (cx > 16.5)
    np.testing.assert_allclose(clip[seen_cells], linear[seen_cells], rtol=0, atol=1e-6)  # the cubic within: alike
    with pytest.raises(ValueError, match="cubic limit must be one of clip, linear"):
        SmoothingOptions(limit="spline")


def test_that_an_unknown_fit_is_refused():
    with pytest.raises(ValueError, match="surface fit"):
        fit_heights(np.zeros((5, 3)), Grid(10, 10, 1.0), "spline")


def swaths(gap_x_m: float, gap_y_m: float, line_spacing_m: float = 1.5) -> np.ndarray:
    """Sweep-like points over a 30 x 20 m floor: lines across y every line_spacing_m of x, a point every
    5 cm, on a smooth mound, with no points in the corner [0, gap_x_m) x [0, gap_y_m) (unseen). Jittered by
    a millimetre (as flown points are): a lattice's co-circular points have no unique triangulation."""
    x, y = np.meshgrid(np.append(np.arange(0.0, 30.0, line_spacing_m), 30.0), np.linspace(0.0, 20.0, 401),
                       indexing="ij")
    jitter = np.random.default_rng(1).uniform(-1e-3, 1e-3, (2, *x.shape))
    x, y = np.clip(x + jitter[0], 0.0, 30.0), np.clip(y + jitter[1], 0.0, 20.0)
    keep = ~((x < gap_x_m) & (y < gap_y_m))
    x, y = x[keep], y[keep]
    z = 3.0 * np.exp(-((x - 12.0) ** 2 + (y - 8.0) ** 2) / 40.0) + 0.3 * np.sin(y)
    return np.column_stack([x, y, z])


@pytest.mark.parametrize("method", ["cubic-limited", "cubic", "linear"])
@pytest.mark.parametrize("gap_m", [(3.0, 2.0), (12.0, 9.0)])
def test_that_the_fit_from_the_shaping_points_equals_the_whole_clouds_in_the_wanted_cells(method, gap_m):
    """The wall-contact fit is needed only in the unseen cells: triangulating only the points near them
    must give the same surface there as triangulating the whole cloud (to the interpolator's own tolerance)."""
    pts = swaths(*gap_m)
    g = Grid(30, 20, 0.25)
    full = fit_heights(pts, g, method)
    nodes = np.array([[0.0, y, 1.0] for y in np.arange(0.01, 20.0, 0.53)]
                     + [[x, 0.0, 0.5] for x in np.arange(0.02, 30.0, 0.47)])  # wall contacts, off the lattice
    with_nodes = np.vstack([pts, nodes])
    wanted = ~np.isfinite(full)
    near = shaping_points(with_nodes[:, :2], wanted, g)
    assert 0 < near.sum() < len(with_nodes)  # a real subset: the far side of the building is left out
    whole, part = fit_heights(with_nodes, g, method), fit_heights(with_nodes[near], g, method)
    assert np.isfinite(whole[wanted]).all()
    np.testing.assert_allclose(part[wanted], whole[wanted], atol=1e-4)
    np.testing.assert_array_equal(fit_heights(with_nodes, g, method, wanted=wanted), part)  # what wanted= does


@pytest.mark.parametrize("gap_m", [(3.0, 2.0), (12.0, 9.0)])
def test_that_the_estimated_fit_asked_for_some_cells_equals_the_whole_fit_there(gap_m):
    """``local-linear`` with wanted cells: every point is smoothed, then only the nodes near the wanted cells
    carry the surface; there it is the surface through every node, to a millimetre (the cubic's gradients are
    estimated over all its nodes and iterated to a tolerance; measured: 0.12 mm at most here, and 1e-7 of the
    volume on flown surveys). With scipy's slopes: the GP's process is fitted over every node, so a subset of the
    nodes is refused rather than given another surface."""
    pts = swaths(*gap_m)
    g = Grid(30, 20, 0.25)
    sigma = np.full(len(pts), 0.02)
    scipy_slopes = SmoothingOptions(slopes=NodeSlopes.CURVATURE)
    wanted = ~np.isfinite(fit_heights(pts, g, "local-linear", sigma))
    nodes = np.array([[0.0, y, 1.0] for y in np.arange(0.01, 20.0, 0.53)])
    with_nodes, s_all = np.vstack([pts, nodes]), np.concatenate([sigma, np.full(len(nodes), 0.05)])
    whole = fit_heights(with_nodes, g, "local-linear", s_all, scipy_slopes)
    part = fit_heights(with_nodes, g, "local-linear", s_all, scipy_slopes, wanted=wanted)
    assert np.isfinite(whole[wanted]).any() and np.isnan(part[~wanted]).any()  # a real subset
    np.testing.assert_allclose(part[wanted], whole[wanted], atol=1e-3, equal_nan=True)
    for slopes in (NodeSlopes.GP, NodeSlopes.GP_BRIDGES):
        with pytest.raises(ValueError, match="takes scipy's slopes"):
            fit_heights(with_nodes, g, "local-linear", s_all, SmoothingOptions(slopes=slopes), wanted=wanted)


def test_that_sparse_points_make_every_point_shape_the_fit():
    """Where the sweep lines are half the building apart, the reach from the middle takes the whole cloud."""
    pts = swaths(0.0, 0.0, line_spacing_m=15.0)
    g = Grid(30, 20, 0.25)
    wanted = np.zeros(g.shape, dtype=bool)
    wanted[58:62, 38:42] = True
    assert shaping_points(pts[:, :2], wanted, g).all()
    assert not shaping_points(pts[:, :2], np.zeros(g.shape, dtype=bool), g).any()


def test_that_a_surface_with_the_gps_slopes_brings_the_same_nodes_surface_with_scipys_slopes():
    """`fit_surface`: with the GP's slopes, scipy_slopes_m is the cubic through the same nodes with scipy's slopes,
    the `curvature` surface to the bit (the unseen term takes its edge slope from it); with scipy's own, None."""
    from ground.surface import fit_surface

    rng = np.random.default_rng(3)
    pts = swaths(12.0, 9.0)
    pts = pts + np.column_stack([np.zeros((len(pts), 2)), rng.normal(0, 0.05, len(pts))])
    g = Grid(30, 20, 0.25)
    sigma = np.full(len(pts), 0.05)
    plain = fit_surface(pts, g, "local-linear", sigma, SmoothingOptions(slopes=NodeSlopes.CURVATURE))
    assert plain.scipy_slopes_m is None
    for slopes in (NodeSlopes.GP, NodeSlopes.GP_BRIDGES):
        fit = fit_surface(pts, g, "local-linear", sigma, SmoothingOptions(slopes=slopes))
        np.testing.assert_array_equal(fit.scipy_slopes_m, plain.heights_m)
        assert np.nanmax(np.abs(fit.heights_m - plain.heights_m)) > 1e-3  # the GP's slopes did change the surface


def test_that_the_cells_a_hull_bridges_beyond_the_seen_radius_are_told_apart_from_the_seen_and_the_filled():
    # 0.25 m cells with points in every fitted cell but a 3 x 2.5 m hole (rows 10-21, columns 10-19); the last four
    # columns are outside the hull (not fitted) and hold none
    counts = np.ones((40, 40), dtype=int)
    counts[10:22, 10:20] = 0
    fitted = np.ones((40, 40), dtype=bool)
    fitted[:, 36:] = False
    counts[:, 36:] = 0
    bridged = bridged_cells(counts, fitted, (0.25, 0.25))
    # bridged: more than 1 m (four cells) from the nearest cell with points, so five cells in from every edge
    expected = np.zeros((40, 40), dtype=bool)
    expected[14:18, 14:16] = True
    assert np.array_equal(bridged, expected)
    assert not bridged_cells(counts, fitted, (0.25, 0.25), radius_m=1.5).any()  # a wider radius sees it all
    assert np.array_equal(bridged_cells(np.zeros((4, 4)), np.eye(4, dtype=bool), (1.0, 1.0)), np.eye(4, dtype=bool))


def test_that_flat_cells_are_the_cells_histogram2d_counts_and_sums_in_to_the_bit():
    """The sweeps' check sums the points' heights per cell once a candidate of the servo's timing search: one cell
    lookup for both sums, the same sums as two histograms (the last edge in the last cell, nothing off the floor)."""
    g = Grid(60.0, 40.0, 0.25)
    rng = np.random.default_rng(5)
    p = np.column_stack([rng.uniform(-1.0, 61.0, 5000), rng.uniform(-1.0, 41.0, 5000), rng.normal(3.0, 2.0, 5000)])
    p[:4, :2] = [[60.0, 40.0], [0.0, 0.0], [60.0, 12.3], [0.25, 40.0]]  # on the edges, the far ones included
    p[4:6, 0] = np.nan, np.inf
    cell = g.flat_cells(p)
    size = g.shape[0] * g.shape[1]
    bins = (g.x_edges, g.y_edges)
    count, _, _ = np.histogram2d(p[:, 0], p[:, 1], bins=bins)
    height, _, _ = np.histogram2d(p[:, 0], p[:, 1], bins=bins, weights=p[:, 2])
    assert np.array_equal(g.cell_sums(cell), count) and np.array_equal(g.counts(p), count)
    assert np.array_equal(g.cell_sums(cell, p[:, 2]), height)
    assert cell[0] == size - 1 and cell[1] == 0 and np.all(cell[4:6] == -1)
