"""Contours: nice levels, lines where the surface crosses them, GeoJSON in W and WGS-84, drawn on a map."""

import json
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from firmware_py.core.geodesy import ned_to_wgs84
from firmware_py.core.site import Site
from ground.exports.contours import (
    MAX_LINES,
    Contour,
    contour_levels,
    contour_lines,
    contours_geojson,
    draw_contours,
    nice_interval_m,
)
from ground.exports.georef import Georef
from ground.surface import Grid
from tests.ground.exports.conftest import SITE


@given(st.floats(0.001, 500.0))
def test_that_the_interval_is_nice_and_gives_7_to_15_levels(hi_m):
    step = nice_interval_m(0.0, hi_m)
    mantissa = step / 10.0 ** math.floor(math.log10(step) + 1e-9)
    assert round(mantissa, 6) in (1.0, 2.0, 2.5, 5.0)
    n = len(contour_levels(np.array([[0.0, hi_m]])))
    assert 7 <= n <= MAX_LINES


def test_that_a_surface_that_never_rises_has_no_contours():
    assert nice_interval_m(0.0, 0.0) is None and nice_interval_m(1.0, 1.0) is None
    assert contour_levels(np.full((3, 3), -0.01)).size == 0
    assert contour_levels(np.full((3, 3), np.nan)).size == 0
    grid = Grid(3.0, 3.0, 1.0)
    assert contour_lines(np.zeros(grid.shape), grid) == []


def test_that_a_cones_contours_are_circles_of_the_right_radius():
    grid = Grid(20.0, 20.0, 0.1)
    x, y = grid.centres()
    h = np.maximum(0.0, 6.0 - np.hypot(x - 10.0, y - 10.0))  # a 6 m cone of 45 deg slopes
    contours = contour_lines(h, grid)
    assert [c.level_m for c in contours] == pytest.approx(list(np.arange(0.5, 6.0, 0.5)))
    for c in contours:
        (line,) = c.lines
        r = np.hypot(line[:, 0] - 10.0, line[:, 1] - 10.0)
        assert r == pytest.approx(6.0 - c.level_m, abs=0.05)


def test_that_the_report_writes_the_levels_of_its_surface_in_both_frames(flown):
    w = json.loads((flown.report_dir / "contours.geojson").read_text())
    g = json.loads((flown.report_dir / "contours_wgs84.geojson").read_text())
    levels = sorted({f["properties"]["height_m"] for f in w["features"]})
    assert levels == pytest.approx(list(contour_levels(flown.survey.heights)))
    assert 7 <= len(levels) <= MAX_LINES and "storage frame W" in w["pilescan_frame"]
    top = float(np.nanmax(flown.survey.heights))  # the 4 m cone: 0.5 m steps (0.25 would need 16 levels)
    assert w["pilescan_interval_m"] == pytest.approx(0.5 if top > 4.0 else 0.25)
    assert len(g["features"]) == len(w["features"]) and "pilescan_frame" not in g
    for fw, fg in zip(w["features"], g["features"], strict=True):
        assert fw["geometry"]["type"] == fg["geometry"]["type"] == "LineString"
        cw, cg = np.array(fw["geometry"]["coordinates"]), np.array(fg["geometry"]["coordinates"])
        assert cw.shape == cg.shape and np.all(cw[:, 2] == fw["properties"]["height_m"])
        assert fg["properties"]["elevation_m"] == pytest.approx(SITE.corner.alt_m + fw["properties"]["height_m"])
        lon, lat, _ = Georef(SITE).w_to_lonlat_alt(np.column_stack([cw[:, :2], np.zeros(len(cw))]))
        assert cg[:, 0] == pytest.approx(lon, abs=2e-8) and cg[:, 1] == pytest.approx(lat, abs=2e-8)


def test_that_the_vectorised_mapping_is_the_cores_scalar_one():
    pts = np.array([[0.0, 0.0, 0.0], [30.0, 0.0, 1.0], [0.0, 20.0, 2.0], [30.0, 20.0, 3.0]])
    lon, lat, alt = Georef(SITE).w_to_lonlat_alt(pts)
    for (x, y, z), a, b, c in zip(pts, lon, lat, alt, strict=True):
        n = x * math.cos(SITE.heading_rad) + y * math.sin(SITE.heading_rad)
        e = x * math.sin(SITE.heading_rad) - y * math.cos(SITE.heading_rad)
        assert (b, a) == pytest.approx(ned_to_wgs84(n, e, SITE.corner.lat_deg, SITE.corner.lon_deg), abs=1e-12)
        assert c == SITE.corner.alt_m + z


def test_that_without_a_site_the_geojson_says_its_frame():
    grid = Grid(4.0, 4.0, 0.5)
    x, y = grid.centres()
    doc = contours_geojson(contour_lines(np.maximum(0.0, 2.0 - np.hypot(x - 2, y - 2)), grid))
    assert doc["features"] and "not WGS-84" in doc["pilescan_frame"]


def test_that_contours_are_drawn_and_labelled_once_per_level():
    grid = Grid(20.0, 20.0, 0.25)
    x, y = grid.centres()
    contours = contour_lines(np.maximum(0.0, 6.0 - np.hypot(x - 10.0, y - 10.0)), grid)
    fig = Figure()
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    draw_contours(ax, contours)
    assert len(ax.collections) == 1 and len(ax.collections[0].get_segments()) == len(contours)
    assert [t.get_text() for t in ax.texts] == [f"{c.level_m:.1f}" for c in contours]
    fig.canvas.draw()


def test_that_a_contour_across_the_antimeridian_is_cut_there_not_drawn_round_the_globe():
    site = Site.of(-17.0, 179.9998, 10.0, 90.0)  # x east: the 180th meridian 22 m along the building
    line = np.column_stack([np.linspace(0.0, 60.0, 31), np.full(31, 5.0)])
    doc = contours_geojson([Contour(1.0, (line,))], Georef(site))
    geom = doc["features"][0]["geometry"]
    assert geom["type"] == "MultiLineString" and len(geom["coordinates"]) == 2
    west, east = (np.array(p) for p in geom["coordinates"])
    assert west[-1, 0] == 180.0 and east[0, 0] == -180.0 and west[-1, 1] == east[0, 1]  # meets itself on the line
    for part in (west, east):
        assert np.all(np.abs(np.diff(part[:, 0])) < 1.0)  # no jump of 360 deg inside a part
    assert len(west) + len(east) == 31 + 2
    plain = contours_geojson([Contour(1.0, (line,))], Georef(Site.of(-17.0, 100.0, 10.0, 90.0)))
    assert plain["features"][0]["geometry"]["type"] == "LineString"
