"""Huge point clouds (2D and 3D scanning LiDARs) into the volume computation, in fixed memory.

A 3D LiDAR returns tens of millions of points per flight; the 0.25 m volume grid needs a few
hundred thousand. `HeightBinner` streams the points chunk by chunk: wall and roof points are
removed exactly as for the 1D LiDAR (`ground.pointcloud.structure_mask`), the rest are summed
into fine floor bins, and the per-bin mean points go to the same surface fit and volume as
`ground.report.survey_from_samples`.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from firmware_py.core.storage import Storage
from ground.pointcloud import N_SIGMA, Cloud, SensorErrorModel, structure_mask
from ground.report import check_grid_memory
from ground.smoothing import SmoothingOptions
from ground.surface import Grid, clip_to_building, fill_empty, fit_heights
from ground.survey import DEFAULT_MAX_GRID_MEMORY_BYTES, ReportOptions, Survey

DEFAULT_BIN_M = 0.1
"""Floor bin side. Far finer than the 0.25 m volume grid, so the fitted surface keeps its shape (a
bin's mean point lies on a plane through its points, and a pile's curvature over 10 cm is
sub-millimetre), while a 3D LiDAR's tens of millions of points shrink to <= 240k bins over a
60 x 40 m floor: a Delaunay triangulation the surface fit handles in seconds."""


BIN_BYTES = 4 * 8 + 3 * 8
"""Memory per floor bin: the four accumulators, plus the bincount temporaries of one `add`."""

N_SIGMA_MANY = 6.0
"""Wall/roof tolerance in expected errors. The 1D's 3 sigma lets 0.27 % of structure points through;
of a 3D LiDAR's ~26 million wall and roof returns that is ~70,000 points at wall and roof heights,
and one roof point in a bin lifts its mean by metres. At 6 sigma a normal error escapes with
probability 2e-9: none of tens of millions. The cost: pile points within 6 sigma (18 cm for a 3 cm
sensor, beam along the normal) of a wall are dropped too, a strip the empty-cell fill covers."""


class HeightBinner:
    """Streaming reduction of a point cloud to per-bin mean points over the floor.

    Memory is fixed by the building and the bin size: four arrays of nx x ny (sums of x, y, z in
    float64, counts in int64), 7.7 MB for 600 x 400 bins, however many points stream through.
    """

    def __init__(self, storage: Storage, error_model: SensorErrorModel, bin_m: float = DEFAULT_BIN_M,
                 n_sigma: float = N_SIGMA_MANY, max_memory_bytes: int = DEFAULT_MAX_GRID_MEMORY_BYTES) -> None:
        if not (math.isfinite(bin_m) and 0.01 <= bin_m <= min(storage.length_m, storage.width_m)):
            raise ValueError(f"bin size must be between 0.01 m and the building's width, got {bin_m}")
        if not (math.isfinite(n_sigma) and n_sigma > 0):
            raise ValueError(f"n_sigma must be > 0, got {n_sigma}")
        self.storage = storage
        self.error_model = error_model
        self.n_sigma = float(n_sigma)
        s = self.n_sigma / N_SIGMA  # structure_mask's tolerance at n_sigma instead of its N_SIGMA
        self._mask_model = dataclasses.replace(error_model, range_sigma_m=s * error_model.range_sigma_m,
                                               range_sigma_rel=s * error_model.range_sigma_rel,
                                               position_sigma_m=s * error_model.position_sigma_m)
        self.bin_m = float(bin_m)
        self.shape = (max(1, round(storage.length_m / bin_m)), max(1, round(storage.width_m / bin_m)))
        n = self.shape[0] * self.shape[1]
        if n * BIN_BYTES > max_memory_bytes:  # a fine bin over a big floor: refuse, not MemoryError later
            raise ValueError(f"{n:,} bins of {bin_m:g} m over a {storage.length_m:g} x {storage.width_m:g} m floor "
                             f"need {n * BIN_BYTES / 2**20:,.0f} MiB, more than the {max_memory_bytes / 2**20:,.0f} "
                             "MiB allowed: use a larger bin size")
        self.sum_x = np.zeros(n)
        self.sum_y = np.zeros(n)
        self.sum_z = np.zeros(n)
        self.count = np.zeros(n, dtype=np.int64)
        self.n_in = 0
        self.n_removed = 0

    def add(self, points_w: np.ndarray, range_m: np.ndarray, dirs_w: np.ndarray | None = None) -> None:
        """Remove wall and roof points and accumulate the rest.

        dirs_w (N, 3), the unit beam directions, sharpen the tolerance (the range error projected on
        each plane's normal); without them every point gets the worst case, the whole range error.
        """
        p = np.asarray(points_w, dtype=float).reshape(-1, 3)
        r = np.asarray(range_m, dtype=float).reshape(-1)
        if len(r) != len(p):
            raise ValueError(f"{len(p)} points but {len(r)} ranges")
        d = np.broadcast_to(np.ones(3), p.shape) if dirs_w is None else np.asarray(dirs_w, dtype=float)
        if d.shape != p.shape:
            raise ValueError(f"{len(p)} points but directions of shape {d.shape}")
        keep = ~structure_mask(Cloud(p, d, r, np.empty((0, 3)), len(p), 0), self.storage, self._mask_model,
                               n_sigma=N_SIGMA)  # the model is already scaled to n_sigma
        keep &= np.isfinite(p).all(axis=1)
        self.n_in += len(p)
        self.n_removed += int(len(p) - keep.sum())
        q = p[keep]
        nx, ny = self.shape
        ix = np.clip((q[:, 0] * (nx / self.storage.length_m)).astype(np.int64), 0, nx - 1)
        iy = np.clip((q[:, 1] * (ny / self.storage.width_m)).astype(np.int64), 0, ny - 1)
        flat = ix * ny + iy
        n = nx * ny
        self.sum_x += np.bincount(flat, weights=q[:, 0], minlength=n)
        self.sum_y += np.bincount(flat, weights=q[:, 1], minlength=n)
        self.sum_z += np.bincount(flat, weights=q[:, 2], minlength=n)
        self.count += np.bincount(flat, minlength=n)

    @property
    def n_kept(self) -> int:
        return self.n_in - self.n_removed

    def occupied(self) -> np.ndarray:
        return self.count > 0

    def points(self) -> np.ndarray:
        """Mean point (M, 3) of each occupied bin, in bin order."""
        occ = self.occupied()
        c = self.count[occ]
        return np.column_stack([self.sum_x[occ] / c, self.sum_y[occ] / c, self.sum_z[occ] / c])

    def counts(self) -> np.ndarray:
        """Points (M,) behind each mean of `points()`."""
        return self.count[self.occupied()]


def survey_from_points(binner: HeightBinner, storage: Storage, opts: ReportOptions,
                       path_w: np.ndarray | None = None) -> Survey:
    """The surface and volume from the binned points, fitted as `survey_from_samples` fits a cloud.

    The Survey's cloud holds the bin means (the points the surface went through): they come from
    many beams each, so their directions and ranges are NaN; n_samples counts the points streamed
    in. path_w (optional) is the flown path for plots. `counts` are raw points per volume cell.
    """
    check_grid_memory(storage, opts.cell_m, opts.max_grid_memory_bytes)
    pile = binner.points()
    grid = Grid(storage.length_m, storage.width_m, opts.cell_m)
    fit, n_clipped = clip_to_building(fit_heights(pile, grid, opts.surface_fit,
                                                  smoothing=SmoothingOptions(limit=opts.surface_limit)),
                                      storage.height_m)
    counts, _, _ = np.histogram2d(pile[:, 0], pile[:, 1], bins=(grid.x_edges, grid.y_edges),
                                  weights=binner.counts())
    path = np.empty((0, 3)) if path_w is None else np.asarray(path_w, dtype=float).reshape(-1, 3)
    cloud = Cloud(pile, np.full(pile.shape, np.nan), np.full(len(pile), np.nan), path, binner.n_in, 0)
    heights = fill_empty(fit, opts.empty_cells, cell_xy_m=grid.cell_xy_m)
    return Survey(cloud, pile, grid, fit, heights, counts.astype(np.int64), storage, n_clipped)
