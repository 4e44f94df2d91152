"""The GeoTIFF export, read back by rasterio: the report's grid, NaN nodata, placed on Earth by the site."""

import numpy as np
import pytest
import rasterio
from rasterio.warp import transform

from firmware_py.core.frames import StorageFrame
from firmware_py.core.geodesy import ned_to_wgs84
from ground.exports.raster import raster_rows, write_geotiff
from ground.surface import Grid
from tests.ground.exports.conftest import SITE, STORAGE


def _utm_of_w(x_m: float, y_m: float) -> tuple[float, float]:
    """W -> NED about the corner (the frame) -> lat/lon (the core's scalar tangent plane) -> UTM 56S (PROJ)."""
    n, e, _ = StorageFrame(heading_rad=SITE.heading_rad).w_to_ned(np.array([[x_m, y_m, 0.0]]))[0]
    lat, lon = ned_to_wgs84(n, e, SITE.corner.lat_deg, SITE.corner.lon_deg)
    east, north = transform("EPSG:4326", "EPSG:32756", [lon], [lat])
    return east[0], north[0]


@pytest.fixture(scope="module")
def tif(flown):
    with rasterio.open(flown.report_dir / "surface.tif") as src:
        yield src, src.read(1)


def test_that_the_raster_is_the_reports_grid_as_altitudes(flown, tif):
    src, band = tif
    nx, ny = flown.survey.grid.shape
    assert band.shape == (ny, nx) and src.count == 1 and src.dtypes[0] == "float32"
    assert np.isnan(src.nodata)
    want = raster_rows(flown.survey.heights) + SITE.corner.alt_m
    assert np.array_equal(np.isnan(band), np.isnan(want))
    assert band == pytest.approx(want.astype(np.float32), abs=1e-5, nan_ok=True)
    assert float(src.tags()["PILESCAN_FLOOR_ALTITUDE_M"]) == SITE.corner.alt_m
    # the top row is the far side (y = width), column 0 the x = 0 end: the cone's peak cell lands where it stands
    row, col = np.unravel_index(np.nanargmax(band), band.shape)
    x, y = (col + 0.5) * STORAGE.length_m / nx, STORAGE.width_m - (row + 0.5) * STORAGE.width_m / ny
    assert np.hypot(x - 15.0, y - 10.0) < 1.0


def test_that_pixel_corners_map_to_the_buildings_corners_within_2_cm(flown, tif):
    src, _ = tif
    assert src.crs.to_epsg() == 32756 or "UTM zone 56S" in src.crs.to_wkt()
    nx, ny = flown.survey.grid.shape
    L, W = STORAGE.length_m, STORAGE.width_m
    for (col, row), (x, y) in {(0, 0): (0.0, W), (0, ny): (0.0, 0.0), (nx, ny): (L, 0.0), (nx, 0): (L, W),
                               (nx / 2, ny / 2): (L / 2, W / 2)}.items():
        got = src.transform @ (col, row)
        want = _utm_of_w(x, y)
        assert np.hypot(got[0] - want[0], got[1] - want[1]) < 0.02, (col, row)
    # the building is turned 30 deg from north and the grid further by the UTM convergence: not a north-up image
    assert abs(src.transform.b) > 0.05 * abs(src.transform.a)


def test_that_without_a_site_the_raster_is_in_the_storage_frame_and_says_so(tmp_path):
    grid = Grid(6.0, 4.0, 0.5)
    h = np.arange(12 * 8, dtype=float).reshape(12, 8)
    h[3, 2] = np.nan
    with rasterio.open(write_geotiff(h, grid, tmp_path / "s.tif")) as src:
        band = src.read(1)
        assert src.crs is None
        assert tuple(src.transform)[:6] == pytest.approx((0.5, 0.0, 0.0, 0.0, -0.5, 4.0))
        assert "storage frame W" in src.tags()["PILESCAN_FRAME"]
        assert "above the floor" in src.tags()["PILESCAN_VALUES"]
    assert band[8 - 1 - 2, 3] != band[8 - 1 - 2, 3]  # the NaN cell, at row ny-1-iy, column ix
    assert band[0, 0] == h[0, 7] and band[7, 11] == h[11, 0]  # top-left is (x 0, y far); bottom-right (x far, y 0)
    assert src.transform @ (0, 8) == pytest.approx((0.0, 0.0))  # the storage corner
