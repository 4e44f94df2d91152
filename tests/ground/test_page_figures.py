"""The customer's figures: a labelled map (contours, pile names at centroids, scale bar, north arrow, the
flight path's legend inside the axes), a 3D view with its exaggeration stated and its cost bounded, and
cross-sections through the largest pile's peak with the points near each line."""

from __future__ import annotations

import math

import numpy as np
import pytest
from matplotlib.contour import ContourSet
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from ground import page_figures as pf
from ground.piles import PileOptions, pile_table
from ground.surface import Grid

GRID = Grid(40.0, 20.0, 0.25)
LW = (GRID.length_m, GRID.width_m)


def cone(cx: float, cy: float, r: float, h: float) -> np.ndarray:
    xc = 0.5 * (GRID.x_edges[:-1] + GRID.x_edges[1:])
    yc = 0.5 * (GRID.y_edges[:-1] + GRID.y_edges[1:])
    x, y = np.meshgrid(xc, yc, indexing="ij")
    return np.clip(h * (1 - np.hypot(x - cx, y - cy) / r), 0, None)


def cone_of(peak_m: float, side_m: float) -> np.ndarray:
    """A cone peak_m high in the middle of a side_m x side_m / 2 floor on 80 x 40 cells."""
    g = Grid(side_m, side_m / 2, side_m / 80)
    x, y = np.meshgrid(0.5 * (g.x_edges[:-1] + g.x_edges[1:]), 0.5 * (g.y_edges[:-1] + g.y_edges[1:]), indexing="ij")
    return np.clip(peak_m * (1 - np.hypot(x - side_m / 2, y - side_m / 4) / (side_m / 5)), 0, None)


def two_piles() -> tuple[np.ndarray, dict]:
    """A small cone at x = 10 and a large one at x = 28: the large one is the sections' pile."""
    h = np.maximum(cone(10.0, 10.0, 5.0, 3.0), cone(28.0, 9.0, 8.0, 6.0))
    return h, pile_table(h, GRID, 0.03, PileOptions(), None)


def map_legend(fig):
    """The site map's one legend: the figure's, under the map."""
    assert len(fig.legends) == 1 and fig.axes[0].get_legend() is None
    return fig.legends[0]


def test_that_contours_step_1_2_5_from_above_the_floor_to_the_peak():
    assert pf.nice_step(7.3, 8) == 1.0 and pf.nice_step(0.9, 8) == 0.2 and pf.nice_step(40, 8) == 5.0
    levels = pf.contour_levels(np.array([[-0.04, 0.02], [3.1, 7.3]]))
    assert levels == pytest.approx([1, 2, 3, 4, 5, 6, 7])  # none at the floor's noise
    assert pf.contour_levels(np.full((3, 3), 2.0)).size == 0
    assert pf.contour_levels(np.full((3, 3), np.nan)).size == 0


def test_that_heights_are_exaggerated_by_a_1_2_5_factor_only_when_the_pile_is_flat():
    assert pf.vertical_exaggeration(15.0, (60.0, 40.0)) == 1.0  # 15 m on 60 m: already a quarter
    assert pf.vertical_exaggeration(7.0, (60.0, 40.0)) == 2.0  # wants 2.1
    assert pf.vertical_exaggeration(1.0, (60.0, 40.0)) == 10.0  # wants 15
    assert pf.vertical_exaggeration(0.0, (60.0, 40.0)) == 1.0


@pytest.mark.parametrize("heading, north", [(0, (1, 0)), (90, (0, 1)), (180, (-1, 0)), (-90, (0, -1))])
def test_that_north_in_the_frame_follows_the_x_axis_heading(heading, north):
    """x at `heading` clockwise from north, y 90 deg to its left: at 90 deg, x points east and y north."""
    assert pf.north_in_frame(heading) == pytest.approx(north, abs=1e-12)


def test_that_the_map_names_each_pile_at_its_centroid_with_contours_scale_bar_north_and_path_legend_under_it():
    h, piles = two_piles()
    path = np.column_stack([np.linspace(2, 38, 50), np.full(50, 10.0)])
    fig = pf.site_map_figure(GRID.x_edges, GRID.y_edges, h, LW, piles, heading_deg=30.0, path_w=path)
    ax = fig.axes[0]
    labels = {t.get_text().split("\n")[0]: t.get_position() for t in ax.texts}
    for p in piles["piles"]:
        assert labels[p["label"]] == pytest.approx(tuple(p["centroid_xy_m"]))
    assert any(f"{piles['piles'][0]['volume_m3']:,.0f} m³" in t.get_text() for t in ax.texts)
    cs = [c for c in ax.collections if isinstance(c, ContourSet)]
    assert len(cs) == 1 and list(cs[0].levels) == pytest.approx([1, 2, 3, 4, 5])
    assert any(isinstance(a, AnchoredSizeBar) for a in ax.artists)
    assert "30° from north" in ax.get_title()
    compass = [t for a in ax.child_axes for t in a.texts if t.get_text() == "N"]
    assert len(compass) == 1
    n = compass[0].get_position()
    assert math.degrees(math.atan2(n[1], n[0])) == pytest.approx(30.0)
    fig.canvas.draw()
    leg, frame = map_legend(fig).get_window_extent(), ax.get_window_extent()
    assert leg.y1 <= frame.y0 and frame.x0 <= leg.x0 and leg.x1 <= frame.x1  # under the map, hiding none of it
    assert [t.get_text() for t in map_legend(fig).get_texts()] == ["flight path"]


def test_that_the_maps_legend_of_path_filled_ground_and_outlines_stays_off_the_map_and_on_the_page():
    """Inside the map the three entries hid a corner of the ground they name (the demo's pile top at 30 % P_traj)."""
    from ground.piles import find_piles
    h, piles = two_piles()
    filled = np.zeros(h.shape, bool)
    filled[:8, :] = True
    path = np.column_stack([np.linspace(2, 38, 50), np.full(50, 10.0)])
    fig = pf.site_map_figure(GRID.x_edges, GRID.y_edges, h, LW, piles, heading_deg=0.0, path_w=path, filled=filled,
                             pile_labels=find_piles(h, GRID, 0.03, PileOptions()).labels)
    ax = fig.axes[0]
    fig.canvas.draw()
    leg = map_legend(fig)
    box, frame, page = leg.get_window_extent(), ax.get_window_extent(), fig.bbox
    assert len(leg.get_texts()) == 3
    assert not box.overlaps(frame) and box.y1 <= frame.y0
    assert page.x0 <= box.x0 and box.x1 <= page.x1 and page.y0 <= box.y0
    xlabel = ax.xaxis.label.get_window_extent()
    assert not box.overlaps(xlabel)
    outline = [hd for hd, t in zip(leg.legend_handles, leg.get_texts(), strict=True) if t.get_text().startswith("pile")]
    assert outline[0].get_path_effects()  # drawn with the map's dark edge: white alone is lost on the page


def test_that_a_pile_label_under_the_scale_bar_or_the_compass_is_moved_clear_of_them():
    # a 13 m³ heap in the corner at (1.5, 0.8) m was named under the scale bar's box, which is drawn over the map
    h = np.maximum(cone(1.5, 0.8, 3.0, 1.0), cone(2.0, 18.5, 3.0, 1.0))
    piles = pile_table(h, GRID, 0.03, PileOptions(), None)
    fig = pf.site_map_figure(GRID.x_edges, GRID.y_edges, h, LW, piles, heading_deg=0.0)
    ax = fig.axes[0]
    fig.canvas.draw()
    covers = [a.get_window_extent() for a in ax.artists if isinstance(a, AnchoredSizeBar)]
    covers += [a.get_window_extent() for a in ax.child_axes]  # the compass
    labels = [t for t in ax.texts if t.get_text().startswith("P")]
    assert len(labels) == 2
    for t in labels:
        box = t.get_window_extent()
        assert not any(box.overlaps(c) for c in covers), t.get_text()


def test_that_the_map_outlines_each_pile_as_the_table_sums_it():
    from matplotlib.collections import LineCollection

    from ground.piles import find_piles
    h, piles = two_piles()
    labels = find_piles(h, GRID, 0.03, PileOptions()).labels
    fig = pf.site_map_figure(GRID.x_edges, GRID.y_edges, h, LW, piles, pile_labels=labels)
    ax = fig.axes[0]
    outline = [c for c in ax.collections if isinstance(c, LineCollection) and "pile outline" in str(c.get_label())]
    assert len(outline) == 1
    segs = np.asarray(outline[0].get_segments())
    for p in piles["piles"]:  # each pile's outline encloses its centroid, within its extent
        (x0, x1), (y0, y1) = p["extent_m"]["x"], p["extent_m"]["y"]
        near = segs[(segs[:, :, 0].min(axis=1) >= x0 - 1e-9) & (segs[:, :, 0].max(axis=1) <= x1 + 1e-9)
                    & (segs[:, :, 1].min(axis=1) >= y0 - 1e-9) & (segs[:, :, 1].max(axis=1) <= y1 + 1e-9)]
        assert len(near) > 20
    assert "pile outline (the cells its volume sums)" in [t.get_text() for t in map_legend(fig).get_texts()]
    with pytest.raises(ValueError, match="pile_labels shape"):
        pf.site_map_figure(GRID.x_edges, GRID.y_edges, h, LW, piles, pile_labels=labels[:-1])


def test_that_the_map_outlines_the_filled_cells_and_names_them_in_its_legend():
    h, piles = two_piles()
    filled = np.zeros(h.shape, bool)
    filled[:8, :] = True  # a 2 m strip along the wall x = 0, never seen
    fig = pf.site_map_figure(GRID.x_edges, GRID.y_edges, h, LW, piles, filled=filled)
    ax = fig.axes[0]
    outline = [c for c in ax.collections if c.get_label() == "filled: never seen"]
    assert len(outline) == 1
    xs = np.concatenate([seg[:, 0] for seg in outline[0].get_segments()])
    assert xs.max() == pytest.approx(2.0)  # the strip's inner edge (and the walls it runs along)
    assert "filled: never seen" in [t.get_text() for t in map_legend(fig).get_texts()]
    plain = pf.site_map_figure(GRID.x_edges, GRID.y_edges, h, LW, piles)
    assert not [c for c in plain.axes[0].collections if c.get_label() == "filled: never seen"]
    assert not plain.legends and plain.axes[0].get_legend() is None
    with pytest.raises(ValueError, match="filled shape"):
        pf.site_map_figure(GRID.x_edges, GRID.y_edges, h, LW, filled=filled[:, :-1])


def test_that_the_map_draws_no_compass_without_a_heading_and_says_so_without_data():
    h, piles = two_piles()
    fig = pf.site_map_figure(GRID.x_edges, GRID.y_edges, h, LW, piles)
    assert not [t for a in fig.axes[0].child_axes for t in a.texts if t.get_text() == "N"]  # no compass
    empty = pf.site_map_figure(GRID.x_edges, GRID.y_edges, np.full(h.shape, np.nan), LW)
    assert any(t.get_text() == "no data" for t in empty.axes[0].texts)


def test_that_the_3d_view_states_its_exaggeration_and_draws_a_bounded_number_of_quads(monkeypatch):
    monkeypatch.setattr(pf, "MAX_3D_CELLS_PER_SIDE", 20)
    h = 0.3 * two_piles()[0]  # 160 x 80 cells, 1.8 m high on a 40 m floor: wants x5.6
    fig = pf.surface_3d_figure(GRID.x_edges, GRID.y_edges, h, LW)
    ax = fig.axes[0]
    assert "vertical exaggeration ×5" in ax.get_title()
    quads = ax.collections[0]
    assert len(quads.get_paths()) <= 20 * 20
    assert ax.get_zlim()[1] == pytest.approx(h.max())  # the block maximum keeps the peak


@pytest.mark.parametrize(("peak_m", "side_m"), [(8.17, 60.0), (0.5, 40.0), (2.0, 40.0), (30.0, 40.0), (0.04, 20.0)])
def test_that_the_3d_views_height_labels_are_spaced_like_its_floors(peak_m, side_m):
    ve = pf.vertical_exaggeration(peak_m, (side_m, side_m / 2))
    g = Grid(side_m, side_m / 2, side_m / 80)
    fig = pf.surface_3d_figure(g.x_edges, g.y_edges, cone_of(peak_m, side_m), (side_m, side_m / 2))
    ax = fig.axes[0]
    ticks = [t for t in ax.get_zticks() if ax.get_zlim()[0] - 1e-9 <= t <= ax.get_zlim()[1] + 1e-9]
    assert len(ticks) >= 2 and min(ticks) == pytest.approx(0.0)  # the floor and one height above it
    # no closer on the drawn axis than the longer floor axis' own labels (about X_TICKS_PER_SIDE of them)
    spacing_drawn = (ticks[1] - ticks[0]) * ve / side_m
    assert len(ticks) == 2 or spacing_drawn >= 1.0 / (pf.X_TICKS_PER_SIDE + 1)
    assert ax.get_xaxis().labelpad >= 8


def test_that_a_flat_surface_gets_one_height_label():
    fig = pf.surface_3d_figure(GRID.x_edges, GRID.y_edges, np.zeros(GRID.shape), LW)
    assert list(fig.axes[0].get_zticks()) == [0.0]


def test_that_coarsening_keeps_each_blocks_highest_cell():
    h = np.zeros((5, 4))
    h[4, 3] = 9.0
    h[0, 0] = np.nan
    out, sx, sy = pf._block_max(h, 2)
    assert (sx, sy) == (3, 2) and out.shape == (2, 2)
    assert out[1, 1] == 9.0 and out[0, 0] == 0.0  # a block with one NaN still has a height


def test_that_the_sections_cross_at_the_largest_piles_peak_with_surface_base_and_nearby_points():
    h, piles = two_piles()
    big = max(piles["piles"], key=lambda p: p["volume_m3"])
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(0, 40, 20000), rng.uniform(0, 20, 20000), rng.uniform(0, 1, 20000)])
    base = np.full(h.shape, 0.2)
    fig = pf.sections_figure(GRID.x_edges, GRID.y_edges, h, LW, pts, base, piles, band_m=0.5)
    ax_x, ax_y = fig.axes
    x0, y0 = big["peak_xy_m"]
    assert f"y = {y0:.1f} m" in ax_x.get_title() and f"x = {x0:.1f} m" in ax_y.get_title()
    surf_x, base_x = ax_x.get_lines()[:2]
    iy = int(y0 / GRID.cell_m)
    assert surf_x.get_ydata() == pytest.approx(h[:, iy]) and base_x.get_ydata() == pytest.approx(0.2)
    assert max(surf_x.get_ydata()) == pytest.approx(big["peak_height_m"])
    shown = ax_x.collections[-1].get_offsets()  # (x, z) of the points within 0.5 m of y = y0
    near = pts[np.abs(pts[:, 1] - y0) <= 0.5]
    assert len(shown) == len(near) and set(np.round(shown[:, 0], 9)) == set(np.round(near[:, 0], 9))
    assert "exaggeration" in fig._suptitle.get_text()


def test_that_the_sections_draw_the_filled_stretches_dashed_and_the_seen_ones_solid():
    h, piles = two_piles()
    filled = np.zeros(h.shape, bool)
    filled[:20, :] = True  # the first 5 m along x: never seen, filled
    ax_x = pf.sections_figure(GRID.x_edges, GRID.y_edges, h, LW, None, None, piles, filled=filled).axes[0]
    lines = {ln.get_label(): ln for ln in ax_x.get_lines()}
    seen, fill = lines["surface"], lines["surface, filled (never seen)"]
    assert np.isnan(seen.get_ydata()[:20]).all() and np.isfinite(seen.get_ydata()[20:]).all()
    assert np.isfinite(fill.get_ydata()[:21]).all() and np.isnan(fill.get_ydata()[21:]).all()  # joined at the end
    assert fill.get_linestyle() != seen.get_linestyle()
    plain = pf.sections_figure(GRID.x_edges, GRID.y_edges, h, LW, None, None, piles).axes[0]
    assert [ln.get_label() for ln in plain.get_lines()] == ["surface", "base"]
    with pytest.raises(ValueError, match="filled shape"):
        pf.sections_figure(GRID.x_edges, GRID.y_edges, h, LW, filled=filled[:-1])


def test_that_the_sections_band_widens_for_a_sparse_survey_but_stays_bounded():
    pts = np.array([[5.0, 5.0, 1.0]] * 3)
    assert pf.section_band_m(pts, 20.0, 10.0, 0.25, 20.0) == pytest.approx(1.0)  # 5 % of 20 m, then stops
    rng = np.random.default_rng(1)
    dense = np.column_stack([rng.uniform(0, 40, 40000), rng.uniform(0, 20, 40000), np.zeros(40000)])  # ~1000 a line
    assert pf.section_band_m(dense, 20.0, 10.0, 0.25, 20.0) == pytest.approx(0.25)


def test_that_the_sections_without_piles_pass_through_the_highest_cell_and_without_data_say_so():
    h = cone(30.0, 5.0, 3.0, 2.0)
    x0, y0, what = pf.section_centre(None, h, GRID.x_edges, GRID.y_edges)
    assert (x0, y0, what) == (pytest.approx(30.0, abs=0.25), pytest.approx(5.0, abs=0.25), "the highest cell")
    fig = pf.sections_figure(GRID.x_edges, GRID.y_edges, np.full(h.shape, np.nan), LW)
    assert all(any(t.get_text() == "no data" for t in ax.texts) for ax in fig.axes)


@pytest.mark.parametrize("draw", [pf.site_map_figure, pf.surface_3d_figure, pf.sections_figure])
def test_that_a_grid_that_does_not_match_its_edges_is_refused_in_one_line(draw):
    with pytest.raises(ValueError, match="needs x_edges"):
        draw(GRID.x_edges, GRID.y_edges, np.ones((3, 3)), LW)
