"""The surface as a GeoTIFF (float32, one band, NaN nodata), read by QGIS, ArcGIS, GDAL, rasterio.

One pixel per grid cell of the report (its cell size, its cells), holding the height the report's volume
sums (`Survey.heights`: after the empty-cell policy; NaN where no height was defined, which is nodata). Columns
run along W's x (the length), rows along -y, so the top row is the building's far side (y = W's width) and
pixel (0, 0)'s outer corner is W's point (0, width): with heading 90 deg (x east) that is an ordinary north-up
image.

- Without a site in the log header: no CRS (W is a local engineering frame no EPSG code names); the affine
  transform maps pixels to W metres, and the tags say so. Values: heights above the floor, m.
- With a site: the CRS is the site's UTM zone + MSL height (`ground.exports.georef`), the affine transform
  maps pixels to easting/northing, rotated by the building's heading and the UTM grid convergence (GeoTIFF
  writes a rotated transform as a ModelTransformation tag; GDAL and QGIS read it), and the values are
  altitudes above mean sea level (the corner's altitude + height), so the raster overlays the UTM LAS in
  3-D; the tag PILESCAN_FLOOR_ALTITUDE_M gives the floor to subtract. The transform is fitted through three
  corners; its error at the fourth (sub-millimetre over a building: the projection is affine at that scale)
  is in the tag PILESCAN_AFFINE_RESIDUAL_M.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ground.exports.formats import ExportFormat, need
from ground.exports.georef import Georef
from ground.surface import Grid


def raster_rows(heights: np.ndarray) -> np.ndarray:
    """heights[ix, iy] -> image[row, col] with col = ix and row = ny - 1 - iy (module docstring)."""
    return np.asarray(heights, dtype=float).T[::-1, :]


def local_transform(grid: Grid):
    """The affine pixel -> W metres: x = col * cx, y = width - row * cy."""
    from rasterio.transform import Affine

    nx, ny = grid.shape
    return Affine(grid.length_m / nx, 0.0, 0.0, 0.0, -grid.width_m / ny, grid.width_m)


def georeferenced_transform(grid: Grid, georef: Georef):
    """The affine pixel -> UTM metres through three of the building's corners, and its error (m) at the
    fourth: (transform, residual_m)."""
    from rasterio.transform import Affine

    nx, ny = grid.shape
    L, W = grid.length_m, grid.width_m
    e, n, _ = georef.w_to_utm(np.array([[0.0, W, 0.0], [L, W, 0.0], [0.0, 0.0, 0.0], [L, 0.0, 0.0]]))
    t = Affine((e[1] - e[0]) / nx, (e[2] - e[0]) / ny, e[0], (n[1] - n[0]) / nx, (n[2] - n[0]) / ny, n[0])
    e4, n4 = t.a * nx + t.b * ny + t.c, t.d * nx + t.e * ny + t.f  # the fourth corner, (L, 0)
    return t, float(np.hypot(e4 - e[3], n4 - n[3]))


def write_geotiff(heights: np.ndarray, grid: Grid, out: Path, georef: Georef | None = None) -> Path:
    """Write the height grid (module docstring) to out."""
    rasterio = need("rasterio", ExportFormat.TIF)
    image = raster_rows(heights)
    tags = {"PILESCAN_GRID_CELLS": f"{grid.shape[0]} x {grid.shape[1]} (x along the length, y along the width)",
            "PILESCAN_STORAGE_TRANSFORM": " ".join(f"{v:.12g}" for v in tuple(local_transform(grid))[:6]),
            "PILESCAN_NODATA": "NaN: no surface height defined for the cell"}
    if georef is None:
        transform, crs = local_transform(grid), None
        tags["PILESCAN_FRAME"] = ("storage frame W, metres: x along the building's length, y along its width from "
                                  "the floor corner; no CRS (the log header has no site)")
        tags["PILESCAN_VALUES"] = "height above the floor, m"
    else:
        transform, residual = georeferenced_transform(grid, georef)
        crs = rasterio.crs.CRS.from_user_input(georef.crs_text)
        image = image + georef.site.corner.alt_m
        tags["PILESCAN_FRAME"] = (f"WGS 84 / UTM zone {georef.utm_zone}{'N' if georef.utm_epsg < 32700 else 'S'}; "
                                  f"site {georef.site.describe()}")
        tags["PILESCAN_VALUES"] = "altitude above mean sea level, m (height above the floor + the floor's altitude)"
        tags["PILESCAN_FLOOR_ALTITUDE_M"] = f"{georef.site.corner.alt_m:.6g}"
        tags["PILESCAN_AFFINE_RESIDUAL_M"] = f"{residual:.3g}"
    out.parent.mkdir(parents=True, exist_ok=True)
    profile = {"driver": "GTiff", "width": image.shape[1], "height": image.shape[0], "count": 1,
               "dtype": "float32", "nodata": float("nan"), "transform": transform, "crs": crs,
               "compress": "deflate", "predictor": 3}
    with rasterio.open(out, "w", **profile) as dst:
        dst.write(image.astype(np.float32), 1)
        dst.update_tags(**tags)
        dst.set_band_description(1, tags["PILESCAN_VALUES"])
    return out
