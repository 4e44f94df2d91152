"""What the flight says about the ground it could not reconstruct, and a fill bounded by it.

A cell outside the surface (outside the convex hull of the pile points, or emptied by
`surface.clip_to_building`) was not measured, but it was not unobserved either: every beam that
crossed above it on its way to a hit travelled through free space, so the surface there lies
below the beam. The lowest beam over a cell is therefore an upper bound on its height (the
*free-space ceiling*); the floor is the lower bound. Beams that hit a wall high up bound little,
beams that reached the floor beside a corner bound it to almost nothing. Ground no steeper than
MAX_SLOPE rises from a bound at most MAX_SLOPE times the distance, so the ceiling is carried from the
cells the beams crossed to those between them (`spread_down_slope`): a few diagonal beams low over an
unseen strip at a wall bound the whole strip, not only their own lines.

The `bounded` empty-cell policy carries the seen surface into the unseen cells (`BOUNDED_EXTENSION`:
the nearest seen cell's height, as `nearest` does) and holds it between the floor and the ceiling;
a smooth extension (harmonic membrane or thin plate: the obstacle problem, a sparse solve and an
active set) is available to `bounded_fill`, and docs/unseen.md measures all three. `unseen_bounds`
gives the per-cell bounds the fill respects, for the volume interval.

Margins come from the log header's sensor model (docs/design-notes.md, "Free-space ceiling"): a
beam's measured path is off its true one by the pose error and, growing along the beam, the
servo and attitude errors; its end is off by the range error. The ceiling is raised by k of
those sigmas (k from the number of beams, as the wall tolerance is) and the segment stops k range
sigmas short of the hit, so noise loosens the bound instead of cutting real material.
"""

from __future__ import annotations

import math
from enum import Enum
from typing import Protocol

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse.linalg import spsolve

from firmware_py.core.sensor_noise import stated_angle_sigma_rad
from firmware_py.core.storage import Storage
from ground.pointcloud import Cloud, SensorErrorModel, structure_n_sigma

MAX_SLOPE = 1.0
"""Steepest rise over run the ground may have between a beam and a cell centre (45 deg): above the
angle of repose of bulk materials (30-40 deg), so a beam crossing a cell off its centre still bounds the
centre. Vertical faces (a wall, a box) are steeper: that is what `--empty-cells nearest` is for."""
STEP_CELLS = 0.5
"""Beams are sampled every half cell along their horizontal track, so no crossed cell is skipped."""
BLOCK_CELLS = 8
"""Side of the blocks a beam is first walked through (coarse steps of half a block)."""
CHUNK_BEAMS = 20_000
"""Beams walked at once: bounds the memory of a whole-floor ceiling (a few hundred MB at most)."""
MAX_ACTIVE_SET_ROUNDS = 20
"""Rounds of the bounded fill's active set (each fixes the cells beyond a bound); it settles in 2-4."""


class GridLike(Protocol):
    """The grid's geometry (ground.surface.Grid; not imported: surface dispatches to this module)."""

    @property
    def shape(self) -> tuple[int, int]: ...

    @property
    def x_edges(self) -> np.ndarray: ...

    @property
    def y_edges(self) -> np.ndarray: ...


def beam_angle_sigma_rad(header: dict) -> float:
    """The beam's direction error, 1 sigma, that the header's ``sensor_noise`` record states (servo and
    attitude in quadrature; 0 without a record). The pose and range errors are in SensorErrorModel.
    A value that is not a number >= 0 gives infinity: the beams' paths are then unknown, and the ceiling
    falls back to the roof (bounds nothing) rather than cut material on a guess."""
    try:
        return stated_angle_sigma_rad(header)
    except ValueError:
        return math.inf


def free_space_ceiling_m(cloud: Cloud, grid: GridLike, storage: Storage, err: SensorErrorModel,
                         angle_sigma_rad: float = 0.0, n_sigma: float | None = None,
                         where: np.ndarray | None = None, spread: bool = True) -> np.ndarray:
    """The free-space ceiling (`free_space_ceilings_m`): carried at the slope (spread) or the beams' own bounds."""
    own, carried = free_space_ceilings_m(cloud, grid, storage, err, angle_sigma_rad, n_sigma, where, spread)
    return carried if spread else own


def free_space_ceilings_m(cloud: Cloud, grid: GridLike, storage: Storage, err: SensorErrorModel,
                          angle_sigma_rad: float = 0.0, n_sigma: float | None = None,
                          where: np.ndarray | None = None, spread: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Per cell, the lowest height any beam passed at over it, raised by the beams' error margins and
    by MAX_SLOPE times the distance from the beam to the cell centre: an upper bound on the surface at
    the cell centre, (nx, ny). That bound is then carried from cell to cell at MAX_SLOPE
    (`spread_down_slope`; `spread=False`: the beams' own bounds only), so a cell no beam crossed is bounded by
    the beams near it, and by the roof when none is; cells outside `where` (when given) are not computed (NaN)
    and carry no bound of their own to the others. Returns both, from one walk of the beams: (the beams' own
    bounds, the bounds carried; the same array twice when not spread). A cell whose own bound is under the roof
    is one a beam passed over (`ground.carry_down`: the shadows behind what the beams hit).

    Every usable sample's beam counts, the walls' and roof's included (a wall hit says the air before
    the wall was empty); only the free part of each beam, from the sensor to k range sigmas (and half
    the range resolution) short of the hit. Beams are walked coarse to fine: in steps of half a block of
    BLOCK_CELLS cells first, then in half cells only where a step lands within a block of a cell asked
    for, so bounding the unseen cells costs little more than the beams' count.
    """
    nx, ny = grid.shape
    ceiling = np.full(nx * ny, float(storage.height_m))
    want = np.ones((nx, ny), dtype=bool) if where is None else np.asarray(where, dtype=bool)
    if want.shape != (nx, ny):
        raise ValueError(f"where must have the grid's shape {(nx, ny)}, got {want.shape}")
    p, d, r = cloud.points_w, cloud.dirs_w, np.asarray(cloud.range_m, dtype=float)
    if len(r) and want.any() and math.isfinite(angle_sigma_rad):
        k = structure_n_sigma(len(r)) if n_sigma is None else n_sigma
        free = r - k * err.range_sigma(r) - 0.5 * err.resolution_m
        keep = np.isfinite(free) & (free > 0) & np.isfinite(p).all(axis=1) & np.isfinite(d).all(axis=1)
        p, d, r, free = p[keep], d[keep], r[keep], free[keep]
        origin = p - d * r[:, None]
        horiz = np.hypot(d[:, 0], d[:, 1])  # horizontal metres per metre of beam
        xe, ye = grid.x_edges, grid.y_edges
        cell_x, cell_y = (xe[-1] - xe[0]) / nx, (ye[-1] - ye[0]) / ny
        fine = STEP_CELLS * min(cell_x, cell_y)
        per = max(1, round(BLOCK_CELLS / 2 / STEP_CELLS))  # fine steps per coarse step (half a block)
        # Blocks holding a wanted cell, grown by one: a coarse step lands within half a block of its fine ones.
        bx, by = -(-nx // BLOCK_CELLS), -(-ny // BLOCK_CELLS)
        blocks = np.zeros((bx * BLOCK_CELLS, by * BLOCK_CELLS), dtype=bool)
        blocks[:nx, :ny] = want
        blocks = ndimage.binary_dilation(blocks.reshape(bx, BLOCK_CELLS, by, BLOCK_CELLS).any(axis=(1, 3)),
                                         structure=np.ones((3, 3), dtype=bool))
        reach = free * horiz  # horizontal length of the free part
        # Only beams whose track's bounding box holds a wanted block can bound a wanted cell (summed-area table).
        end = origin + d * free[:, None]
        nbx, nby = blocks.shape
        ax = np.clip(np.floor((np.minimum(origin[:, 0], end[:, 0]) - xe[0]) / (cell_x * BLOCK_CELLS)), 0, nbx - 1)
        bx1 = np.clip(np.floor((np.maximum(origin[:, 0], end[:, 0]) - xe[0]) / (cell_x * BLOCK_CELLS)), 0, nbx - 1)
        ay = np.clip(np.floor((np.minimum(origin[:, 1], end[:, 1]) - ye[0]) / (cell_y * BLOCK_CELLS)), 0, nby - 1)
        by1 = np.clip(np.floor((np.maximum(origin[:, 1], end[:, 1]) - ye[0]) / (cell_y * BLOCK_CELLS)), 0, nby - 1)
        ax, ay, bx1, by1 = ax.astype(np.int64), ay.astype(np.int64), bx1.astype(np.int64) + 1, by1.astype(np.int64) + 1
        table = np.pad(blocks.astype(np.int64).cumsum(axis=0).cumsum(axis=1), ((1, 0), (1, 0)))
        crosses = (table[bx1, by1] - table[ax, by1] - table[bx1, ay] + table[ax, ay]) > 0
        origin, d, free, horiz, reach = origin[crosses], d[crosses], free[crosses], horiz[crosses], reach[crosses]
        for lo in range(0, len(free), CHUNK_BEAMS):  # bounded memory: ~100 bytes a step of the chunk's beams
            c = slice(lo, lo + CHUNK_BEAMS)
            _lower(ceiling, origin[c], d[c], free[c], horiz[c], reach[c], want, blocks, (xe[0], ye[0], cell_x, cell_y),
                   fine, per, k * (1.0 + MAX_SLOPE), err.position_sigma_m, angle_sigma_rad)
    own = np.clip(ceiling, 0.0, storage.height_m).reshape(nx, ny)
    out = own.copy()
    if spread and want.any() and (out < storage.height_m).any():
        out = spread_down_slope(out, (grid.x_edges[-1] - grid.x_edges[0]) / nx,
                                (grid.y_edges[-1] - grid.y_edges[0]) / ny)
    own[~want] = np.nan
    out[~want] = np.nan
    return own, out if spread else own


def passed_over(own_m: np.ndarray, roof_m: float) -> np.ndarray:
    """The cells a beam passed over on its way to a hit beyond: those whose own bound (`free_space_ceilings_m`'s
    first array) is under the roof; a cell not computed (NaN) is none."""
    with np.errstate(invalid="ignore"):
        return np.asarray(own_m) < roof_m


SPREAD_RADIUS_CELLS = 2
"""`spread_down_slope` relaxes over the cells within this many of each other (a 5 x 5 neighbourhood): its path
lengths exceed the straight line by at most ~3 % (a 3 x 3 one's by 8 %), so the bound is barely loosened."""


def spread_down_slope(ceiling_m: np.ndarray, cell_x_m: float, cell_y_m: float,
                      max_slope: float = MAX_SLOPE) -> np.ndarray:
    """The ceiling carried to every cell from every other: min over cells A of ceiling(A) + max_slope * |A - cell|.

    A beam bounds only the thin line of cells it crossed, and an unseen strip along a wall is often crossed by a
    few diagonal beams only (a turn's sweeps, low at the wall). Ground no steeper than max_slope that lies under a
    beam at A lies under that height plus the slope times the distance anywhere else too, so the bound holds
    between the beams' lines (the paper's pile 2, a valley at a wall's unseen foot: the copied edge 2-3 m too high
    there, docs/design-notes.md). Exact on straight steps of the neighbourhood, a little loose between them: iterated
    grey erosions with the distances as the structuring element, until nothing moves."""
    off = np.arange(-SPREAD_RADIUS_CELLS, SPREAD_RADIUS_CELLS + 1)
    dx, dy = np.meshgrid(off * cell_x_m, off * cell_y_m, indexing="ij")
    step = max_slope * np.hypot(dx, dy)
    out = np.asarray(ceiling_m, dtype=float)
    for _ in range(out.size):  # each round carries the bound SPREAD_RADIUS_CELLS further; it settles long before
        nxt = np.minimum(out, ndimage.grey_erosion(out, structure=-step, mode="constant", cval=np.inf))
        if np.array_equal(nxt, out):
            break
        out = nxt
    return out


def _lower(ceiling: np.ndarray, origin: np.ndarray, d: np.ndarray, free: np.ndarray, horiz: np.ndarray,
           reach: np.ndarray, want: np.ndarray, blocks: np.ndarray, geometry: tuple[float, float, float, float],
           fine: float, per: int, margin_sigmas: float, position_sigma_m: float, angle_sigma_rad: float) -> None:
    """Lower the flat ceiling (nx * ny) to these beams' bounds (free_space_ceiling_m): coarse steps of
    `per` fine ones, kept near wanted blocks, refined, plus each beam's last free point."""
    nx, ny = want.shape
    x0, y0, cell_x, cell_y = geometry
    bx, by = blocks.shape
    coarse = per * fine
    n_coarse = np.floor(reach / coarse).astype(np.int64) + 1
    ray = np.repeat(np.arange(len(free)), n_coarse)
    u = (np.arange(len(ray)) - np.repeat(np.cumsum(n_coarse) - n_coarse, n_coarse)) * coarse
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(horiz[ray] > 0, u / horiz[ray], 0.0)
    cbx = np.floor((origin[ray, 0] + s * d[ray, 0] - x0) / (cell_x * BLOCK_CELLS)).astype(np.int64)
    cby = np.floor((origin[ray, 1] + s * d[ray, 1] - y0) / (cell_y * BLOCK_CELLS)).astype(np.int64)
    near = (cbx >= 0) & (cbx < bx) & (cby >= 0) & (cby < by)
    near[near] = blocks[cbx[near], cby[near]]
    ray = np.repeat(ray[near], per)
    u = (u[near][:, None] + np.arange(per) * fine).ravel()
    ok = u <= reach[ray]
    ray, u = ray[ok], u[ok]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(horiz[ray] > 0, u / horiz[ray], 0.0)
    ends = np.arange(len(free))  # each beam's last free point: its lowest for a descending beam
    ray, s = np.concatenate([ray, ends]), np.concatenate([s, free])
    x = origin[ray, 0] + s * d[ray, 0]
    y = origin[ray, 1] + s * d[ray, 1]
    ix = np.floor((x - x0) / cell_x).astype(np.int64)
    iy = np.floor((y - y0) / cell_y).astype(np.int64)
    inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    inside[inside] = want[ix[inside], iy[inside]]
    ray, s, x, y, ix, iy = ray[inside], s[inside], x[inside], y[inside], ix[inside], iy[inside]
    z = origin[ray, 2] + s * d[ray, 2]
    off_centre = np.hypot(x - (x0 + (ix + 0.5) * cell_x), y - (y0 + (iy + 0.5) * cell_y))
    sigma = np.hypot(position_sigma_m, s * angle_sigma_rad)  # how far the measured beam may be off
    np.minimum.at(ceiling, ix * ny + iy, z + margin_sigmas * sigma + MAX_SLOPE * off_centre)


def unseen_bounds(heights_fit: np.ndarray, ceiling_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-cell (lower, upper) heights the ground can have: the fitted surface where there is one (both
    bounds), the floor and the free-space ceiling where there is none. Summed times the cell area they
    bound the volume for what the fill had to invent (the fit's own error is not in them)."""
    seen = np.isfinite(heights_fit)
    lower = np.where(seen, heights_fit, 0.0)
    upper = np.where(seen, heights_fit, np.maximum(ceiling_m, 0.0))
    return lower, upper


class Extension(Enum):
    """How the seen surface is carried into the unseen cells: NEAREST copies the nearest seen cell's
    height (the `nearest` policy's guess, then held within the bounds); HARMONIC keeps the slope small
    (each cell the mean of its neighbours: flattens towards the mean of the edge); BIHARMONIC keeps the
    curvature small (a thin plate free at the walls: continues the edge's slope)."""

    NEAREST = "nearest"
    HARMONIC = "harmonic"
    BIHARMONIC = "biharmonic"


BOUNDED_EXTENSION = Extension.NEAREST
"""The `bounded` policy's extension, chosen by docs/unseen.md: in the unseen cells it is never worse than
`nearest` without noise and better with Appendix A's; the thin plate is best without noise (corner pile
at P_traj 30 %: 6.2 % of the volume wrong in the unseen cells against 11.8 %) but carries the noisy
edge's slope metres off (pile 2 at 30 %: 4.4 % against 1.2 %)."""


def upper_bound_m(ceiling_m: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray:
    """The ceiling as each cell's upper bound for a fill: never below the floor, and unbounded (infinity) where it was
    not computed (NaN) or where there is none (None)."""
    if ceiling_m is None:
        return np.full(shape, np.inf)
    upper = np.maximum(np.asarray(ceiling_m, dtype=float), 0.0)
    return np.where(np.isnan(upper), np.inf, upper)


def bounded_fill(heights: np.ndarray, ceiling_m: np.ndarray | None = None,
                 extension: Extension = BOUNDED_EXTENSION) -> np.ndarray:
    """The unseen (non-finite) cells filled by the extension (nearest copy, or the smoothest surface that
    meets the seen cells at their edge) and held within [0, ceiling] (module docstring); seen cells
    unchanged. Without a ceiling only the floor bounds it."""
    h = np.array(heights, dtype=float)
    empty = ~np.isfinite(h)
    if not empty.any() or empty.all():
        return h
    upper = upper_bound_m(ceiling_m, h.shape)
    lower = np.zeros(h.shape)
    if extension is Extension.NEAREST:
        _, (ix, iy) = ndimage.distance_transform_edt(empty, return_indices=True)
        h[empty] = np.clip(h[ix, iy][empty], lower[empty], upper[empty])
        return h
    solve = _harmonic if extension is Extension.HARMONIC else _biharmonic
    fixed = np.zeros(h.shape)  # value of cells held at a bound
    held = np.zeros(h.shape, dtype=bool)
    for _ in range(MAX_ACTIVE_SET_ROUNDS):
        free = empty & ~held
        if not free.any():
            break
        known = np.where(empty, fixed, h)
        sol = solve(known, free)
        over, under = free & (sol > upper), free & (sol < lower)
        if not (over.any() or under.any()):
            h[free] = sol[free]
            break
        fixed[over], fixed[under] = upper[over], lower[under]
        held |= over | under
    else:  # did not settle: what is left takes its clamped value
        free = empty & ~held
        if free.any():
            sol = solve(np.where(empty, fixed, h), free)
            h[free] = np.clip(sol[free], lower[free], upper[free])
    h[held] = fixed[held]
    return h


def _thin_plate(shape: tuple[int, int]) -> sparse.csr_matrix:
    """Rows whose squares sum to the discrete thin-plate energy h_xx^2 + 2 h_xy^2 + h_yy^2, each taken only
    where its stencil lies inside the walls (a free edge: any plane costs nothing, so a slope carries on
    to the wall)."""
    nx, ny = shape
    idx = np.arange(nx * ny).reshape(shape)
    parts = []
    for cells, coef in (((idx[:-2, :], idx[1:-1, :], idx[2:, :]), (1.0, -2.0, 1.0)),
                        ((idx[:, :-2], idx[:, 1:-1], idx[:, 2:]), (1.0, -2.0, 1.0)),
                        ((idx[:-1, :-1], idx[1:, :-1], idx[:-1, 1:], idx[1:, 1:]),
                         tuple(math.sqrt(2.0) * c for c in (1.0, -1.0, -1.0, 1.0)))):
        n = cells[0].size
        rows = np.tile(np.arange(n), len(cells))
        cols = np.concatenate([c.ravel() for c in cells])
        vals = np.repeat(np.asarray(coef), n)
        parts.append(sparse.csr_matrix((vals, (rows, cols)), shape=(n, nx * ny)))
    return sparse.vstack(parts).tocsr()


def _biharmonic(known: np.ndarray, free: np.ndarray) -> np.ndarray:
    """Values on the free cells minimising the thin-plate energy of every stencil that touches one, the
    other cells held at `known`."""
    out = np.array(known, dtype=float)
    plate = _thin_plate(free.shape)
    f = free.ravel()
    rows = plate[np.asarray(plate[:, f].getnnz(axis=1) > 0).ravel()]
    pf, pk = rows[:, f], rows[:, ~f]
    out[free] = spsolve((pf.T @ pf).tocsc(), -(pf.T @ (pk @ out.ravel()[~f])))
    return out


def _harmonic(known: np.ndarray, free: np.ndarray) -> np.ndarray:
    """Values on the free cells such that each is the mean of its in-grid 4-neighbours (the building's
    walls reflect: no neighbour beyond them), the other cells held at `known`. Every region of free cells touches a held
    one (a region bounded by walls alone would be the whole floor, which `bounded_fill` leaves empty), so
    the system is regular."""
    out = np.array(known, dtype=float)
    nx, ny = free.shape
    idx = -np.ones(free.shape, dtype=np.int64)
    n = int(free.sum())
    idx[free] = np.arange(n)
    rows, cols, vals = [np.arange(n)], [np.arange(n)], []
    deg = np.zeros(n)
    rhs = np.zeros(n)
    fi, fj = np.nonzero(free)
    for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        ni, nj = fi + di, fj + dj
        ok = (ni >= 0) & (ni < nx) & (nj >= 0) & (nj < ny)
        a, ni, nj = np.nonzero(ok)[0], ni[ok], nj[ok]
        deg[a] += 1.0
        nb = idx[ni, nj]
        to_free = nb >= 0
        rows.append(a[to_free])
        cols.append(nb[to_free])
        vals.append(-np.ones(int(to_free.sum())))
        np.add.at(rhs, a[~to_free], known[ni[~to_free], nj[~to_free]])
    a = sparse.csr_matrix((np.concatenate([deg, *vals]), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(n, n))
    out[free] = spsolve(a.tocsc(), rhs)
    return out
