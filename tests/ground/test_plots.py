"""Report figures: valid PNGs, empty inputs, and grids drawn the right way round."""

from __future__ import annotations

from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest
from matplotlib import colormaps
from matplotlib.collections import LineCollection, QuadMesh
from matplotlib.image import AxesImage

from ground import plots

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
EXPECTED_SHAPE = (
    round(plots.FIGSIZE_IN[1] * plots.DPI),
    round(plots.FIGSIZE_IN[0] * plots.DPI),
    4,
)
L, W = 20.0, 10.0


def assert_valid_png(path: Path, min_bytes: int = 5_000) -> np.ndarray:
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC
    assert len(data) > min_bytes
    img = mpimg.imread(path)
    assert img.shape == EXPECTED_SHAPE
    return img


def texts(fig) -> str:
    return " ".join(t.get_text() for ax in fig.axes for t in ax.texts)


def pixel_rgb(fig, img: np.ndarray, x: float, y: float) -> np.ndarray:
    """RGB (0..1) of the saved PNG at data point (x, y) of the figure's first axes."""
    px, py = fig.axes[0].transData.transform((x, y))
    row = round(img.shape[0] - float(py))
    col = round(float(px))
    return img[row, col, :3]


def scan_cloud(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, n)
    x = 1.0 + 18.0 * t
    y = W / 2 + 4.5 * np.sin(2 * np.pi * 60 * t)
    z = 3.0 * np.exp(-((x - 10) ** 2 / 20 + (y - 5) ** 2 / 8)) + rng.normal(0, 0.01, n)
    return np.c_[x, y, z]


# ------------------------------------------------------------------------------------------- cloud


def test_cloud_top_writes_valid_png(tmp_path):
    pts = scan_cloud(5_000)
    path = np.c_[np.linspace(1, 19, 20), np.full(20, W / 2), np.full(20, 6.0)]
    out = plots.plot_cloud_top(pts, path, (L, W), tmp_path / "cloud.png", title="test cloud")
    assert out == tmp_path / "cloud.png"
    assert_valid_png(out)


def test_cloud_top_figure_contents():
    pts = scan_cloud(2_000)
    fig = plots.cloud_top_figure(pts, pts[:10, :2], (L, W), title="t")
    ax = fig.axes[0]
    assert ax.get_xlabel() == "x [m]" and ax.get_ylabel() == "y [m]"
    assert ax.get_aspect() == 1.0
    # One scatter collection with every point, coloured by z; highest drawn last (seen from above).
    (sc,) = [c for c in ax.collections if len(c.get_offsets()) == len(pts)]
    assert sc.get_array()[-1] == pytest.approx(pts[:, 2].max())
    assert [cax.get_ylabel() for cax in ax.child_axes] == [plots.HEIGHT_LABEL]  # colourbar inset
    assert len(ax.lines) == 1  # flight path
    assert ax.patches  # storage outline


def test_cloud_top_empty_and_no_path(tmp_path):
    fig = plots.cloud_top_figure(np.empty((0, 3)), None, (L, W))
    assert "no data" in texts(fig)
    assert_valid_png(plots.plot_cloud_top(np.empty((0, 3)), None, (L, W), tmp_path / "e.png"), 1_000)
    assert_valid_png(plots.plot_cloud_top([], np.empty((0, 3)), (L, W), tmp_path / "e2.png"), 1_000)


def test_cloud_top_drops_non_finite_points():
    pts = scan_cloud(100)
    pts[::10, 2] = np.nan
    fig = plots.cloud_top_figure(pts, None, (L, W))
    (sc,) = fig.axes[0].collections
    assert len(sc.get_offsets()) == 90


def test_cloud_top_large_cloud_is_binned_not_subsampled(monkeypatch, tmp_path):
    monkeypatch.setattr(plots, "SCATTER_MAX_POINTS", 1_000)
    pts = scan_cloud(5_000)
    fig = plots.cloud_top_figure(pts, None, (L, W), title="big")
    ax = fig.axes[0]
    (im,) = [a for a in ax.get_images() if isinstance(a, AxesImage)]
    assert "5,000 points binned" in ax.get_title()
    assert np.nanmax(im.get_array()) == pytest.approx(pts[:, 2].max())
    img = assert_valid_png(plots.save_png(fig, tmp_path / "big.png"))
    # A spot far from every point stays white (blind spots must show).
    assert np.allclose(pixel_rgb(fig, img, 10.0, 9.9), 1.0)


def test_invalid_storage_raises():
    with pytest.raises(ValueError):
        plots.cloud_top_figure(np.zeros((1, 3)), None, (0.0, W))
    with pytest.raises(ValueError):
        plots.height_map_figure(np.arange(3.0), np.arange(3.0), np.zeros((2, 2)), (L,))


# -------------------------------------------------------------------------------------- height map


def test_height_map_orientation_single_raised_cell(tmp_path):
    # 10 x 5 cells of 2 m; heights are indexed [ix, iy] (x first).
    x_edges = np.linspace(0.0, L, 11)
    y_edges = np.linspace(0.0, W, 6)
    heights = np.zeros((10, 5))
    heights[7, 1] = 5.0  # cell x in [14, 16], y in [2, 4]
    fig = plots.height_map_figure(x_edges, y_edges, heights, (L, W))

    (mesh,) = [c for c in fig.axes[0].collections if isinstance(c, QuadMesh)]
    arr = np.ma.getdata(mesh.get_array()).reshape(5, 10)  # matplotlib's [row=y, col=x]
    assert np.unravel_index(np.argmax(arr), arr.shape) == (1, 7)

    img = assert_valid_png(plots.save_png(fig, tmp_path / "hm.png"))
    top = np.array(colormaps[plots.HEIGHT_CMAP](1.0)[:3])
    bottom = np.array(colormaps[plots.HEIGHT_CMAP](0.0)[:3])
    assert np.allclose(pixel_rgb(fig, img, 15.0, 3.0), top, atol=0.03)
    # Where the cell would land if x or y were flipped, or x and y swapped, the map is low.
    for x, y in [(5.0, 3.0), (15.0, 7.0), (3.0, 5.0)]:
        assert np.allclose(pixel_rgb(fig, img, x, y), bottom, atol=0.03), (x, y)


def test_height_map_nan_cells_are_white(tmp_path):
    x_edges = np.linspace(0.0, L, 11)
    y_edges = np.linspace(0.0, W, 6)
    heights = np.tile(np.linspace(0.0, 2.0, 10)[:, None], (1, 5))
    heights[2, 3] = np.nan  # x in [4, 6], y in [6, 8]
    fig = plots.height_map_figure(x_edges, y_edges, heights, (L, W), title="hm")
    img = assert_valid_png(plots.save_png(fig, tmp_path / "hm.png"))
    assert np.allclose(pixel_rgb(fig, img, 5.0, 7.0), 1.0)
    assert not np.allclose(pixel_rgb(fig, img, 5.0, 3.0), 1.0)
    assert "98.0 %" in fig.axes[0].get_title()


@pytest.mark.parametrize(
    ("xe", "ye", "h"),
    [
        (np.linspace(0, L, 5), np.linspace(0, W, 4), np.full((4, 3), np.nan)),
        (np.array([]), np.array([]), np.empty((0, 0))),
    ],
)
def test_height_map_no_data(tmp_path, xe, ye, h):
    fig = plots.height_map_figure(xe, ye, h, (L, W))
    assert "no data" in texts(fig)
    assert_valid_png(plots.plot_height_map(xe, ye, h, (L, W), tmp_path / "hm.png"), 1_000)


def test_height_map_shape_mismatch_raises():
    with pytest.raises(ValueError, match="x_edges"):
        plots.height_map_figure(np.linspace(0, L, 6), np.linspace(0, W, 11), np.zeros((10, 5)), (L, W))


# ---------------------------------------------------------------------------------------- coverage


def test_mask_boundary_segments_follow_cell_edges():
    xe = np.array([0.0, 1.0, 2.0, 3.0])
    ye = np.array([0.0, 2.0, 4.0])
    single = np.zeros((3, 2), bool)
    single[1, 1] = True
    segs = plots.mask_boundary_segments(xe, ye, single)
    assert segs.shape == (4, 2, 2)
    assert {tuple(p) for s in segs for p in s} == {(1.0, 2.0), (2.0, 2.0), (1.0, 4.0), (2.0, 4.0)}
    block = np.zeros((3, 2), bool)
    block[0:2, 0] = True  # 2 x 1 cells touching the outer border
    assert plots.mask_boundary_segments(xe, ye, block).shape == (6, 2, 2)
    assert plots.mask_boundary_segments(xe, ye, np.zeros((3, 2), bool)).shape == (0, 2, 2)


def test_coverage_plot(tmp_path):
    x_edges = np.linspace(0.0, L, 11)
    y_edges = np.linspace(0.0, W, 6)
    counts = np.full((10, 5), 10)
    counts[0, :] = 0  # x in [0, 2]: no points
    counts[5, 2] = 1000
    mask = counts > 0
    mask[9, :] = False
    fig = plots.coverage_figure(x_edges, y_edges, counts, mask, (L, W), title="Coverage")
    ax = fig.axes[0]
    assert "45 of 50 cells" in ax.get_title() and "90.0 %" in ax.get_title()
    (lc,) = [c for c in ax.collections if isinstance(c, LineCollection) and not isinstance(c, QuadMesh)]
    assert len(lc.get_segments()) == 2 * 8 + 2 * 5  # an 8 x 5 rectangle of cells
    img = assert_valid_png(plots.save_png(fig, tmp_path / "cov.png"))
    assert np.allclose(pixel_rgb(fig, img, 1.0, 5.0), 1.0)  # zero-count cell is white
    assert not np.allclose(pixel_rgb(fig, img, 11.0, 5.0), 1.0)
    out = plots.plot_coverage(x_edges, y_edges, counts, mask, (L, W), tmp_path / "cov2.png")
    assert_valid_png(out)
    # the bridged cells (fitted, no point within the seen radius) in grey, with their own legend entry
    bridged = np.zeros_like(mask)
    bridged[0, 1] = True  # a cell without points: grey, not white
    fig = plots.coverage_figure(x_edges, y_edges, counts, mask, (L, W), bridged=bridged)
    img = assert_valid_png(plots.save_png(fig, tmp_path / "cov3.png"))
    assert np.allclose(pixel_rgb(fig, img, 1.0, 3.0), 0.78, atol=0.02)  # cell (0, 1), 2 m cells: grey
    assert np.allclose(pixel_rgb(fig, img, 1.0, 5.0), 1.0)  # cell (0, 2): still white
    assert "bridged: no point within 1 m" in [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    with pytest.raises(ValueError, match="bridged shape"):
        plots.coverage_figure(x_edges, y_edges, counts, mask, (L, W), bridged=bridged[:, :2])


@pytest.mark.parametrize(("most", "named"), [(8, ["1", "2", "3", "4", "6"]), (2000, ["1", "10", "100", "1000"])])
def test_that_the_coverage_bar_names_counts_as_plain_numbers(most, named):
    """A sparse survey's bar runs 1-8 points a cell: "2, 3, 4, 6", not a log axis's "2 x 10^0"; a dense one's names
    its decades only, so its ticks do not crowd."""
    counts = np.ones((10, 5), dtype=int)
    counts[5, 2] = most
    fig = plots.coverage_figure(np.linspace(0.0, L, 11), np.linspace(0.0, W, 6), counts, counts > 0, (L, W))
    fig.canvas.draw()
    bar = fig.axes[0].child_axes[0]
    labels = [t.get_text() for t in bar.yaxis.get_ticklabels(which="both")
              if t.get_text() and 1.0 <= t.get_position()[1] <= most]
    assert sorted(labels, key=float) == named


@pytest.mark.parametrize("empty_grid", [True, False])
def test_coverage_no_data(tmp_path, empty_grid):
    if empty_grid:
        xe, ye, c = np.array([]), np.array([]), np.zeros((0, 0), int)
    else:
        xe, ye, c = np.linspace(0, L, 5), np.linspace(0, W, 4), np.zeros((4, 3), int)
    fig = plots.coverage_figure(xe, ye, c, c > 0, (L, W))
    assert "no data" in texts(fig)
    assert_valid_png(plots.plot_coverage(xe, ye, c, c > 0, (L, W), tmp_path / "c.png"), 1_000)


def test_coverage_mask_shape_mismatch_raises():
    with pytest.raises(ValueError, match="surface_mask"):
        plots.coverage_figure(
            np.linspace(0, L, 5), np.linspace(0, W, 4), np.ones((4, 3)), np.ones((3, 4), bool), (L, W)
        )
